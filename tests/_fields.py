"""Level-set fields shared by several test files."""

import numpy as np


def flat_bottom_ellipsoid(n: int, gap_steps: float) -> np.ndarray:
    """An oblate ellipsoid (0.32, 0.32, 0.1) on an n^3 grid whose flat bottom lies gap_steps grid steps
    above z = 0 (below when negative), about a distance near its surface: a matrix layer that thin
    along the plane, or an interface crossing it at a shallow angle."""
    x = np.arange(n) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    axes = np.array([0.32, 0.32, 0.1])
    u = np.stack([X - 0.5, Y - 0.5, Z - (0.1 + gap_steps / n)], -1) / axes
    r = np.linalg.norm(u, axis=-1)
    return (r - 1) * r / np.linalg.norm(u / axes, axis=-1).clip(1e-9)
