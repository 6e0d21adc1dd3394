"""Multi-view line scanner modelled on the RIEGL VUX-160 (paper 000 §2, Fig. 2).

Scan mechanism
--------------
A polygon mirror with three facets rotates continuously; each facet sweeps one scan line
over 120 degrees of scan angle, of which the central ``field_of_view_deg`` (default 100)
is used. The facets are tilted differently, so consecutive lines cycle through the views
nadir (channel 0), forward (channel 1, ``+10`` deg) and backward (channel 2, ``-10`` deg)
(``facet_tilt_deg``). Pulses are emitted at a constant ``pulse_rate_hz``; the pulse clock
and the mirror phase are anchored at the dataset epoch ``t = 0``: pulse ``k`` is emitted at
``t_k = k / pulse_rate_hz``, it belongs to line ``l = floor(t_k line_rate_hz)`` of channel
``l mod 3``, and its scan angle is ``alpha = (frac(t_k line_rate_hz) - 1/2) 120 deg``
(sweeping from left to right).

Scanner frame ``s`` (SOCS)
--------------------------
Nominally aligned with the body frame ``b``: x forward, y right, z down, origin at the
mirror centre. The beam of facet tilt ``tau`` at scan angle ``alpha`` is
``d_s = [sin(tau), cos(tau) sin(alpha), cos(tau) cos(alpha)]``: ``alpha = 0`` in the
vertical plane containing x, positive to the right; ``tau > 0`` looks forward.
The caller gives the mounting: lever arm ``p_b_s`` [m] and boresight ``R_b_s``, so
``p_w_s = p_w_b + R_w_b p_b_s`` and ``R_w_s = R_w_b R_b_s``.

Measurement model
-----------------
First return only. The true range ``r`` is the distance from ``p_w_s`` along
``R_w_s d_s`` to the first surface of the scene; the recorded point is
``xyz_s = ((1 + k) r + r0 + b_inc + b_int + e) d_s(alpha_rec, tau_c)`` with
``e ~ N(0, range_sigma_m^2)``. Intensity follows the scene albedo ``rho``, the incidence angle
``theta`` and the range: ``I = I_0 (1 + sigma_rel n)``, clipped to 1..65535, with the noise-free
amplitude ``I_0 = I_ref rho cos(theta) (r_ref / r)^2``.

Errors of the unit (every one 0 by default, i.e. an ideal, calibrated scanner; the beam really goes
where they send it and the range really is read as they say, while the recorded scan angle and channel
are the nominal ones, so a georeferencing with the nominal model is off by exactly these errors):

* range scale error ``k`` (``range_scale_ppm``) and offset ``r0`` (``range_offset_m``); real units keep
  centimetres and tens of ppm.
* incidence-angle range bias: at grazing incidence the return's centroid moves to the far part of the
  footprint, ``b_inc = range_incidence_bias_m (1 / cos(theta) - 1)`` (``theta`` clipped at
  ``MAX_INCIDENCE_DEG`` = 80 deg): 0 at normal incidence, ``0.41 range_incidence_bias_m`` at 45 deg.
* intensity-dependent range bias ("range walk"): weak and strong returns are timed differently,
  ``b_int = range_walk_m ln(I_ref / I_0)`` with the noise-free amplitude ``I_0`` clipped to 1..65535 like
  the recorded intensity: 0 at the reference amplitude, positive for weaker returns; a deterministic
  function of the geometry and the reflectance.
* per-channel angles: the beam leaves at the channel's true angles ``d_s(alpha + d_alpha_c, tau_c + d_tau_c)``
  while the point is recorded along ``d_s(alpha, tau_c)``: each facet's tilt and its scan angle (its angle
  on the mirror wheel and the encoder's offset) as far off as ``channel_tilt_error_mdeg`` and
  ``channel_scan_angle_error_mdeg`` say (a few mdeg remain after a calibration).
* the scan-angle encoder's periodic error, a function of the polygon's angle ``alpha`` (from the facet's
  centre; the scan angle turns at the polygon's rate, so ``alpha`` is the recorded scan angle and the
  error is the same on every facet): ``e_enc(alpha) = sum_k a_k sin(k alpha + phi_k)``, ``k = 1, 2``
  (``encoder_error_mdeg``, ``encoder_error_phase_deg``); the beam leaves at ``alpha + e_enc(alpha)``
  (plus ``d_alpha_c``). With ``encoder_resolution_mdeg`` the recorded angle is ``alpha`` rounded to that
  step, ``alpha_rec = q round(alpha / q)``, otherwise ``alpha_rec = alpha``.

``range_error_m`` of each point is its whole range error ``k r + r0 + b_inc + b_int + e``, the truth of the
range errors; the angle errors are in the :class:`ScannerConfig` (written with the scenario's truth).
The time of flight (~1 µs at 160 m, i.e. ~20 µm of platform motion) and the beam divergence are
neglected: each point carries its pulse emission time and the pose at that time. Returns beyond
``max_range_m`` and misses are dropped.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from georefine.sim.scene import Scene

if TYPE_CHECKING:
    from georefine.tasks import TaskRunner

log = logging.getLogger(__name__)

__all__ = [
    "ScannerConfig", "ScanChunk", "scan", "scan_span", "chunk_seed", "beam_directions_s", "encoder_error_rad",
    "N_FACETS", "FACET_SWEEP_RAD", "MAX_INCIDENCE_DEG",
]

N_FACETS = 3
FACET_SWEEP_RAD = 2 * np.pi / N_FACETS  #: scan angle swept by one facet (120 deg)
MAX_INCIDENCE_DEG = 80.0  #: incidence angle at which the incidence range bias stops growing


class ScannerConfig(BaseModel):
    """Scanner parameters (VUX-160-like; defaults for the ``corridor`` scenario).

    With the defaults at 160 m above ground and 18 m/s, each view gets
    ``pulse_rate / (2 pi v h) ~ 11`` points/m² at nadir (~4.5 at the swath edge, 8 on
    average; the paper's 1.8 MHz gives 50/m² per view), and the line rate makes the
    along-track spacing of a view (``3 v / line_rate = 0.30 m``) equal to the nadir
    across-track spacing (``h 120 deg line_rate / pulse_rate = 0.30 m``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    pulse_rate_hz: float = Field(200_000.0, gt=0, le=5e6, description="laser pulse repetition rate")
    line_rate_hz: float = Field(180.0, gt=0, description="scan lines per second, all channels")
    facet_tilt_deg: tuple[float, float, float] = Field(
        (0.0, 10.0, -10.0), description="tilt of channels 0 (nadir), 1 (forward), 2 (backward)")
    field_of_view_deg: float = Field(100.0, gt=0, le=120, description="used part of each line")
    range_sigma_m: float = Field(
        0.005, ge=0, description="1-sigma range noise; VUX-160 datasheet precision 5 mm")
    max_range_m: float = Field(1000.0, gt=0, description="returns beyond are dropped")
    range_offset_m: float = Field(0.0, ge=-1.0, le=1.0, description="the unit's range offset r0 (m)")
    range_scale_ppm: float = Field(0.0, ge=-10000.0, le=10000.0, description="the unit's range scale error k (ppm)")
    channel_tilt_error_mdeg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="per channel, the true facet tilt minus the unit's calibrated one (mdeg)")
    channel_scan_angle_error_mdeg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="per channel, the true scan angle minus the one the unit records (mdeg): "
        "the facet's angle on the mirror wheel and its encoder offset")
    encoder_error_mdeg: tuple[float, float] = Field(
        (0.0, 0.0), description="the scan-angle encoder's periodic error, amplitudes a_1, a_2 of its first and second "
        "harmonic in the polygon angle (mdeg): the beam leaves at alpha + sum_k a_k sin(k alpha + phi_k)")
    encoder_error_phase_deg: tuple[float, float] = Field(
        (0.0, 0.0), description="phases phi_1, phi_2 of the encoder error's harmonics (deg)")
    encoder_resolution_mdeg: float = Field(
        0.0, ge=0.0, le=1000.0, description="the encoder's step: the recorded scan angle is rounded to it (mdeg; 0: off)")
    range_incidence_bias_m: float = Field(
        0.0, ge=-1.0, le=1.0, description="range bias at grazing incidence, b = this (1/cos(theta) - 1), theta the "
        f"incidence angle clipped at {MAX_INCIDENCE_DEG:g} deg (m)")
    range_walk_m: float = Field(
        0.0, ge=-1.0, le=1.0, description="intensity-dependent range bias, b = this ln(I_ref / I) with I the "
        "noise-free return amplitude (1..65535) and I_ref intensity_at_reference (m)")
    intensity_at_reference: float = Field(
        60000.0, gt=0, description="albedo 1, normal incidence, at the reference range")
    intensity_reference_range_m: float = Field(100.0, gt=0)
    intensity_noise_rel: float = Field(0.03, ge=0, description="relative 1-sigma intensity noise")

    @model_validator(mode="after")
    def _check(self) -> "ScannerConfig":
        if self.pulse_rate_hz / self.line_rate_hz < 10:
            raise ValueError("pulse_rate_hz / line_rate_hz must be >= 10 pulses per line")
        return self


