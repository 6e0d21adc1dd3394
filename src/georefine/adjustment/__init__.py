"""Sparse non-linear least squares and the GNSS/IMU problem (layer 6, docs/ARCHITECTURE.md §1).

``problem``, ``blocks``, ``solver``, ``linalg``, ``robust`` and ``statistics`` are the engine
(parameter blocks on manifolds, observation groups, Levenberg-Marquardt with sparse Cholesky,
robust losses, statistics and posterior covariances, §4.4); ``observations`` holds the
observation models (§4.3); ``gnss_imu`` builds and solves the GNSS/IMU adjustment (§4.5
step 2); ``testing`` checks Jacobians against finite differences. It may import the root
modules, ``geometry``, ``config`` and ``trajectory``, but nothing from ``io`` (it reads and
writes no files) and nothing from ``lidar``, ``lidargrammetry`` or any higher layer.
"""
