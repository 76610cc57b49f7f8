"""Constrained 2D triangulation (NumPy/SciPy only, never imports jax).

The 2D mesher hands this module a planar straight-line graph (``_contours.PSLG``: the interface
polylines and the box edges) plus free interior nodes, and gets back a triangulation in
which every constrained segment is an edge:

- :func:`conforming_delaunay`: scipy Delaunay of all nodes; a missing segment first loses the
  free interior nodes that encroach on it (inside its diametral circle), else it is split at
  its midpoint (interface midpoints are projected back onto the level set by a callback, box
  midpoints are mirrored onto the opposite edge so the boundary stays periodic); repeat.
  Whatever is still missing after ``max_rounds`` is forced in by edge flips.
- :func:`constrained_delaunay`: Delaunay + edge-flip recovery (Sloan 1993) without new nodes,
  the ``triangulate_fn`` of the truss relaxation.
- :func:`flood_fill` / :func:`component_labels`: connected components of triangles across
  non-constrained edges and their majority label.
- :func:`improve_by_flips`: flips of non-constrained edges that raise the smaller quality
  of the two triangles (paper Fig. 12).
- :func:`refine_bad_triangles`: Delaunay refinement (Ruppert 1995) of the triangles the truss
  could not fix (thin gaps between an interface and a box edge, shallow crossings): circumcentres
  inserted, encroached segments split (projected / mirrored), geometric corners left alone.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree

from ._errors import MeshingError
from ._contours import BOX_SEGMENT, PSLG, split_segments
from ._quality import cell_quality
from ._slivers import _star_rows, _stars, colour_classes
from ._surface_ops import half_edges

# ----------------------------------------------------------------------------- basic helpers
def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Twice the signed area of (a, b, c), positive when counter-clockwise."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def edge_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Orientation-free int64 key of the edges (a, b) of an n-node mesh (DESIGN 3: no unique(axis=0))."""
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    return np.minimum(a, b) * n + np.maximum(a, b)


def orient_ccw(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles reordered counter-clockwise (positive signed area)."""
    tri = np.array(triangles, dtype=np.int64, copy=True)
    neg = _orient(points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]) < 0
    tri[neg, 1], tri[neg, 2] = tri[neg, 2], tri[neg, 1].copy()
    return tri


def delaunay_triangles(points: np.ndarray) -> np.ndarray:
    """scipy (Qhull) Delaunay triangles, counter-clockwise, flat ones (collinear hull nodes) dropped.

    Args:
        points: (n, 2). Returns: (m, 3) int64.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 3:
        raise ValueError(f"expected (n >= 3, 2) points, got shape {points.shape}; hint: pass 2D node coordinates")
    tri = orient_ccw(points, Delaunay(points).simplices)
    area = _orient(points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]])
    scale = float(np.ptp(points, axis=0).max()) ** 2
    return tri[area > 1e-14 * scale]


def _half_edges(triangles: np.ndarray, n: int):
    """Directed edges (c, d) of CCW triangles, their owner and opposite vertex, with keys."""
    m = len(triangles)
    c = triangles.reshape(-1)
    d = triangles[:, [1, 2, 0]].reshape(-1)
    u = triangles[:, [2, 0, 1]].reshape(-1)
    owner = np.repeat(np.arange(m), 3)
    return c, d, u, owner, edge_keys(c, d, n)


def interior_edges(triangles: np.ndarray, n: int):
    """Edges shared by two triangles.

    Returns:
        (c, d, u, v, t1, t2, key): the edge (c, d) oriented as in t1 = (c, d, u) (CCW), t2 = (d, c, v),
        each (e,), and the edge keys. Raises MeshingError on an edge in more than two triangles.
    """
    c, d, u, owner, key = _half_edges(triangles, n)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = np.nonzero(ks[1:] == ks[:-1])[0]
    if same.size > 1 and np.any(np.diff(same) == 1):
        raise MeshingError("triangulate", "an edge is shared by more than two triangles (non-manifold)")
    h1, h2 = order[same], order[same + 1]
    return c[h1], d[h1], u[h1], u[h2], owner[h1], owner[h2], ks[same]