@dataclass(frozen=True, eq=False)
class ScanChunk:
    """Returns of the pulses emitted in one time chunk, ordered by time.

    Attributes
    ----------
    time : ndarray (N,) float64
        Pulse emission time [s] relative to the dataset epoch.
    xyz_s : ndarray (N, 3)
        Measured point in the scanner frame ``s`` [m] (true range + noise along the beam).
    channel : ndarray (N,) uint8
        View: 0 nadir, 1 forward, 2 backward.
    scan_angle_rad : ndarray (N,)
        Scan angle [rad] within the line as recorded: the polygon angle ``alpha``, rounded to
        ``encoder_resolution_mdeg`` where set (the beam left at ``alpha + e_enc(alpha)`` plus the channel's error).
    intensity : ndarray (N,) uint16
    range_error_m : ndarray (N,)
        The simulated range error ``k r + r0 + b_inc + b_int + e`` [m] (noise, and scale, offset, incidence
        and intensity biases where set).
    face_id : ndarray (N,) int64
        Scene face hit.
    xyz_w_true : ndarray (N, 3)
        Noiseless hit point in ``w`` [m].
    beam_w : ndarray (N, 3)
        Unit beam direction in ``w``; the measured point in ``w`` is
        ``xyz_w_true + range_error_m * beam_w``.
    forward_w : ndarray (N, 3)
        The body's x axis (forward) in ``w`` at the pulse time (for the LAS scan angle of the
        georeferenced truth, :func:`georefine.lidar.georeference.scan_angles_deg`).
    pulses : int
        Pulses emitted in the chunk's field of view (returns and misses).
    """

    time: np.ndarray
    xyz_s: np.ndarray
    channel: np.ndarray
    scan_angle_rad: np.ndarray
    intensity: np.ndarray
    range_error_m: np.ndarray
    face_id: np.ndarray
    xyz_w_true: np.ndarray
    beam_w: np.ndarray
    forward_w: np.ndarray
    pulses: int = 0

    def __post_init__(self):
        n = len(self.time)
        for name in ("channel", "scan_angle_rad", "intensity", "range_error_m", "face_id"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"ScanChunk.{name} must have shape ({n},)")
        for name in ("xyz_s", "xyz_w_true", "beam_w", "forward_w"):
            if getattr(self, name).shape != (n, 3):
                raise ValueError(f"ScanChunk.{name} must have shape ({n}, 3)")

    def __len__(self) -> int:
        return len(self.time)


