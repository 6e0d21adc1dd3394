"""Trajectory models and the initialisation filter (layer 5, docs/ARCHITECTURE.md §1).

``spline`` (continuous-time trajectory on uniform knots, §4.2) and ``spline_fit``,
``sampled`` (the sampled ``Trajectory`` the stages exchange), ``strapdown`` (mechanisation in
``w``, §4.1) and ``ekf`` with its numba kernels (error-state EKF and RTS smoother, §4.5
step 1). Estimation only: it may import the root modules, ``geometry`` and ``config``, but
nothing from ``io`` (it reads and writes no files; the workflows pass it arrays) and nothing
from a higher layer.
"""