def missing_segments(triangles: np.ndarray, segments: np.ndarray, n: int) -> np.ndarray:
    """(s,) bool: the constrained segments that are not an edge of the triangulation."""
    if len(segments) == 0:
        return np.zeros(0, dtype=bool)
    _, _, _, _, keys = _half_edges(triangles, n)
    return ~np.isin(edge_keys(segments[:, 0], segments[:, 1], n), keys)


def conforming_delaunay(
    pslg: PSLG,
    interior: np.ndarray,
    project_fn: Callable,
    *,
    max_rounds: int = 12,
    remove_encroaching: bool = True,
) -> tuple[PSLG, np.ndarray, np.ndarray, dict]:
    """Delaunay triangulation of the PSLG nodes plus free interior nodes containing every segment.

    Each round triangulates, then for every missing segment removes the free interior nodes
    inside its diametral circle (they would be relaxed anyway) or, when none encroach, splits
    the segment (:func:`split_segments`). Segments still missing after ``max_rounds`` are
    forced in by edge flips (:func:`recover_segments_by_flips`).

    Args:
        pslg: constrained nodes and segments. interior: (k, 2) free nodes.
        project_fn: ``(points (k, 2), inclusion_ids (k,)) -> (k, 2)`` projection onto the level sets.
        max_rounds: split/remove rounds before flipping the rest in.
        remove_encroaching: remove encroaching interior nodes before splitting.
    Returns:
        (pslg, interior, triangles, stats): triangles (m, 3) CCW index ``concat(pslg.points, interior)``;
        stats counts the splits, removed nodes and flip-recovered segments.
    """
    interior = np.asarray(interior, dtype=float).reshape(-1, 2)
    stats = {"rounds": 0, "split": 0, "removed": 0, "flip_recovered": 0}
    for _ in range(max_rounds):
        pts = np.vstack([pslg.points, interior])
        tri = delaunay_triangles(pts)
        miss = missing_segments(tri, pslg.segments, len(pts))
        if not miss.any():
            return pslg, interior, tri, stats
        stats["rounds"] += 1
        seg = pslg.segments[miss]
        a, b = pslg.points[seg[:, 0]], pslg.points[seg[:, 1]]
        split = np.ones(len(seg), dtype=bool)
        if remove_encroaching and len(interior):
            mid, rad = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
            hits = cKDTree(interior).query_ball_point(mid, rad * (1.0 + 1e-9))
            drop = np.zeros(len(interior), dtype=bool)
            for k, hit in enumerate(hits):
                if hit:
                    drop[hit] = True
                    split[k] = False
            stats["removed"] += int(drop.sum())
            interior = interior[~drop]
        if split.any():
            stats["split"] += int(split.sum())
            pslg = split_segments(pslg, np.nonzero(miss)[0][split], project_fn)
    pts = np.vstack([pslg.points, interior])
    tri = delaunay_triangles(pts)
    miss = missing_segments(tri, pslg.segments, len(pts))
    if miss.any():
        stats["flip_recovered"] = int(miss.sum())
        tri = recover_segments_by_flips(pts, tri, pslg.segments[miss])
    return pslg, interior, tri, stats


# ----------------------------------------------------------------------------- flip recovery
class SegmentRecoveryError(MeshingError):
    """A constrained segment could not be forced into the triangulation; `segment` holds its two
    node indices, so that a caller can say where (e.g. which inclusion's trace) it failed."""

    def __init__(self, message: str, segment: tuple[int, int]):
        super().__init__("triangulate", message)
        self.segment = segment


