"""Georefine: rigorous georeferencing of airborne LiDAR point clouds and aerial images.

Conventions (stated once, followed everywhere)
----------------------------------------------
Frames
    ``e``  ECEF, WGS84.
    ``w``  mapping frame: local tangent plane, east-north-up, at the project's reference
           point (default: first GNSS fix). ECEF rotated and shifted: it rotates with the
           Earth, so the physics written in it is exact (Earth rate and normal gravity are
           expressed in ``w``).
    ``n``  local-level north-east-down at the current platform position (used only for
           roll/pitch/heading at the edges).
    ``b``  IMU body frame, forward-right-down. The trajectory is the IMU's.
    ``s``  scanner's own coordinate system (SOCS).
    ``a``  GNSS antenna phase centre.
    ``c``  camera, computer-vision convention (x right, y down, z along the optical axis).

Names
    ``R_a_b`` maps vectors from ``b`` to ``a``; ``p_a_b`` is the origin of ``b`` expressed
    in ``a``: ``x_a = R_a_b @ x_b + p_a_b``. Inner letters cancel: ``R_w_s = R_w_b @ R_b_s``.
    Rates: ``omega_ib_b`` is the rate of ``b`` relative to ``i`` expressed in ``b``.
    Lever arms ``p_b_a`` (antenna), ``p_b_s`` (scanner); boresight ``R_b_s``.
    Stacked arrays carry a leading axis: ``R_w_b`` has shape ``(N, 3, 3)``.

Rotations
    Perturbations are on the right, in the body frame: ``R <- R @ Exp(dtheta)``.
    Quaternions, where stored at all, are ``xyzw`` (SciPy's order).

Units
    SI and radians inside. Degrees, mdeg, ppm, deg/h, deg/sqrt(h), micro-g only at the
    edges (configuration, files, reports), with the unit in the name (``heading_deg``).

Time
    GPS time in seconds, continuous, no leap seconds. Files use GPS seconds since
    1980-01-06 00:00:00 GPST; LAS files use adjusted standard GPS time (GPS seconds - 1e9,
    LAS 1.4 global-encoding bit set). In memory, times are float64 seconds relative to the
    dataset epoch ``t0`` (stored with the data) so that microseconds survive.

Public API
----------
The functions of :mod:`georefine.api` -- one per command of the ``georefine`` command line,
which calls them and nothing else -- their results and the project they open, re-exported
here: ``georefine.open_project``, ``georefine.simulate``, ``georefine.run``, ... (see
``help(georefine.api)`` and the README, "Using Georefine from Python"). They are loaded on
first use (PEP 562), so that ``import georefine`` and the lower layers, which never import
the API, stay light.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("georefine")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

API = (
    "Flight", "Project", "open_project",
    "adjust_hybrid", "check", "clean", "coadjust", "estimate_trajectory", "evaluate_reference_planes",
    "evaluate_run", "evaluate_strip_differences", "evaluate_trajectory", "export_trajectory", "georeference",
    "import_strips", "match", "render_lidargrams", "run", "run_demo", "simulate",
    "BlockDemoResult", "CleanResult", "CoadjustResult", "DemoResult", "GeoreferenceRunResult", "HybridResult",
    "ImportResult", "MatchSummary", "ProjectSummary", "ReferencePlaneFigures", "RunEvaluation", "SimulationResult",
    "StripDifferenceMap", "TrajectoryComparison", "TrajectoryEvaluation", "TrajectoryExport", "TrajectoryRunResult",
    "FlightsResult", "WorkflowResult",
    "ConfigError", "GeorefineError", "InputError", "Progress", "TaskRunner",
)
"""The names of :mod:`georefine.api` re-exported here (``tests/test_api.py`` holds it to ``api.__all__``)."""

__all__ = ["__version__", *API]


def __getattr__(name: str):
    """The API's names, imported from :mod:`georefine.api` on first use (the one reference from the
    root to the top layer: docs/ARCHITECTURE.md §1)."""
    if name in API:
        value = getattr(import_module("georefine.api"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'georefine' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(API))
