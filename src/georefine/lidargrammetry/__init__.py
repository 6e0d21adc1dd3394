"""Lidargrammetric co-matching and co-adjustment, paper 004 (layer 7, docs/ARCHITECTURE.md §1).

``render`` (lidargrams with their ULPI raster), ``matching`` (keypoints, verified pair
matches, tracks), ``bundle`` (co-adjustment of photos and lidargrams, cases 1-3),
``reintersect`` (the refined point cloud) and ``crosscheck`` (the same tie problem solved by
COLMAP and by Georefine); see §4.8. It may import any lower layer (the camera model is in
``geometry``, the engine in ``adjustment``) but not its sibling ``lidar`` and nothing above
(``evaluation``, ``workflows``, ``sim``, ``demo``, ``cli``).
"""
