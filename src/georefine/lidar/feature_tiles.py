"""Planar features in ground tiles: extracted to disk, matched tile by tile (docs/ARCHITECTURE.md §4.7).

An hour of corridor has millions of planar features, of which the balancing keeps a fraction.
Holding them all to match them made memory grow with the flight's length. Here the features
stream from the extraction tasks into a :class:`FeatureStore`, files of one ground tile each
(square tiles of ``tile_m`` in ``w``, a whole number of balancing cells), and each tile is then
matched on its own (:func:`match_tile`, one task per tile): memory holds a tile and its margin,
and the matched features that the adjustment takes.

**The same objects as the whole flight's matching.**
:func:`~georefine.lidar.correspondences.match_features` decides every object from the connected
component of accepted pairs it belongs to (rules 1-6 of :mod:`georefine.lidar.correspondences`,
ties broken by the features' order) and balances each cell of ``balance_cell_m`` alone (rule 7).
A tile is matched with the features within ``margin`` of it, kept in the whole flight's order
(strip, channel, time, then the order they came in). Only the features within
``max_centre_distance_m`` of the margin's edge can pair with one beyond it; from them
:func:`~georefine.lidar.correspondences.group_features` bounds which features' groups the
features beyond could change (the anti-chaining split decides a feature from those within 3 hops
per round, so a road chained over kilometres is decided locally) and calls the others settled.
An object of the tile's own cells has every member within ``2 max_object_radius_m`` of them; when
one of those is not settled the margin widens (to what the split's rounds need, :func:`margin_for`)
and the tile is matched again. The tile keeps the objects whose centre ``c0`` lies in its own
balancing cells; the tiles' objects, put back into the flight's order, are those of the whole
flight's matching, with the same frames to the last bit (the sums run over the same members in
the same order; ``tests/test_feature_tiles.py``). The first margin (:data:`TYPICAL_ROUNDS`)
settles the tiles of a 10-minute corridor at once: matching in tiles of 200 m takes 1.6 times
the whole flight's matching in one process (the margins are matched twice), and runs as tasks.

Only the matched features leave the tiles: a feature no object took is used nowhere after
matching. The store also keeps a bounded sample of the features (:class:`SearchSample`) for the
time offset search, which scores a sample of them anyway.

Written by hand: the spill files are numpy records (``ndarray.tofile``), the tiles' tasks run on
the :class:`~georefine.tasks.TaskRunner`.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from georefine.config import MatchingConfig
from georefine.lidar.correspondences import PlanarObjects, balanced, group_features, objects_from_groups
from georefine.lidar.feature_sample import feature_keys
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.time_offset import MAX_POOL, MIN_TILTED, tilted
from georefine.progress import no_progress
from georefine.tasks import TaskRunner

__all__ = ["SEARCH_SAMPLE", "TYPICAL_ROUNDS", "FeatureStore", "SearchSample", "TiledFeatures", "margin_for",
           "match_store", "match_tile", "read_rect", "tile_size"]

log = logging.getLogger(__name__)

_EPS_M = 1e-6

_VEC = ("centre_s", "axis1_s", "axis2_s", "normal_s", "centre_w", "normal_w")
_TYPES = {"strip": np.int32, "channel": np.int16, "n_points": np.int32}


def _record_dtype() -> np.dtype:
    cols = []
    for f in fields(PlanarFeatures):
        if f.name in _VEC:
            cols.append((f.name, np.float64, (3,)))
        elif f.name == "seed_cell":
            cols.append((f.name, np.int64, (3,)))
        else:
            cols.append((f.name, _TYPES.get(f.name, np.float64)))
    return np.dtype([*cols, ("arrival", np.int64)])


RECORD = _record_dtype()


def tile_size(tile_m: float, cfg: MatchingConfig) -> float:
    """``tile_m`` rounded to a whole number (at least one) of balancing cells: a cell never spans two tiles."""
    return cfg.balance_cell_m * max(1, round(tile_m / cfg.balance_cell_m))


def _sort_key(f: PlanarFeatures, arrival: np.ndarray) -> np.ndarray:
    """The whole flight's order: strip, channel, time (``sort_features``), then arrival."""
    return np.lexsort((arrival, f.time, f.channel, f.strip))


def _to_records(f: PlanarFeatures, arrival: np.ndarray) -> np.ndarray:
    rec = np.empty(len(f), RECORD)
    for fld in fields(PlanarFeatures):
        rec[fld.name] = getattr(f, fld.name)
    rec["arrival"] = arrival
    return rec


