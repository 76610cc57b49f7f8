"""Triangle-triangle self-intersection tests for surface meshes (NumPy only).

Broad phase: a k-d tree over the triangles' bounding boxes; narrow phase: orientation
(determinant) tests. Two triangles intersect when an edge of one properly crosses the other,
when they are coplanar and overlap, or when two triangles sharing an edge fold onto each other.
Pairs sharing a vertex are tested on their opposite edges only.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from ._quality import cross3


def _orient3d(a, b, c, d):
    return np.einsum("ij,ij->i", b - a, cross3(c - a, d - a))


def _segment_crosses_triangle(p, q, a, b, c, eps):
    """(k,) bool: the segment pq crosses the triangle abc at a point interior to both (strict)."""
    o1, o2 = _orient3d(a, b, c, p), _orient3d(a, b, c, q)
    straddle = ((o1 > eps) & (o2 < -eps)) | ((o1 < -eps) & (o2 > eps))
    s1, s2, s3 = _orient3d(p, q, a, b), _orient3d(p, q, b, c), _orient3d(p, q, c, a)
    inside = ((s1 > eps) & (s2 > eps) & (s3 > eps)) | ((s1 < -eps) & (s2 < -eps) & (s3 < -eps))
    return straddle & inside


def _orient2d(a, b, c):
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _coplanar_overlap(P, Q, axis, eps):
    """(k,) bool: coplanar triangles P, Q (k, 3, 3) overlap with positive area (projected 2D test)."""
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    P2 = np.take_along_axis(P, keep[:, None, :].repeat(3, 1), axis=2)
    Q2 = np.take_along_axis(Q, keep[:, None, :].repeat(3, 1), axis=2)
    hit = np.zeros(len(P), bool)
    for i in range(3):
        a, b = P2[:, i], P2[:, (i + 1) % 3]
        for j in range(3):
            c, d = Q2[:, j], Q2[:, (j + 1) % 3]
            o1, o2 = _orient2d(a, b, c), _orient2d(a, b, d)
            o3, o4 = _orient2d(c, d, a), _orient2d(c, d, b)
            hit |= (o1 * o2 < -eps * eps) & (o3 * o4 < -eps * eps)

    def strictly_inside(T, x):
        s = [_orient2d(T[:, k], T[:, (k + 1) % 3], x) for k in range(3)]
        return ((s[0] > eps) & (s[1] > eps) & (s[2] > eps)) | ((s[0] < -eps) & (s[1] < -eps) & (s[2] < -eps))

    for k in range(3):
        hit |= strictly_inside(P2, Q2[:, k]) | strictly_inside(Q2, P2[:, k])
    return hit


def candidate_pairs(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Triangle pairs (k, 2), i < j, whose bounding boxes overlap, in ascending (i, j) order.

    Broad phase on the boxes' circumscribed balls: overlapping boxes have centres within
    r_i + r_j <= 2 max(r_i, r_j), so every pair lies in the ball of radius 2 r about its larger
    triangle's centre. Each query scales with its own triangle, so graded surfaces stay cheap (a
    grid sized by the mean extent crowded thousands of tiny triangles into one cell)."""
    if len(tris) < 2:
        return np.zeros((0, 2), np.int64)
    p = points[tris]
    lo, hi = p.min(axis=1), p.max(axis=1)
    centre, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1)
    slack = 1e-12 * (float(np.ptp(centre, axis=0).max()) + float(radius.max()))  # rounding of centres
    near = cKDTree(centre).query_ball_point(centre, 2.0 * radius + slack, return_sorted=False)
    counts = np.fromiter(map(len, near), np.int64, len(near))
    first = np.repeat(np.arange(len(tris), dtype=np.int64), counts)
    second = np.fromiter(itertools.chain.from_iterable(near), np.int64, int(counts.sum()))
    i, j = np.minimum(first, second), np.maximum(first, second)
    t = len(tris)
    key = np.unique((i * t + j)[i != j])
    pr = np.stack([key // t, key % t], axis=1)
    ok = np.all((lo[pr[:, 0]] <= hi[pr[:, 1]]) & (lo[pr[:, 1]] <= hi[pr[:, 0]]), axis=1)
    return pr[ok]


def intersecting_pairs(points: np.ndarray, tris: np.ndarray, *, rel_eps: float = 1e-10) -> np.ndarray:
    """Pairs of triangles (k, 2) that intersect other than along a shared vertex or edge.

    Args:
        points: (n, 3). tris: (t, 3). rel_eps: tolerance of the orientation tests, relative to
            the cube of the mean edge length.
    Returns:
        (k, 2) int64 triangle index pairs.

    Example:
        >>> intersecting_pairs(mesh.points, mesh.triangles).shape[0] == 0
    """
    points = np.asarray(points, float)
    tris = np.asarray(tris, np.int64)
    if points.ndim != 2 or points.shape[1] != 3 or tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"expected points (n, 3) and triangles (t, 3), got {points.shape}, {tris.shape}.")
    if len(tris) < 2:
        return np.zeros((0, 2), np.int64)
    pr = candidate_pairs(points, tris)
    A, B = tris[pr[:, 0]], tris[pr[:, 1]]
    shared = (A[:, :, None] == B[:, None, :]).sum(axis=(1, 2))
    edge = np.linalg.norm(points[tris[:, 1]] - points[tris[:, 0]], axis=1).mean()
    eps = rel_eps * edge**3
    P, Q = points[A], points[B]
    nP = cross3(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    nQ = cross3(Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0])
    hit = np.zeros(len(pr), bool)
    # disjoint pairs: any edge crossing the other triangle, or coplanar overlap
    m = shared == 0
    for X, Y in ((P, Q), (Q, P)):
        for i in range(3):
            hit[m] |= _segment_crosses_triangle(X[m, i], X[m, (i + 1) % 3], Y[m, 0], Y[m, 1], Y[m, 2], eps)
    oq = np.stack([_orient3d(P[:, 0], P[:, 1], P[:, 2], Q[:, k]) for k in range(3)], axis=1)
    coplanar = np.all(np.abs(oq) <= eps, axis=1) & (shared < 2)
    if coplanar.any():
        axis = np.argmax(np.abs(nP[coplanar]), axis=1)
        cp = np.flatnonzero(coplanar)
        ov = _coplanar_overlap(P[cp], Q[cp], axis, eps ** (2 / 3))
        hit[cp] |= ov  # with a shared vertex only strict crossings / strictly inner vertices count
    # pairs sharing one vertex: the opposite edge of each against the other triangle
    m = np.flatnonzero(shared == 1)
    if m.size:
        for X, Y, XA, YB in ((P, Q, A, B), (Q, P, B, A)):
            own = ~(XA[m][:, :, None] == YB[m][:, None, :]).any(axis=2)
            k = np.argmax(~own, axis=1)  # the shared vertex of X
            p = X[m, (k + 1) % 3]
            q = X[m, (k + 2) % 3]
            hit[m] |= _segment_crosses_triangle(p, q, Y[m, 0], Y[m, 1], Y[m, 2], eps)
    # pairs sharing an edge: folded onto each other
    m = shared == 2
    cos = np.einsum("ij,ij->i", nP, nQ) / np.maximum(np.linalg.norm(nP, axis=1) * np.linalg.norm(nQ, axis=1), 1e-300)
    hit |= m & (cos < -1 + 1e-9)
    return pr[hit]