def _triangle_boxes(points, triangles) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle the lower and upper corners (m, 2) of its bounding box."""
    p0, p1, p2 = (points[triangles[:, k]] for k in range(3))
    return np.minimum(np.minimum(p0, p1), p2), np.maximum(np.maximum(p0, p1), p2)


def _crossing_edges(points, triangles, a: int, b: int, boxes=None):
    """Edges (c, d) of the triangulation crossing the open segment ab, with their owner triangles.
    boxes: the triangles' `_triangle_boxes`, when the caller keeps them."""
    n = len(points)
    pa, pb = points[a], points[b]
    lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
    # both triangles of a crossing edge meet ab, so the edges shared within the triangles whose
    # boxes meet ab's box hold every crossing edge (and the search is not over the whole mesh)
    t_lo, t_hi = _triangle_boxes(points, triangles) if boxes is None else boxes
    near_tri = np.flatnonzero((t_lo[:, 0] <= hi[0]) & (t_lo[:, 1] <= hi[1]) & (t_hi[:, 0] >= lo[0])
                              & (t_hi[:, 1] >= lo[1]))
    c, d, u, v, t1, t2, _ = interior_edges(triangles[near_tri], n)
    t1, t2 = near_tri[t1], near_tri[t2]
    pc, pd = points[c], points[d]
    near = np.all(np.minimum(pc, pd) <= hi, axis=1) & np.all(np.maximum(pc, pd) >= lo, axis=1)
    near &= (c != a) & (c != b) & (d != a) & (d != b)
    idx = np.nonzero(near)[0]
    o1 = _orient(pa, pb, pc[idx]) * _orient(pa, pb, pd[idx])
    o2 = _orient(pc[idx], pd[idx], pa) * _orient(pc[idx], pd[idx], pb)
    hit = idx[(o1 < 0) & (o2 < 0)]
    # a vertex lying exactly on ab cannot be flipped around
    on = idx[((o1 == 0) & (o2 < 0))]
    return c[hit], d[hit], t1[hit], t2[hit], on.size > 0


