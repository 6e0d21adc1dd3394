"""Observation models of the adjustment (part of layer 6, docs/ARCHITECTURE.md §1 and §4.3).

One module per observation group: ``gnss`` (antenna positions), ``imu`` (window-averaged
specific force and angular rate), ``bias`` (piecewise-linear biases and their random walk),
``plane`` (plane correspondences), ``prior`` (pseudo-observations) and ``reprojection``
(image points); ``trajectory_blocks`` names the spline's parameter blocks. Each group
evaluates all its whitened residuals and Jacobian blocks at once, as
:mod:`georefine.adjustment.problem` states, and has a finite-difference test
(:func:`georefine.adjustment.testing.check_jacobians`). Like the rest of ``adjustment`` it
imports nothing from ``io`` and nothing from a higher layer.
"""
