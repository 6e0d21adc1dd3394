"""The workflows: project folders in, steps run and cached, products out (layer 9, docs/ARCHITECTURE.md §1).

``opened`` (the opened project: ``project.yaml`` read once, its navigation data and frame ``w``
derived once; the workspace of one command), ``project`` (the sensor files' readers and checks),
``check`` (validate a project, ``georefine check``), ``navigation`` (workflow steps 1-2 and
direct georeferencing with a given trajectory), ``lidar``
(steps 3-6 of paper 000 with the outer iterations, ``georefine run``; the strips and their
planar features in ``strips``), ``lidargrammetry`` (paper 004, ``georefine lidargrams``,
``match``, ``coadjust``; the photo block and the cloud in ``photo_block``, the typed results
in ``lidargrammetry_results``), ``products`` (trajectory files), ``strip_baseline`` (the classical strip adjustment beside the
G/I/L), ``evaluate`` (a run evaluated as paper 000 reports it) and ``cache`` (the step
cache); see §4.5 and §4.8. Each step is a plain function returning a frozen result, taking the
opened project; the public API (:mod:`georefine.api`) calls one per command. It may import every
layer below it but not its sibling ``sim`` (a workflow must run on real data alone) and nothing
above (``demo``, ``api``, ``cli``).
"""

from georefine.workflows.navigation import (
    GeoreferenceRunResult,
    TrajectoryRunResult,
    run_georeference,
    run_trajectory,
    step_adjust_gnss_imu,
    step_initialise,
)
from georefine.workflows.opened import NavigationData, Project, load_navigation, open_project

__all__ = [
    "GeoreferenceRunResult",
    "NavigationData",
    "Project",
    "TrajectoryRunResult",
    "load_navigation",
    "open_project",
    "run_georeference",
    "run_trajectory",
    "step_adjust_gnss_imu",
    "step_initialise",
]