def _from_records(rec: np.ndarray) -> tuple[PlanarFeatures, np.ndarray]:
    return PlanarFeatures(**{f.name: rec[f.name] for f in fields(PlanarFeatures)}), np.asarray(rec["arrival"])


SEARCH_SAMPLE = 5 * MAX_POOL
"""Features of a :class:`SearchSample`: the time offset search's fine pool, which it draws from all features."""


class SearchSample:
    """The features of smallest key (:func:`~georefine.lidar.feature_sample.feature_keys`), at most
    ``size`` of the tilted ones (:func:`~georefine.lidar.time_offset.tilted`) and ``size`` of all: a
    bottom-k sample, the same whatever the order the features came in, for the time offset search
    (its pool, :mod:`georefine.lidar.time_offset`)."""

    def __init__(self, size: int = SEARCH_SAMPLE):
        self.size = int(size)
        self._parts: dict[bool, list[tuple[np.ndarray, PlanarFeatures, np.ndarray]]] = {True: [], False: []}
        self.tilted = 0

    def add(self, f: PlanarFeatures, arrival: np.ndarray) -> None:
        on_tilted = tilted(f)
        self.tilted += int(on_tilted.sum())
        keys = feature_keys(f)
        for kind, mask in ((True, on_tilted), (False, np.ones(len(f), bool))):
            idx = np.flatnonzero(mask)
            self._parts[kind].append((keys[idx], f.select(idx), arrival[idx]))
            self._trim(kind)

    def _trim(self, kind: bool) -> None:
        parts = self._parts[kind]
        if sum(k.size for k, _, _ in parts) <= 2 * self.size:
            return
        keys = np.concatenate([k for k, _, _ in parts])
        feats = PlanarFeatures.concatenate([f for _, f, _ in parts])
        arrival = np.concatenate([a for _, _, a in parts])
        keep = np.argsort(keys, kind="stable")[:self.size]
        self._parts[kind] = [(keys[keep], feats.select(keep), arrival[keep])]

    def features(self) -> PlanarFeatures:
        """The tilted sample when the flight has :data:`~georefine.lidar.time_offset.MIN_TILTED` tilted
        features, else the sample of all, in the flight's order."""
        parts = self._parts[self.tilted >= MIN_TILTED]
        if not parts:
            return PlanarFeatures.empty()
        keys = np.concatenate([k for k, _, _ in parts])
        feats = PlanarFeatures.concatenate([f for _, f, _ in parts])
        arrival = np.concatenate([a for _, _, a in parts])
        keep = np.sort(np.argsort(keys, kind="stable")[:self.size])
        feats, arrival = feats.select(keep), arrival[keep]
        return feats.select(_sort_key(feats, arrival))