def encoder_error_rad(scan_angle_rad: np.ndarray, cfg: ScannerConfig) -> np.ndarray:
    """The encoder's periodic error ``e_enc(alpha) = sum_k a_k sin(k alpha + phi_k)`` [rad] at polygon (scan)
    angles ``alpha`` [rad]: the beam leaves at ``alpha + e_enc(alpha)`` (``encoder_error_mdeg``, ``..._phase_deg``)."""
    alpha = np.asarray(scan_angle_rad, np.float64)
    e = np.zeros_like(alpha)
    for k, (a, phi) in enumerate(zip(cfg.encoder_error_mdeg, cfg.encoder_error_phase_deg), start=1):
        if a:
            e = e + np.radians(a * 1e-3) * np.sin(k * alpha + np.radians(phi))
    return e


def encoder_legendre_terms(cfg: ScannerConfig) -> tuple[float, np.ndarray, float]:
    """The simulated encoder error as the estimator writes it: ``(mean, terms, residual)`` (rad), its mean over
    the field of view (a roll of the boresight), its Legendre coefficients (4,)
    (:func:`~georefine.adjustment.observations.plane.encoder_basis`, least squares over the field of view, taken
    as ``+-`` :data:`~georefine.adjustment.observations.plane.ENCODER_HALF_WIDTH_DEG`) and the largest part
    of the error that they do not represent."""
    from georefine.adjustment.observations.plane import ENCODER_HALF_WIDTH_DEG, encoder_basis

    alpha = np.radians(np.linspace(-ENCODER_HALF_WIDTH_DEG, ENCODER_HALF_WIDTH_DEG, 2001))
    design = np.column_stack([np.ones_like(alpha), encoder_basis(alpha)])
    e = encoder_error_rad(alpha, cfg)
    coef = np.linalg.lstsq(design, e, rcond=None)[0]
    return float(coef[0]), coef[1:], float(np.abs(design @ coef - e).max())


