"""NumPy topology helpers for the truss engine: bars from simplices, capacity buckets, quality.

This module never imports jax: it runs between the jitted scans of the driver, on concrete
arrays, the way jax-md rebuilds neighbour lists outside jit.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = [
    "edges_from_simplices",
    "bucket_capacity",
    "pad_rows",
    "simplex_quality",
]


def edges_from_simplices(simplices: np.ndarray, n_points: int | None = None) -> np.ndarray:
    """Unique undirected edges (bars) of a simplicial mesh.

    Uses one int64 key per edge (``i * n + j`` with ``i < j``) and a 1-D ``np.unique``: sorting
    rows with ``np.unique(axis=0)`` costs as much as the Delaunay itself (DESIGN.md section 3).

    Args:
        simplices: (m, k) integer node indices, k >= 2 (k = 2 bars, 3 triangles, 4 tets).
        n_points: number of nodes; defaults to ``simplices.max() + 1``.

    Returns:
        (n_edges, 2) int64 array, each row sorted (i < j), rows sorted by key. Degenerate
        edges (i == j) are dropped.

    Example:
        >>> edges_from_simplices(np.array([[0, 1, 2], [1, 3, 2]]))
        array([[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])
    """
    s = np.asarray(simplices)
    if s.ndim != 2 or s.shape[1] < 2 or not np.issubdtype(s.dtype, np.integer):
        raise ValueError(
            f"simplices: expected an integer array of shape (m, k) with k >= 2, got dtype "
            f"{s.dtype} and shape {s.shape}. Hint: pass the cells of one simplex type, e.g. "
            "scipy.spatial.Delaunay(points).simplices."
        )
    if s.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if s.min() < 0:
        raise ValueError(f"simplices: expected non-negative node indices, got min {s.min()}.")
    n = int(s.max()) + 1 if n_points is None else int(n_points)
    if s.max() >= n:
        raise ValueError(f"simplices: index {s.max()} out of range for n_points={n}.")
    s = s.astype(np.int64, copy=False)
    pairs = list(itertools.combinations(range(s.shape[1]), 2))
    a = np.concatenate([s[:, i] for i, _ in pairs])
    b = np.concatenate([s[:, j] for _, j in pairs])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keep = lo != hi
    keys = np.unique(lo[keep] * n + hi[keep])
    return np.stack([keys // n, keys % n], axis=1)


def bucket_capacity(size: int, *, current: int | None = None, minimum: int = 64) -> int:
    """Capacity bucket for a padded array: the next power of two >= ``size``.

    A capacity that still fits (``current >= size``) is kept, so that a topology change that
    does not grow past the bucket reuses the compiled kernels.

    Args:
        size: number of rows needed.
        current: the capacity in use, if any.
        minimum: smallest capacity handed out.

    Returns:
        the capacity (int).
    """
    if size < 0:
        raise ValueError(f"size: expected >= 0, got {size}.")
    if current is not None and current >= size:
        return int(current)
    cap = max(int(minimum), 1)
    while cap < size:
        cap *= 2
    return cap


def pad_rows(rows: np.ndarray, capacity: int, *, fill: int = 0, dtype=np.int32):
    """Pad an index array to ``capacity`` rows and return it with its validity mask.

    Args:
        rows: (m, k) integer array (bars, triangles, tets).
        capacity: number of rows of the output, >= m.
        fill: index written in the padding rows (a valid node index, so gathers stay in range).
        dtype: integer dtype of the output.

    Returns:
        (padded (capacity, k) ``dtype``, mask (capacity,) bool), mask True on the first m rows.
    """
    rows = np.asarray(rows)
    m = rows.shape[0]
    if capacity < m:
        raise ValueError(f"capacity: expected >= {m} rows, got {capacity}. Hint: use bucket_capacity.")
    if m and np.abs(rows).max() > np.iinfo(dtype).max:
        raise ValueError(f"rows: indices do not fit in {np.dtype(dtype).name}.")
    out = np.full((capacity,) + rows.shape[1:], fill, dtype=dtype)
    out[:m] = rows
    mask = np.zeros(capacity, dtype=bool)
    mask[:m] = True
    return out, mask


def simplex_quality(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Normalised shape quality of triangles (2 r_in / r_circ) or tets (3 r_in / r_circ).

    1 for the regular simplex, 0 for a degenerate one. Triangles may live in 2D or 3D.

    Args:
        points: (n, d) coordinates.
        simplices: (m, 3) triangles or (m, 4) tetrahedra.

    Returns:
        (m,) float64 qualities.
    """
    p = np.asarray(points, dtype=np.float64)
    s = np.asarray(simplices)
    if s.ndim != 2 or s.shape[1] not in (3, 4):
        raise ValueError(f"simplices: expected shape (m, 3) or (m, 4), got {s.shape}.")
    if s.shape[1] == 3:
        a = np.linalg.norm(p[s[:, 1]] - p[s[:, 2]], axis=1)
        b = np.linalg.norm(p[s[:, 2]] - p[s[:, 0]], axis=1)
        c = np.linalg.norm(p[s[:, 0]] - p[s[:, 1]], axis=1)
        num = (b + c - a) * (c + a - b) * (a + b - c)
        den = a * b * c
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    if p.shape[1] != 3:
        raise ValueError(f"points: tetrahedra need 3D points, got dimension {p.shape[1]}.")
    x0 = p[s[:, 0]]
    e = np.stack([p[s[:, k]] - x0 for k in (1, 2, 3)], axis=1)  # (m, 3, 3) rows = edge vectors
    vol6 = np.abs(np.linalg.det(e))
    faces = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
    area = sum(
        0.5 * np.linalg.norm(np.cross(p[s[:, j]] - p[s[:, i]], p[s[:, k]] - p[s[:, i]]), axis=1)
        for i, j, k in faces
    )
    r_in = 0.5 * vol6 / np.where(area > 0, area, 1.0)  # 3 V / A with V = vol6 / 6
    sq = np.sum(e * e, axis=2)
    # circumcentre c (relative to x0) solves 2 e c = |e|^2; |c| is the circumradius
    ok = vol6 > 1e-300
    c = np.zeros_like(x0)
    c[ok] = np.linalg.solve(2.0 * e[ok], sq[ok][..., None])[..., 0]
    r_circ = np.linalg.norm(c, axis=1)
    return np.where(ok & (r_circ > 0), 3.0 * r_in / np.where(r_circ > 0, r_circ, 1.0), 0.0)
