"""The georeferencing workflow of paper 000 (Fig. 1), one function per step (docs/ARCHITECTURE.md §4.5).

``navigation``: loading and validating GNSS/IMU, step 1 (initialisation filter) and step 2
(GNSS/IMU adjustment) with their products, and direct georeferencing of strips with a given
trajectory. ``lidar``: steps 3-6 (preliminary georeferencing, planar features and matching,
GNSS/IMU/LiDAR adjustment with outer iterations, final georeferencing).
"""

from georefine.workflows.navigation import (
    GeoreferenceRunResult,
    NavigationData,
    TrajectoryRunResult,
    load_navigation,
    run_georeference,
    run_trajectory,
    step_adjust_gnss_imu,
    step_initialise,
)

__all__ = [
    "GeoreferenceRunResult",
    "NavigationData",
    "TrajectoryRunResult",
    "load_navigation",
    "run_georeference",
    "run_trajectory",
    "step_adjust_gnss_imu",
    "step_initialise",
]
