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
    "pad_nodes_to_bucket",
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


def pad_nodes_to_bucket(points: np.ndarray) -> tuple[np.ndarray, int]:
    """Nodes (n, d) padded to their capacity bucket with copies of node 0, and that capacity.

    The copies are for the caller to fix (they take no bars): meshes of similar size then share
    one compilation of the truss kernels.
    """
    n = len(points)
    cap = bucket_capacity(n)
    return np.vstack([points, np.repeat(points[:1], cap - n, axis=0)]), cap


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
