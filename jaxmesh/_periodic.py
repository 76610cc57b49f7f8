"""The one home of periodic (minimum-image / wrap) arithmetic.

Works on NumPy arrays and on JAX arrays (traced or not) alike: the array module is picked
from the argument, and jax is only imported when a JAX array arrives, so NumPy topology
code can use these functions without importing jax.
"""

from __future__ import annotations

import numpy as np


def _array_module(x):
    if isinstance(x, (np.ndarray, np.generic, float, int, list, tuple)):
        return np
    import jax.numpy as jnp  # only reached for JAX arrays / tracers

    return jnp


def wrap(points, box):
    """Map points into the periodic cell [0, L) along every axis.

    points: (..., d); box: (d,) lengths. Returns the same shape.
    """
    xp = _array_module(points)
    box = xp.asarray(box, dtype=points.dtype if hasattr(points, "dtype") else None)
    return points - box * xp.floor(points / box)


def minimum_image(delta, box):
    """Shortest periodic representative of a difference vector: each component in [-L/2, L/2].

    delta: (..., d); box: (d,). Returns the same shape.
    """
    xp = _array_module(delta)
    box = xp.asarray(box, dtype=delta.dtype if hasattr(delta, "dtype") else None)
    return delta - box * xp.round(delta / box)


def periodic_distance(a, b, box):
    """Euclidean minimum-image distance between points a (..., d) and b (..., d)."""
    xp = _array_module(a)
    d = minimum_image(a - b, box)
    return xp.sqrt(xp.sum(d * d, axis=-1))


def image_shifts(dim: int, box) -> np.ndarray:
    """The 3**dim lattice translations {-L, 0, L}^dim, (3**dim, dim), zero shift first."""
    grids = np.meshgrid(*[np.array([0, -1, 1])] * dim, indexing="ij")
    k = np.stack([g.ravel() for g in grids], axis=-1).astype(float)
    return k * np.asarray(box, dtype=float)


def nearest_images_suffice(centre, spread, box) -> bool:
    """Whether, per axis, the two images of a point nearest a shape's centre (2^d of the 3^d shifts
    `image_shifts` gives) always hold its periodic minimum, for a shape between two balls about the
    centre whose radii differ by spread (0 for a sphere, a_max - a_min for an ellipsoid).

    NumPy only. With the centre in the cell the best image per axis lies within L/2 of it, so the
    best of the kept images is at a <= D/2 (D the cell's diagonal); a dropped image is on some axis
    the farthest of three, at least L_min farther in square, so its value is at least
    sqrt(a^2 + L_min^2) - R while the kept one's is at most a - r: it cannot be smaller when
    spread <= sqrt(D^2/4 + L_min^2) - D/2 (0.457 L for a cube).
    """
    centre, box = np.asarray(centre, float), np.asarray(box, float)
    half_diagonal = 0.5 * float(np.linalg.norm(box))
    bound = float(np.hypot(half_diagonal, box.min())) - half_diagonal
    return bool(np.all((centre >= 0) & (centre <= box))) and float(spread) <= bound


def nearest_image_shifts(offsets, box):
    """Per point, the 2^d shifts of {-L, 0, L}^d that keep, per axis, the two images of offsets
    (point - centre, (m, d)) nearest the centre: 0 and -L where the offset is >= 0, else 0 and +L.
    Returns (2^d, m, d), the zero shift first (NumPy or JAX, like offsets)."""
    xp = _array_module(offsets)
    dim = offsets.shape[-1]
    box = xp.asarray(box, dtype=offsets.dtype)
    other = xp.where(offsets >= 0, -box, box)
    corners = np.stack(np.meshgrid(*[np.array([0.0, 1.0])] * dim, indexing="ij"), axis=-1).reshape(-1, dim)
    return xp.asarray(corners, dtype=offsets.dtype)[:, None, :] * other[None]


def points_near(points, centres, radii, box, periodic: bool = True) -> list[np.ndarray]:
    """Per centre i, the sorted indices of points within radii[i] of it (minimum image when periodic).

    NumPy only. A k-d tree over the points (periodic: scipy's boxsize) instead of a distance from
    every point to every centre.
    """
    from scipy.spatial import cKDTree

    points, centres = np.asarray(points, dtype=float), np.asarray(centres, dtype=float)
    if not len(points) or not len(centres):
        return [np.zeros(0, np.int64) for _ in range(len(centres))]
    box = np.asarray(box, dtype=float)
    if periodic:
        points, centres = wrap(points, box), wrap(centres, box)
        points = np.where(points >= box, points - box, points)  # wrap can round up to L itself
        centres = np.where(centres >= box, centres - box, centres)
        tree = cKDTree(points, boxsize=box)
    else:
        tree = cKDTree(points)
    found = tree.query_ball_point(centres, np.asarray(radii, dtype=float))
    return [np.sort(np.asarray(f, dtype=np.int64)) for f in found]


def nearest_centres(points, centres, box, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-image distances (m, k) from each point to its k nearest centres and their indices.

    NumPy only (scipy's periodic k-d tree). k is capped at the number of centres.
    """
    from scipy.spatial import cKDTree

    box = np.asarray(box, dtype=float)
    points, centres = wrap(np.asarray(points, dtype=float), box), wrap(np.asarray(centres, dtype=float), box)
    points = np.where(points >= box, points - box, points)  # wrap can round up to L itself
    centres = np.where(centres >= box, centres - box, centres)
    k = min(int(k), len(centres))
    dist, idx = cKDTree(centres, boxsize=box).query(points, k=k)
    return dist.reshape(len(points), k), idx.reshape(len(points), k)


def wrap_index(index, n):
    """Periodic grid index wrap (integer arrays, NumPy or JAX)."""
    return index % n


def plane_clearances(lower, upper, box, shape) -> list[np.ndarray]:
    """Per axis a, (n_a,) the periodic distance from each grid plane x_a = k L_a / n_a to the nearest
    inclusion extent bound along a (lower[:, a] or upper[:, a]).

    A box plane near such a bound meets an inclusion at a grazing angle (a shallow cap or a surface
    just clear of it), which leaves a wedge of the domain thinner than the elements.
    lower, upper: (N, d) inclusion bounds (unwrapped); box: (d,); shape: grid samples per axis.
    """
    lower, upper = np.asarray(lower, float).reshape(-1, len(box)), np.asarray(upper, float).reshape(-1, len(box))
    out = []
    for a, (length, n) in enumerate(zip(box, shape)):
        planes = np.arange(n) * (length / n)
        bounds = np.concatenate([lower[:, a], upper[:, a]])
        if not len(bounds):
            out.append(np.full(n, np.inf))
            continue
        gap = np.abs(minimum_image(planes[:, None] - bounds[None, :], np.array([length])))
        out.append(gap.min(axis=1))
    return out


def clearest_roll(lower, upper, box, shape) -> tuple[int, ...]:
    """Per axis, the grid sample k whose plane lies farthest from every inclusion bound
    (`plane_clearances`); 0 where the plane x_a = 0 is already as clear. Rolling the periodic
    grid by -k puts the box faces there."""
    return clearest_planes(plane_clearances(lower, upper, box, shape))


def clearest_planes(clearances: list[np.ndarray]) -> tuple[int, ...]:
    """`clearest_roll` from the per-axis clearances of `plane_clearances`."""
    return tuple(0 if c[0] >= c.max() else int(np.argmax(c)) for c in clearances)
