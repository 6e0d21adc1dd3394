"""Geometry core: rotations, the Earth, frames and the frame camera (layer 2, docs/ARCHITECTURE.md §1).

``rotation`` (vectorised SO(3): Exp/Log, right Jacobians, quaternions ``xyzw``, NED Euler
angles), ``earth`` (WGS84, normal gravity, Earth rate, geodetic <-> ECEF), ``frames`` (the
mapping frame ``w`` and the output CRS through pyproj) and ``camera`` (pinhole with Brown
distortion, photogrammetric omega-phi-kappa). Pure functions on arrays in the conventions of
docs/ARCHITECTURE.md §2. It sits just above the root modules and imports nothing else from
Georefine: no file formats, no configuration, no estimation.
"""
