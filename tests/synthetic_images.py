"""A seeded textured image for matcher tests: discs, lines and noise at several scales."""

from __future__ import annotations

import cv2
import numpy as np


def textured_scene(seed: int, width: int, height: int, discs: int, lines: int, max_radius: int) -> np.ndarray:
    """An 8-bit ``(height, width)`` image: ``discs`` filled circles of radius 3..``max_radius``,
    ``lines`` lines, a 1.2 px blur and noise of 3 grey values."""
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width), np.float32)
    for _ in range(discs):
        c = tuple(int(v) for v in rng.uniform([0, 0], [width, height]))
        cv2.circle(img, c, int(rng.uniform(3, max_radius)), float(rng.uniform(0, 255)), -1)
    for _ in range(lines):
        p, q = (tuple(int(v) for v in rng.uniform([0, 0], [width, height])) for _ in range(2))
        cv2.line(img, p, q, float(rng.uniform(0, 255)), int(rng.uniform(1, 4)))
    img = cv2.GaussianBlur(img, (0, 0), 1.2) + rng.normal(0, 3, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)
