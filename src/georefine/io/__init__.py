"""File formats: readers and writers of what real systems deliver (layer 3, docs/ARCHITECTURE.md §1).

One module per format (``las``, with ``las_writer`` and ``las_encode`` for writing it; ``gnss``,
``imu``, ``trajectory``, ``pose_files`` (TUM and trajectopy poses), ``photos``, ``reference``,
``colmap``, ``metashape``, ``run_metrics`` for a run's ``metrics.json`` and every ``adjustment.json``), each reading into and writing from plain frozen containers and
validating what it reads down to file, line or record, field, expected and found
(docs/ARCHITECTURE.md §3); ``files`` holds what they share: atomic writing, GPS time, fast
text parsing, JSON. Formats only: it imports the root modules and ``geometry`` and nothing
above them (not ``config``, not the estimation, not the workflows).
"""