def recover_segments_by_flips(points: np.ndarray, triangles: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Force segments into a triangulation by edge flips (Sloan 1993), no new nodes.

    For each segment ab, the edges crossing it are flipped in turn (non-convex quads are
    postponed) until none crosses; always possible in 2D unless a node lies on ab.

    Args:
        points: (n, 2). triangles: (m, 3) CCW. segments: (s, 2) to recover.
    Returns:
        (m, 3) CCW triangles containing every segment. Raises SegmentRecoveryError (a MeshingError)
        if one cannot be recovered.
    """
    points = np.asarray(points, dtype=float)
    tri = np.array(triangles, dtype=np.int64, copy=True)
    n = len(points)
    boxes = _triangle_boxes(points, tri)  # kept up to date through the flips
    for a, b in np.asarray(segments, dtype=np.int64):
        c, d, t1, t2, degenerate = _crossing_edges(points, tri, a, b, boxes)
        if degenerate:
            raise SegmentRecoveryError(f"a node lies on the constrained segment ({a}, {b})", (int(a), int(b)))
        if c.size == 0:
            continue
        # local edge -> owners map over the triangles crossed by ab (flips stay inside them)
        local = {int(t) for t in np.concatenate([t1, t2])}
        owners: dict[int, list[int]] = {}
        for t in local:
            for k in range(3):
                key = int(edge_keys(tri[t, k], tri[t, (k + 1) % 3], n))
                owners.setdefault(key, []).append(t)
        queue = deque((int(x), int(y)) for x, y in zip(c, d))
        budget = 50 * len(queue) + 100
        pa, pb = points[a], points[b]
        while queue:
            budget -= 1
            if budget < 0:
                raise SegmentRecoveryError(f"edge flips did not recover the segment ({a}, {b})", (int(a), int(b)))
            x, y = queue.popleft()
            key = int(edge_keys(x, y, n))
            ta, tb = owners[key]
            # orient: ta = (x, y, u), tb = (y, x, v)
            ra = tri[ta]
            k = int(np.nonzero(ra == x)[0][0])
            if ra[(k + 1) % 3] != y:
                ta, tb = tb, ta
                ra = tri[ta]
                k = int(np.nonzero(ra == x)[0][0])
            u = int(ra[(k + 2) % 3])
            rb = tri[tb]
            v = int(rb[(int(np.nonzero(rb == y)[0][0]) + 2) % 3])
            px, py, pu, pv = points[x], points[y], points[u], points[v]
            if not (_orient(pu, pv, px) * _orient(pu, pv, py) < 0):
                queue.append((x, y))  # quad not strictly convex: try later
                continue
            tri[ta] = (x, v, u)
            tri[tb] = (v, y, u)
            flipped = np.array([ta, tb])
            boxes[0][flipped], boxes[1][flipped] = _triangle_boxes(points, tri[flipped])
            del owners[key]
            for t, e in ((ta, (x, v)), (tb, (v, y)), (ta, (u, x)), (tb, (y, u))):
                ek = int(edge_keys(*e, n))
                lst = owners.setdefault(ek, [])
                other = tb if t == ta else ta
                if other in lst:
                    lst.remove(other)
                if t not in lst:
                    lst.append(t)
            owners[int(edge_keys(u, v, n))] = [ta, tb]
            if u not in (a, b) and v not in (a, b):
                if _orient(pa, pb, pu) * _orient(pa, pb, pv) < 0 and _orient(pu, pv, pa) * _orient(pu, pv, pb) < 0:
                    queue.append((u, v))
    return tri


def constrained_delaunay(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Delaunay triangulation with the segments forced in by flips (no new nodes).

    The triangulate_fn of the truss relaxation: node count fixed, every segment kept.

    Args:
        points: (n, 2). segments: (s, 2). Returns: (m, 3) CCW triangles.
    """
    points = np.asarray(points, dtype=float)
    tri = delaunay_triangles(points)
    miss = missing_segments(tri, segments, len(points))
    if miss.any():
        tri = recover_segments_by_flips(points, tri, segments[miss])
    return tri


# ----------------------------------------------------------------------------- labels
def flood_fill(triangles: np.ndarray, segments: np.ndarray, n_points: int) -> tuple[int, np.ndarray]:
    """Connected components of triangles across edges that are not constrained segments.

    Args:
        triangles: (m, 3). segments: (s, 2) constrained (interface and box) segments. n_points: n.
    Returns:
        (n_components, component (m,) int).
    """
    m = len(triangles)
    _, _, _, _, t1, t2, key = interior_edges(triangles, n_points)
    free = ~np.isin(key, edge_keys(segments[:, 0], segments[:, 1], n_points)) if len(segments) else np.ones(
        key.size, dtype=bool
    )
    graph = coo_matrix((np.ones(int(free.sum())), (t1[free], t2[free])), shape=(m, m))
    return connected_components(graph, directed=False)


def component_labels(
    component: np.ndarray, votes: np.ndarray, weights: np.ndarray | None = None, n_components: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted majority label of every component.

    Args:
        component: (v,) component id of each vote. votes: (v,) int labels. weights: (v,) optional
            weights. n_components: number of components (default: max id + 1).
    Returns:
        (labels (n_components,) int64: 0 where a component got no vote,
        dissent (n_components,): weight share of votes for another non-zero label than the winner).
    """
    component = np.asarray(component, np.int64)
    votes = np.asarray(votes, np.int64)
    w = np.ones(len(votes)) if weights is None else np.asarray(weights, dtype=float)
    n_comp = (int(component.max()) + 1 if component.size else 0) if n_components is None else int(n_components)
    labels, inv = np.unique(np.concatenate([[0], votes]), return_inverse=True)
    tally = np.zeros((n_comp, len(labels)))
    np.add.at(tally, (component, inv[1:]), w)
    best = np.argmax(tally, axis=1)
    total = tally.sum(axis=1)
    other = tally.copy()
    other[np.arange(n_comp), best] = 0.0
    other[:, labels == 0] = 0.0
    dissent = np.divide(other.sum(axis=1), total, out=np.zeros(n_comp), where=total > 0)
    return labels[best], dissent


def interface_sides(triangles: np.ndarray, segments: np.ndarray, segment_inclusion: np.ndarray, n_points: int):
    """The two triangles along every interface segment, with the segment's inclusion id.

    Returns:
        (triangle (2e,), inclusion_id (2e,)): each triangle bordering an interface, once per border.
    """
    iface = segment_inclusion > 0
    keys = edge_keys(segments[iface, 0], segments[iface, 1], n_points)
    inc_of = dict(zip(keys.tolist(), segment_inclusion[iface].tolist()))
    _, _, _, _, t1, t2, key = interior_edges(triangles, n_points)
    hit = np.isin(key, keys)
    inc = np.array([inc_of[k] for k in key[hit].tolist()], dtype=np.int64)
    return np.concatenate([t1[hit], t2[hit]]), np.concatenate([inc, inc])


def distance_to_segments(points: np.ndarray, nodes: np.ndarray, segments: np.ndarray, resolution: float) -> np.ndarray:
    """Distance from points to the union of segments, exact to the segment nearest to a sample.

    Samples every segment every ``resolution`` (KD-tree), then measures the exact distance to the
    segment of the nearest sample: the error is at most resolution / 2.

    Args:
        points: (m, 2). nodes: (n, 2). segments: (s, 2). resolution: sample spacing.
    Returns:
        (m,) distances.
    """
    a, b = nodes[segments[:, 0]], nodes[segments[:, 1]]
    k = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / resolution).astype(np.int64))
    sid = np.repeat(np.arange(len(segments)), k)
    t = (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k) + 0.5) / np.repeat(k, k)
    samples = a[sid] + t[:, None] * (b - a)[sid]
    _, near = cKDTree(samples).query(points)
    s = sid[near]
    ab = b[s] - a[s]
    u = np.clip(np.sum((points - a[s]) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a[s] + u[:, None] * ab), axis=1)


# ----------------------------------------------------------------------------- quality flips
def improve_by_flips(
    points: np.ndarray,
    triangles: np.ndarray,
    segments: np.ndarray,
    *,
    max_rounds: int = 50,
    tol: float = 1e-9,
    angle_floor: float | None = None,
) -> tuple[np.ndarray, int]:
    """Flip non-constrained edges whose flip raises the smaller quality of their two triangles.

    Each round evaluates every interior edge at once and applies a set of non-conflicting
    improving flips (no triangle in two flips), best gain first.

    Args:
        points: (n, 2). triangles: (m, 3) CCW. segments: (s, 2) edges never flipped.
        max_rounds: rounds cap. tol: minimal gain in q.
        angle_floor: if given, a flip may not bring the pair's smallest angle below
            min(its current smallest angle, angle_floor) (q and angles disagree on slivers).
    Returns:
        (triangles (m, 3) CCW, number of flips).
    """
    points = np.asarray(points, dtype=float)
    tri = np.array(triangles, dtype=np.int64, copy=True)
    n = len(points)
    fixed = edge_keys(segments[:, 0], segments[:, 1], n) if len(segments) else np.zeros(0, np.int64)
    total = 0
    for _ in range(max_rounds):
        c, d, u, v, t1, t2, key = interior_edges(tri, n)
        ok = ~np.isin(key, fixed)
        pc, pd, pu, pv = points[c], points[d], points[u], points[v]
        ok &= (_orient(pu, pv, pc) * _orient(pu, pv, pd) < 0) & (_orient(pc, pd, pu) * _orient(pc, pd, pv) < 0)
        idx = np.nonzero(ok)[0]
        if idx.size == 0:
            break
        q = cell_quality(points, tri)
        old = np.minimum(q[t1[idx]], q[t2[idx]])
        new1 = np.stack([c[idx], v[idx], u[idx]], axis=1)
        new2 = np.stack([v[idx], d[idx], u[idx]], axis=1)
        new = np.minimum(cell_quality(points, new1), cell_quality(points, new2))
        gain = new - old
        if angle_floor is not None:
            a_old = np.minimum(triangle_angles(points, tri[t1[idx]]).min(1), triangle_angles(points, tri[t2[idx]]).min(1))
            a_new = np.minimum(triangle_angles(points, new1).min(1), triangle_angles(points, new2).min(1))
            gain[a_new < np.minimum(a_old, angle_floor)] = -1.0
        good = np.nonzero(gain > tol)[0]
        if good.size == 0:
            break
        good = good[np.argsort(-gain[good])]
        used = np.zeros(len(tri), dtype=bool)
        flipped = 0
        for g in good:
            i = idx[g]
            a, b = t1[i], t2[i]
            if used[a] or used[b]:
                continue
            used[a] = used[b] = True
            tri[a], tri[b] = new1[g], new2[g]
            flipped += 1
        total += flipped
    return tri, total


# ----------------------------------------------------------------------------- Delaunay refinement
def triangle_angles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(m, 3) interior angles in degrees, column k at vertex k."""
    return _angles_of(points[triangles])


def smooth_free_nodes(points: np.ndarray, triangles: np.ndarray, n_fixed: int, iters: int = 5) -> np.ndarray:
    """Laplacian smoothing of the nodes from n_fixed on, of ccw triangles: a node moves to its
    neighbours' mean only where no triangle of its star inverts and their smallest angle does not
    drop (so a node never crosses a segment). Nodes that share no triangle move together
    (`colour_classes`); each keeps or rejects its move on its own star.
    """
    points = np.array(points, dtype=float, copy=True)
    triangles = np.asarray(triangles, dtype=np.int64)
    n = len(points)
    if n <= n_fixed or not len(triangles):
        return points
    by, off = _stars(triangles, n)
    edges, _ = half_edges(triangles, n)
    both = np.concatenate([edges, edges[:, ::-1]])
    neighbours = both[np.argsort(both[:, 0], kind="stable"), 1]
    deg = np.bincount(both[:, 0], minlength=n)
    nb_off = np.concatenate([[0], np.cumsum(deg)])
    classes = colour_classes(edges, (np.arange(n) >= n_fixed) & (deg > 0))
    for _ in range(iters):
        for verts in classes:
            rows, owner = _star_rows(by, off, verts)
            nbr, nb_owner = _star_rows(neighbours, nb_off, verts)
            target = np.stack([np.bincount(nb_owner, points[nbr, j], minlength=len(verts))
                               for j in range(2)], 1) / deg[verts][:, None]
            starts = np.flatnonzero(np.diff(owner, prepend=-1))  # owner is sorted, every star non-empty
            star = triangles[rows]
            before = np.minimum.reduceat(triangle_angles(points, star).min(axis=1), starts)
            p = points[star]
            mover = star == verts[owner][:, None]
            p[mover] = target[owner][np.nonzero(mover)[0]]
            e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
            flipped = np.maximum.reduceat((e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] <= 0).astype(np.int8), starts)
            after = np.minimum.reduceat(_angles_of(p).min(axis=1), starts)
            ok = (flipped == 0) & (after >= before)
            points[verts[ok]] = target[ok]
    return points


def _angles_of(p: np.ndarray) -> np.ndarray:
    """(m, 3) interior angles in degrees of triangles given by their corners p (m, 3, 2)."""
    out = np.empty(p.shape[:2])
    for k in range(3):
        u, v = p[:, (k + 1) % 3] - p[:, k], p[:, (k + 2) % 3] - p[:, k]
        out[:, k] = np.degrees(np.arctan2(np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]), np.sum(u * v, axis=1)))
    return out


