"""LiDAR algorithms of the trajectory workflow (layer 7, docs/ARCHITECTURE.md §1).

``georeference`` (direct georeferencing of scanner-frame points, §4.5 steps 3 and 6),
``planes`` (planar features per view, step 4) and ``correspondences`` (matching features of
different views into planar objects, step 4), ``strip_adjustment`` (the classical per-strip
adjustment from the same planes, the run's baseline). It may import any lower layer (root,
``geometry``, ``io``, ``config``, ``trajectory``, ``adjustment``) but not its sibling
``lidargrammetry`` and nothing above (``evaluation``, ``workflows``, ``sim``, ``demo``,
``cli``).
"""