def _recorded_angle(alpha: np.ndarray, cfg: ScannerConfig) -> np.ndarray:
    """The scan angle the unit records for the polygon angle ``alpha``: rounded to the encoder's step."""
    if not cfg.encoder_resolution_mdeg:
        return alpha
    q = np.radians(cfg.encoder_resolution_mdeg * 1e-3)
    return q * np.rint(alpha / q)


def beam_directions_s(
    channel: np.ndarray, scan_angle_rad: np.ndarray, cfg: ScannerConfig, true: bool = False
) -> np.ndarray:
    """Unit beam directions (N, 3) in ``s`` for channels (N,) and scan angles (N,) [rad]: as the unit's
    calibration has them, or with ``true`` as the beams leave at polygon angles ``scan_angle_rad`` (the
    channel angle errors and the encoder error added)."""
    channel = np.asarray(channel, np.int64)
    tau = np.radians(np.asarray(cfg.facet_tilt_deg))[channel]
    if true:
        tau = tau + np.radians(np.asarray(cfg.channel_tilt_error_mdeg) * 1e-3)[channel]
        scan_angle_rad = (scan_angle_rad + np.radians(np.asarray(cfg.channel_scan_angle_error_mdeg) * 1e-3)[channel]
                          + encoder_error_rad(scan_angle_rad, cfg))
    ct = np.cos(tau)
    return np.column_stack([np.sin(tau), ct * np.sin(scan_angle_rad), ct * np.cos(scan_angle_rad)])


def _pulses(t_a: float, t_b: float, cfg: ScannerConfig):
    """Emitted pulses in [t_a, t_b) inside the field of view: time, channel, scan angle."""
    prr = cfg.pulse_rate_hz
    k = np.arange(np.ceil(t_a * prr), np.ceil(t_b * prr), dtype=np.int64)
    t = k / prr
    phase = t * cfg.line_rate_hz
    line = np.floor(phase)
    alpha = (phase - line - 0.5) * FACET_SWEEP_RAD
    keep = np.abs(alpha) <= np.radians(cfg.field_of_view_deg) / 2
    channel = (line[keep].astype(np.int64) % N_FACETS).astype(np.uint8)
    return t[keep], channel, alpha[keep]


def _rotate(R, v):
    """R (N,3,3) applied to v (N,3) or (3,)."""
    if v.ndim == 1:
        return R @ v
    return R[:, :, 0] * v[:, 0:1] + R[:, :, 1] * v[:, 1:2] + R[:, :, 2] * v[:, 2:3]


PoseFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def scan(
    pose_fn: PoseFn,
    t_start: float,
    t_end: float,
    scene: Scene,
    cfg: ScannerConfig,
    p_b_s: np.ndarray,
    R_b_s: np.ndarray,
    rng: np.random.Generator | np.random.SeedSequence,
    chunk_duration_s: float = 1.0,
    runner: TaskRunner | None = None,
    finish: Callable[..., Any] | None = None,
    finish_args: tuple = (),
) -> Iterator[Any]:
    """Simulate the scanner from ``t_start`` to ``t_end``, chunk by chunk.

    Parameters
    ----------
    pose_fn : callable
        ``pose_fn(t (N,)) -> (p_w_b (N,3), R_w_b (N,3,3))``: true body pose in ``w`` at
        times [s] relative to the dataset epoch.
    t_start, t_end : float
        Time span [s]; pulses with ``t_start <= t < t_end`` are emitted.
    scene : Scene
    cfg : ScannerConfig
    p_b_s : ndarray (3,)
        Scanner origin in the body frame [m] (lever arm).
    R_b_s : ndarray (3, 3)
        Boresight rotation from ``s`` to ``b``.
    rng : numpy.random.SeedSequence or numpy.random.Generator
        Seed of the range and intensity noise. Chunk ``k`` draws its noise from its own
        generator, ``SeedSequence(entropy, spawn_key=(*spawn_key, k))``, so that the chunks
        can be simulated in any order and on any worker with the same result; a generator
        gives the entropy (one draw). The noise depends on ``chunk_duration_s``; the
        geometry does not.
    chunk_duration_s : float
        Duration of a chunk [s]; memory is bounded by
        ``pulse_rate_hz * chunk_duration_s`` pulses (~100 MB at 200 kHz and 1 s).
    runner : TaskRunner, optional
        Where the chunks are simulated (one task each, :mod:`georefine.tasks`); default: in
        this process, one after the other. The chunks are yielded in time order either way,
        and at most a few per task slot wait in memory.
    finish, finish_args : callable, tuple, optional
        ``finish(chunk, *finish_args)`` inside each chunk's task (a module-level function, e.g.
        turning the chunk into file records); its results are yielded instead of the chunks.

    Yields
    ------
    ScanChunk
        Returns of the pulses of each chunk (possibly empty), in time order (or what ``finish``
        made of them).
    """
    p_b_s = np.asarray(p_b_s, np.float64).reshape(3)
    R_b_s = np.asarray(R_b_s, np.float64)
    if R_b_s.shape != (3, 3) or not np.allclose(R_b_s @ R_b_s.T, np.eye(3), atol=1e-9):
        raise ValueError("R_b_s must be a 3x3 rotation matrix")
    if not (np.isfinite(t_start) and np.isfinite(t_end) and t_end > t_start):
        raise ValueError(f"need finite t_start < t_end, got {t_start}, {t_end}")
    if chunk_duration_s <= 0:
        raise ValueError("chunk_duration_s must be positive")
    seed = rng if isinstance(rng, np.random.SeedSequence) else np.random.SeedSequence(int(rng.integers(2**63)))
    return _scan(pose_fn, float(t_start), float(t_end), scene, cfg, p_b_s, R_b_s, seed,
                 float(chunk_duration_s), runner, finish, tuple(finish_args))


def chunk_seed(seed: np.random.SeedSequence, k: int) -> np.random.SeedSequence:
    """The noise seed of chunk ``k`` of a scan seeded with ``seed`` (independent of the order)."""
    return np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, int(k)))


def _scan(pose_fn, t_start, t_end, scene, cfg, p_b_s, R_b_s, seed, chunk_duration_s, runner, finish, finish_args):
    n_chunks = int(np.ceil((t_end - t_start) / chunk_duration_s))
    edges = np.minimum(t_start + chunk_duration_s * np.arange(n_chunks + 1), t_end)
    spans = [(a, b, chunk_seed(seed, k)) for k, (a, b) in enumerate(zip(edges[:-1], edges[1:]))]
    if runner is None:
        results = (_scan_task(pose_fn, a, b, scene, cfg, p_b_s, R_b_s, s, finish, finish_args) for a, b, s in spans)
    else:
        # The trajectory and the scene (~60 MB at `corridor`) travel to each worker once.
        pose, world = runner.share(pose_fn), runner.share(scene)
        results = runner.map(_scan_task, [(pose, a, b, world, cfg, p_b_s, R_b_s, s, finish, finish_args)
                                          for a, b, s in spans], label="scan chunks")
    n_pulses = n_points = 0
    for result, pulses, points in results:
        n_pulses += pulses
        n_points += points
        yield result
    log.info("scanned %.1f s: %d pulses in the field of view, %d returns (%.1f %%)",
             t_end - t_start, n_pulses, n_points, 100.0 * n_points / max(n_pulses, 1))


def _scan_task(pose_fn, t_a, t_b, scene, cfg, p_b_s, R_b_s, seed, finish, finish_args) -> tuple[Any, int, int]:
    chunk = scan_span(pose_fn, t_a, t_b, scene, cfg, p_b_s, R_b_s, seed)
    return (chunk if finish is None else finish(chunk, *finish_args)), chunk.pulses, len(chunk)