def circumcenters(p: np.ndarray) -> np.ndarray:
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    ba, ca = b - a, c - a
    d = 2.0 * (ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0])
    nb, nc = np.sum(ba * ba, axis=1), np.sum(ca * ca, axis=1)
    ux = (ca[:, 1] * nb - ba[:, 1] * nc) / d
    uy = (ba[:, 0] * nc - ca[:, 0] * nb) / d
    return a + np.stack([ux, uy], axis=1)


def refine_bad_triangles(
    pslg: PSLG,
    interior: np.ndarray,
    triangles: np.ndarray,
    project_fn: Callable,
    h_fn: Callable,
    *,
    min_angle: float = 20.5,
    min_edge: float = 0.05,
    max_rounds: int = 20,
) -> tuple[PSLG, np.ndarray, np.ndarray, dict]:
    """Delaunay refinement of triangles with an angle below ``min_angle``.

    The circumcentre of each bad triangle is inserted as a free node unless it encroaches on a
    constrained segment (inside its diametral circle) or leaves the box; then that segment is
    split instead (:func:`split_segments`: interface midpoints projected, box midpoints mirrored
    onto the opposite edge). Left alone: a smallest angle enclosed by two constrained segments (a
    geometric corner, e.g. an interface meeting a box edge at a shallow angle) and triangles whose
    shortest edge is below ``min_edge * h`` (ends cascades near such corners).

    Args:
        pslg, interior, triangles: as returned by :func:`conforming_delaunay`.
        project_fn: level-set projection callback (see :func:`split_segments`).
        h_fn: NumPy size function (m, 2) -> (m,).
        min_angle: target smallest angle (degrees). min_edge: fraction of h. max_rounds: cap.
    Returns:
        (pslg, interior, triangles, stats) with stats counting inserted nodes, splits and the
        triangles left below the target.
    """
    box = np.asarray(pslg.box, dtype=float)
    interior = np.asarray(interior, dtype=float).reshape(-1, 2)
    tri = triangles
    stats = {"inserted": 0, "split": 0, "rounds": 0, "left": 0}
    for _ in range(max_rounds):
        pts = np.vstack([pslg.points, interior])
        n = len(pts)
        ang = triangle_angles(pts, tri)
        k = np.argmin(ang, axis=1)
        rows = np.arange(len(tri))
        v, v1, v2 = tri[rows, k], tri[rows, (k + 1) % 3], tri[rows, (k + 2) % 3]
        seg_keys = edge_keys(pslg.segments[:, 0], pslg.segments[:, 1], n)
        corner = np.isin(edge_keys(v, v1, n), seg_keys) & np.isin(edge_keys(v, v2, n), seg_keys)
        p = pts[tri]
        lmin = np.min(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
        hmin = min_edge * h_fn(p.mean(axis=1))
        small = (ang[rows, k] < min_angle) & (lmin > hmin)
        bad = small & ~corner
        stats["left"] = int(np.count_nonzero(ang[rows, k] < min_angle))
        # at a corner, the chord of a curved interface makes the angle smaller than the geometric
        # one: split the interface side (its midpoint goes onto the curve) while it is long enough
        split = set()
        order_k = np.argsort(seg_keys)
        sorted_keys = seg_keys[order_k]
        for t in np.nonzero((ang[rows, k] < min_angle) & corner)[0]:
            for w in (v1[t], v2[t]):
                j = order_k[np.searchsorted(sorted_keys, edge_keys(v[t], w, n))]
                if pslg.segment_inclusion[j] > 0 and np.linalg.norm(pts[w] - pts[v[t]]) > 4 * hmin[t]:
                    split.add(int(j))
        if not bad.any() and not split:
            break
        stats["rounds"] += 1
        # Ruppert: a segment of a bad triangle seen from its apex at more than 90 deg is encroached by
        # that apex; the circumcentre lies across the segment, where inserting it changes nothing
        t_obtuse, col = np.nonzero(bad[:, None] & (ang > 90.0))
        keys = edge_keys(tri[t_obtuse, (col + 1) % 3], tri[t_obtuse, (col + 2) % 3], n)
        pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
        on_segment = sorted_keys[pos] == keys
        split.update(order_k[pos[on_segment]].tolist())
        bad[t_obtuse[on_segment]] = False
        order = np.argsort(ang[bad, k[bad]])  # worst first
        cc = circumcenters(p[bad][order])
        rad = np.linalg.norm(cc - p[bad][order][:, 0], axis=1)
        # a circumcentre on an existing node (one inserted in an earlier round) adds nothing
        fresh = cKDTree(pts).query(cc)[0] > 1e-9 * rad
        # encroachment: inside the diametral circle of a segment
        a, b = pslg.points[pslg.segments[:, 0]], pslg.points[pslg.segments[:, 1]]
        mid, half = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
        tree = cKDTree(mid)
        hits = tree.query_ball_point(cc, half.max() * (1 + 1e-9))
        insert = []
        outside = np.any((cc <= 0.0) | (cc >= box), axis=1)
        for i, hit in enumerate(hits):
            hit = [s for s in hit if np.linalg.norm(cc[i] - mid[s]) < half[s]]
            if hit:
                split.add(min(hit, key=lambda s: np.linalg.norm(cc[i] - mid[s]) / half[s]))
            elif not fresh[i]:
                continue
            elif outside[i]:
                box_seg = np.nonzero(pslg.segment_inclusion == BOX_SEGMENT)[0]
                split.add(int(box_seg[np.argmin(np.linalg.norm(mid[box_seg] - cc[i], axis=1))]))
            else:
                insert.append(i)
        if insert:  # one new node per cluster of nearby circumcentres
            ins = np.asarray(insert)
            keep = []
            taken = cKDTree(cc[ins])
            used = np.zeros(len(ins), dtype=bool)
            for j in range(len(ins)):
                if used[j]:
                    continue
                keep.append(ins[j])
                used[taken.query_ball_point(cc[ins[j]], 0.5 * rad[ins[j]])] = True
            interior = np.vstack([interior, cc[keep]])
            stats["inserted"] += len(keep)
        if split:
            pslg = split_segments(pslg, np.fromiter(split, dtype=np.int64), project_fn)
            stats["split"] += len(split)
        tri = constrained_delaunay(np.vstack([pslg.points, interior]), pslg.segments)
    return pslg, interior, tri, stats