class FeatureStore:
    """Planar features on disk, one file of records per ground tile of ``tile_m`` (a context manager
    that removes its files). They go to a new folder in ``parent`` (default the system's temporary
    folder); the tiles' tasks read them, so on a cluster ``parent`` must be one the workers see."""

    def __init__(self, tile_m: float, parent: Path | None = None, sample_size: int = SEARCH_SAMPLE):
        self.tile_m = float(tile_m)
        self.parent = parent
        if parent is not None:
            Path(parent).mkdir(parents=True, exist_ok=True)
        self.folder = Path(tempfile.mkdtemp(prefix="georefine-features-", dir=parent))
        self.count = 0
        self.per_tile: dict[tuple[int, int], int] = {}
        self.sample = SearchSample(sample_size)

    def __enter__(self) -> FeatureStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Remove the tiles' files and their folder."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def add(self, f: PlanarFeatures, arrival: np.ndarray | None = None) -> None:
        """Append features (one extraction task's) to their tiles, numbered in the order they come
        (or by ``arrival``, numbers another store gave them)."""
        if len(f) == 0:
            return
        if arrival is None:
            arrival = self.count + np.arange(len(f), dtype=np.int64)
        self.count += len(f)
        self.sample.add(f, arrival)
        ij = np.floor(f.centre_w[:, :2] / self.tile_m).astype(np.int64)
        rec = _to_records(f, arrival)
        order = np.lexsort((ij[:, 1], ij[:, 0]))
        ij, rec = ij[order], rec[order]
        start = np.flatnonzero(np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)])
        for a, b in zip(start, np.r_[start[1:], len(rec)]):
            key = (int(ij[a, 0]), int(ij[a, 1]))
            with open(self.folder / _tile_name(key), "ab") as out:
                rec[a:b].tofile(out)
            self.per_tile[key] = self.per_tile.get(key, 0) + int(b - a)

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """The tiles holding features, in order."""
        return sorted(self.per_tile)

    def extent(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the tiles holding features (m, ``w``)."""
        ij = np.array(self.tiles)
        return (float(ij[:, 0].min() * self.tile_m), float(ij[:, 1].min() * self.tile_m),
                float((ij[:, 0].max() + 1) * self.tile_m), float((ij[:, 1].max() + 1) * self.tile_m))

    def read_tile(self, ij: tuple[int, int]) -> tuple[PlanarFeatures, np.ndarray]:
        """The features of tile ``ij`` (as stored) and their arrival numbers."""
        return _from_records(np.fromfile(self.folder / _tile_name(ij), RECORD))

    def transformed(self, fn) -> FeatureStore:
        """A new store (same tiles' size, folder's parent and sample size) of every tile's features
        passed through ``fn(features, arrival) -> (features, arrival)``; this store is closed, and
        the new one too if ``fn`` fails."""
        out = FeatureStore(self.tile_m, self.parent, self.sample.size)
        try:
            for ij in self.tiles:
                out.add(*fn(*self.read_tile(ij)))
        except BaseException:
            out.close()
            raise
        finally:
            self.close()
        return out

    def read_all(self) -> tuple[PlanarFeatures, np.ndarray]:
        """Every feature, in the flight's order (tests, and small flights)."""
        return read_rect(self.folder, self.tile_m, self.extent())


def _tile_name(ij: tuple[int, int]) -> str:
    return f"tile_{ij[0]}_{ij[1]}.rec"


def read_rect(folder: Path, tile_m: float, rect: tuple[float, float, float, float]
              ) -> tuple[PlanarFeatures, np.ndarray]:
    """The features whose centre lies in ``rect`` = (x0, y0, x1, y1) (m, half-open), in the flight's
    order, and their arrival numbers."""
    x0, y0, x1, y1 = rect
    parts = []
    for i in range(int(np.floor(x0 / tile_m)), int(np.floor(x1 / tile_m)) + 1):
        for j in range(int(np.floor(y0 / tile_m)), int(np.floor(y1 / tile_m)) + 1):
            path = Path(folder) / _tile_name((i, j))
            if path.exists():
                rec = np.fromfile(path, RECORD)
                xy = rec["centre_w"][:, :2]
                parts.append(rec[(xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)])
    rec = np.concatenate(parts) if parts else np.empty(0, RECORD)
    f, arrival = _from_records(rec)
    order = _sort_key(f, arrival)
    return f.select(order), arrival[order]


TYPICAL_ROUNDS = 5
"""Rounds of the anti-chaining split that the first margin allows for: its priorities (degree, then
``sigma_d_m``) behave like random ones, whose rounds grow with the logarithm of a component's size;
a 10-minute corridor's tiles take 5."""


def margin_for(rounds: int, cfg: MatchingConfig) -> float:
    """The margin (m) that settles a tile's objects when the split takes ``rounds`` rounds: unsure
    features lie within ``max_centre_distance_m`` ``d`` of the margin's edge, or in small components
    that touch that band (within ``d + 2 r sqrt 3``, ``r = max_object_radius_m``); the unsure reach
    ``3 K + 3`` hops of at most ``d`` further
    (:func:`~georefine.lidar.correspondences.group_features`), and an object of the tile has its
    members within ``2 r`` of it."""
    d, r = cfg.max_centre_distance_m, cfg.max_object_radius_m
    return (3 * rounds + 4) * d + 2.0 * r * np.sqrt(3.0) + 2.0 * r + 1.0


@dataclass(frozen=True)
class TileObjects:
    """One tile's objects: their member features (flight's order), arrival numbers, and object of each (0..)."""

    features: PlanarFeatures
    arrival: np.ndarray
    group: np.ndarray
    grown: int  # times the margin was doubled


def match_tile(folder: Path, tile_m: float, tile: tuple[int, int], extent: tuple[float, float, float, float],
               cfg: MatchingConfig, margin_m: float | None = None) -> TileObjects:
    """The objects whose centre lies in ``tile``'s own balancing cells, as the whole flight's matching
    makes them (module docstring); ``extent`` bounds the store's features (the margin grows to it at most).
    ``margin_m``: the first margin, default :func:`margin_for` :data:`TYPICAL_ROUNDS`; it widens
    while features within ``2 max_object_radius_m`` of the tile are not settled."""
    x0, y0 = tile[0] * tile_m, tile[1] * tile_m
    x1, y1 = x0 + tile_m, y0 + tile_m
    d, r = cfg.max_centre_distance_m, cfg.max_object_radius_m
    margin, grown = (margin_for(TYPICAL_ROUNDS, cfg) if margin_m is None else float(margin_m)), 0
    cells_per_tile = round(tile_m / cfg.balance_cell_m)
    while True:
        rect = (x0 - margin, y0 - margin, x1 + margin, y1 + margin)
        whole = rect[0] <= extent[0] and rect[1] <= extent[1] and rect[2] >= extent[2] and rect[3] >= extent[3]
        f, arrival = read_rect(folder, tile_m, rect)
        if len(f) == 0:
            return TileObjects(PlanarFeatures.empty(), np.zeros(0, np.int64), np.zeros(0, np.int64), grown)
        xy = f.centre_w[:, :2]
        inner = d + _EPS_M  # a feature this near the margin's edge may pair with one beyond it
        open_ = None if whole else ((xy[:, 0] <= rect[0] + inner) | (xy[:, 0] >= rect[2] - inner)
                                    | (xy[:, 1] <= rect[1] + inner) | (xy[:, 1] >= rect[3] - inner))
        grouping = group_features(f, cfg, open_)
        group = grouping.group
        if not whole:
            # An object of the tile's cells has every member within 2 r of its c0 (the members
            # before the member check lie within 2 r of each other), so those must be settled.
            reach = 2.0 * r + _EPS_M
            near = ((xy[:, 0] >= x0 - reach) & (xy[:, 0] < x1 + reach)
                    & (xy[:, 1] >= y0 - reach) & (xy[:, 1] < y1 + reach))
            if not np.all(grouping.settled[near]):
                margin = max(2.0 * margin, margin_for(grouping.rounds, cfg))
                grown += 1
                continue
        objects = objects_from_groups(f, group, cfg)
        keep = balanced(objects, f, cfg)
        cell = np.floor(objects.c0[:, :2] / cfg.balance_cell_m).astype(np.int64)
        own = np.all(np.floor_divide(cell, cells_per_tile) == np.asarray(tile, np.int64), axis=1)
        keep &= own
        g = objects.feature_object
        member = g >= 0
        member[member] = keep[g[member]]
        local = np.full(len(objects), -1, np.int64)
        local[keep] = np.arange(int(keep.sum()))
        sel = np.flatnonzero(member)
        if grown:
            log.debug("ground tile %s matched with a %.0f m margin after %d narrower ones left features near it "
                      "unsettled", tile, margin, grown)
        return TileObjects(f.select(sel), arrival[sel], local[g[sel]], grown)


@dataclass(frozen=True)
class TiledFeatures:
    """The matched features of a flight (flight's order) and their objects; ``extracted`` counts all."""

    features: PlanarFeatures
    objects: PlanarObjects
    extracted: int
    tiles: int
    grown: int


def match_store(store: FeatureStore, cfg: MatchingConfig, runner=None, progress=None,
                margin_m: float | None = None) -> TiledFeatures:
    """Every tile of ``store`` matched (:func:`match_tile`, one task each on ``runner``); the objects
    and their features as :func:`~georefine.lidar.correspondences.match_features` gives them for the
    matched features of the whole flight."""
    runner = runner or TaskRunner("sync")
    tiles = store.tiles
    if not tiles:
        return TiledFeatures(PlanarFeatures.empty(), objects_from_groups(PlanarFeatures.empty(), np.zeros(0, np.int64),
                                                                          cfg), store.count, 0, 0)
    extent = store.extent()
    tasks = [(store.folder, store.tile_m, t, extent, cfg, margin_m) for t in tiles]
    parts, arrivals, groups, offset, grown = [], [], [], 0, 0
    for r in runner.map(match_tile, tasks, label="matching planar features", progress=progress or no_progress):
        parts.append(r.features)
        arrivals.append(r.arrival)
        groups.append(np.where(r.group >= 0, r.group + offset, -1))
        offset += int(r.group.max(initial=-1)) + 1
        grown += r.grown
    f = PlanarFeatures.concatenate(parts)
    arrival, group = np.concatenate(arrivals), np.concatenate(groups)
    order = _sort_key(f, arrival)
    f, group = f.select(order), group[order]
    objects = objects_from_groups(f, group, cfg)
    log.info("matched %d of %d features into %d planar objects (%d vertical) in %d ground tiles of %.0f m%s",
             len(f), store.count, len(objects), int(objects.is_vertical.sum()), len(tiles), store.tile_m,
             f" ({grown} matched again with a wider margin)" if grown else "")
    return TiledFeatures(f, objects, store.count, len(tiles), grown)
