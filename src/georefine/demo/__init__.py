"""``georefine demo``: simulation, workflow, evaluation and report in one command (layer 10, docs/ARCHITECTURE.md §1).

``corridor`` (paper 000: both passes and a single pass, evaluated against the truth),
``block`` (paper 004: the jammed cloud and the three co-adjustment cases) and ``lanes`` (the
second process the demos run beside their own). The only package besides ``cli`` that
imports ``sim``; it may import every layer below it, and nothing imports it but ``cli``.
"""
