"""The six steps of the GNSS/IMU/LiDAR workflow (paper 000), named once.

The command line's help quotes them from here, and ``tests/test_cli_help.py`` holds README.md's
numbered list of the workflow (section "GNSS/IMU/LiDAR: the whole workflow") to the same names,
so that help, README and code cannot drift apart (docs/ARCHITECTURE.md §1, layer 0).
"""

from __future__ import annotations

__all__ = ["WORKFLOW_STEPS", "steps_text"]

WORKFLOW_STEPS: dict[int, str] = {
    1: "initialisation",
    2: "GNSS/IMU adjustment",
    3: "preliminary georeferencing",
    4: "planar features and matching",
    5: "G/I/L adjustment",
    6: "final georeferencing",
}


def steps_text(*numbers: int) -> str:
    """``"steps 1, 2 and 6 (initialisation, GNSS/IMU adjustment, final georeferencing)"``, or
    ``"step 6 (final georeferencing)"`` for one."""
    if not numbers:
        raise ValueError("steps_text needs at least one step")
    unknown = [n for n in numbers if n not in WORKFLOW_STEPS]
    if unknown:
        raise ValueError(f"no workflow step {unknown[0]} (expected 1-6)")
    names = ", ".join(WORKFLOW_STEPS[n] for n in numbers)
    if len(numbers) == 1:
        return f"step {numbers[0]} ({names})"
    listed = ", ".join(str(n) for n in numbers[:-1]) + f" and {numbers[-1]}"
    return f"steps {listed} ({names})"
