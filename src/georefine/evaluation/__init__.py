"""Metrics, figures and report pages (layer 8, docs/ARCHITECTURE.md §1 and §5).

Trajectory differences (``trajectory``, ``trajectory_files``, ``plots``), reference planes,
strip differences and point-cloud errors (``reference_planes``, ``cell_moments``,
``strip_differences``, ``strip_pairs``, ``clouds``, ``point_cloud``, ``coadjust``), the typed figures of ``summary.json`` (``summary``) and the self-contained HTML pages
(``page``, ``report``). It may import the layers below it, reading result files through ``io``, but
not ``workflows``, ``sim``, ``demo`` or ``cli``: the workflows call it, never the other way
round.
"""