def scan_span(pose_fn: PoseFn, t_a: float, t_b: float, scene: Scene, cfg: ScannerConfig, p_b_s: np.ndarray,
              R_b_s: np.ndarray, seed: np.random.SeedSequence) -> ScanChunk:
    """The returns of the pulses emitted in ``[t_a, t_b)``, noise from ``seed`` (one scan task)."""
    t, channel, alpha = _pulses(t_a, t_b, cfg)
    chunk = _scan_chunk(pose_fn, t, channel, alpha, scene, cfg, p_b_s, R_b_s, np.random.default_rng(seed))
    return dataclasses.replace(chunk, pulses=len(t))


def _scan_chunk(pose_fn, t, channel, alpha, scene, cfg, p_b_s, R_b_s, rng) -> ScanChunk:
    if len(t):
        p_w_b, R_w_b = pose_fn(t)
        p_w_b, R_w_b = np.asarray(p_w_b, np.float64), np.asarray(R_w_b, np.float64)
        if p_w_b.shape != (len(t), 3) or R_w_b.shape != (len(t), 3, 3):
            raise ValueError(f"pose_fn returned {p_w_b.shape}, {R_w_b.shape} for {len(t)} times")
        alpha_rec = _recorded_angle(alpha, cfg)
        d_s = beam_directions_s(channel, alpha_rec, cfg)  # as recorded
        p_w_s = p_w_b + _rotate(R_w_b, p_b_s)
        ideal = alpha_rec is alpha and not any(
            cfg.channel_tilt_error_mdeg + cfg.channel_scan_angle_error_mdeg + cfg.encoder_error_mdeg)
        d_true = d_s if ideal else beam_directions_s(channel, alpha, cfg, true=True)
        d_w = _rotate(R_w_b, d_true @ R_b_s.T)  # R_w_s d_s = R_w_b (R_b_s d_s)
        range_m, face_id = scene.intersect(p_w_s, d_w, max_range_m=cfg.max_range_m)
        hit = np.flatnonzero(face_id >= 0)
    else:
        hit = np.zeros(0, np.int64)
    if len(hit) == 0:
        z = np.zeros(0)
        return ScanChunk(z, np.zeros((0, 3)), np.zeros(0, np.uint8), z, np.zeros(0, np.uint16),
                         z, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    r, face, d_w, d_s = range_m[hit], face_id[hit], d_w[hit], d_s[hit]
    d_w = d_w / np.linalg.norm(d_w, axis=1, keepdims=True)  # as used by the ray cast
    xyz_w_true = p_w_s[hit] + r[:, None] * d_w
    cos_inc = np.abs(np.einsum("ij,ij->i", scene.surface_normal(face), d_w))
    rho = scene.albedo(xyz_w_true, face)
    amplitude = cfg.intensity_at_reference * rho * cos_inc * (cfg.intensity_reference_range_m / r) ** 2  # noise-free
    # The draws: the range noise, then the intensity noise; the biases below draw nothing.
    err = rng.normal(0.0, cfg.range_sigma_m, len(hit))
    if cfg.range_offset_m or cfg.range_scale_ppm:
        err = err + cfg.range_offset_m + cfg.range_scale_ppm * 1e-6 * r
    if cfg.range_incidence_bias_m:
        cos_clipped = np.maximum(cos_inc, np.cos(np.radians(MAX_INCIDENCE_DEG)))
        err = err + cfg.range_incidence_bias_m * (1.0 / cos_clipped - 1.0)
    if cfg.range_walk_m:
        err = err + cfg.range_walk_m * np.log(cfg.intensity_at_reference / np.clip(amplitude, 1.0, 65535.0))
    xyz_s = (r + err)[:, None] * d_s
    inten = amplitude * (1.0 + cfg.intensity_noise_rel * rng.standard_normal(len(hit)))
    inten = np.clip(np.rint(inten), 1, 65535).astype(np.uint16)
    return ScanChunk(t[hit], xyz_s, channel[hit], alpha_rec[hit], inten, err, face, xyz_w_true, d_w,
                     np.ascontiguousarray(R_w_b[hit, :, 0]))
