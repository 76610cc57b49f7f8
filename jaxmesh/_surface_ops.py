"""NumPy topology of triangulated surfaces (paper 4.4): edge tables, 1-to-4 refinement with
conforming closure, quality-raising edge flips, and cutting by the box planes.

Never imports jax. Triangles are (t, 3) int64 with a consistent orientation, which every
operation here preserves.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from ._quality import cell_quality, cross3
from ._slivers import _star_rows, _stars


def half_edges(tris: np.ndarray, n: int):
    """Edges of a triangulated surface, each once.

    Args:
        tris: (t, 3) int. n: number of points.
    Returns:
        (edges (e, 2) sorted rows, tri_edge (t, 3) edge id of half-edge k = (tri[k], tri[k+1])).
    """
    a = tris.reshape(-1)
    b = tris[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b) * n + np.maximum(a, b)
    uniq, inv = np.unique(key, return_inverse=True)
    return np.stack([uniq // n, uniq % n], axis=1), inv.reshape(-1, 3)


def edge_pairs(tris: np.ndarray, n: int):
    """Interior edges of a manifold surface with their two triangles.

    Returns:
        (u, v, c, d, t1, t2): edge u-v, t1 = (u, v, c) in its orientation, t2 = (v, u, d).
    """
    t = len(tris)
    ti = np.repeat(np.arange(t), 3)
    u, v, w = tris.reshape(-1), tris[:, [1, 2, 0]].reshape(-1), tris[:, [2, 0, 1]].reshape(-1)
    key = np.minimum(u, v) * n + np.maximum(u, v)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.flatnonzero((ks[:-1] == ks[1:]) & np.r_[True, ks[1:-1] != ks[:-2]])
    i, j = order[first], order[first + 1]
    return u[i], v[i], w[i], w[j], ti[i], ti[j]


def refine(points: np.ndarray, tris: np.ndarray, split: np.ndarray):
    """Split the marked edges at their midpoints; triangles with 1, 2 or 3 split edges become 2, 3
    or 4 (the regular 1-to-4 of Fig. 11), which keeps the mesh conforming without a closure pass.

    Args:
        points: (n, 3). tris: (t, 3). split: (e,) bool over ``half_edges(tris, n)[0]``.
    Returns:
        (points (n + s, 3) with midpoints appended (not projected), tris, parents (s, 2) edge of each new point).
    """
    n = len(points)
    edges, te = half_edges(tris, n)
    new_id = np.full(len(edges), -1, np.int64)
    new_id[split] = n + np.arange(int(split.sum()))
    mid = 0.5 * (points[edges[split, 0]] + points[edges[split, 1]])
    m = new_id[te]  # (t, 3) midpoint of half-edge k or -1
    cnt = (m >= 0).sum(axis=1)
    out = [tris[cnt == 0]]
    rows = np.arange(len(tris))
    # one split edge: rotate it to position 0
    r = rows[cnt == 1]
    k = np.argmax(m[r] >= 0, axis=1)
    v = np.stack([tris[r, (k + s) % 3] for s in range(3)], axis=1)
    mk = m[r, k]
    out += [np.stack([v[:, 0], mk, v[:, 2]], 1), np.stack([mk, v[:, 1], v[:, 2]], 1)]
    # two split edges: rotate the unsplit one to position 2
    r = rows[cnt == 2]
    k = (np.argmax(m[r] < 0, axis=1) + 1) % 3
    v = np.stack([tris[r, (k + s) % 3] for s in range(3)], axis=1)
    m0, m1 = m[r, k], m[r, (k + 1) % 3]
    out += [np.stack([m0, v[:, 1], m1], 1), np.stack([v[:, 0], m0, m1], 1), np.stack([v[:, 0], m1, v[:, 2]], 1)]
    r = rows[cnt == 3]
    a, b, c = tris[r].T
    m0, m1, m2 = m[r].T
    out += [np.stack(x, 1) for x in ((a, m0, m2), (m0, b, m1), (m2, m1, c), (m0, m1, m2))]
    return np.vstack([points, mid]), np.vstack(out).astype(np.int64), edges[split]


def _normals(p):
    """Unit normals; 0 for a flat triangle. The truss relaxation passes float32 points, in which
    1e-300 is 0: a flat candidate of flip_edges gave 0 / 0 (the RuntimeWarning of the surfaces)."""
    nrm = cross3(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), np.finfo(nrm.dtype).tiny)


def flip_edges(
    points: np.ndarray,
    tris: np.ndarray,
    allowed: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    *,
    max_rounds: int = 20,
    min_cos: float = 0.5,
    tol: float = 1e-6,
    on_plane: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """Flip edges of a closed surface where the smaller quality of the two triangles rises.

    A flip needs a nearly flat pair (normals' cosine > min_cos before and after), a new edge that
    does not exist yet and end vertices of degree > 3 (the surface stays a manifold). With
    on_plane, a flip that would lay a triangle flat on a box plane (three trace nodes, where the
    surface grazes the plane) is refused: the box face would hold the same triangle after the cut.

    Args:
        points: (n, 3). tris: (t, 3) oriented. allowed: optional (t1, t2) -> (k,) bool, pairs of
            triangles whose common edge may flip (e.g. not a trace edge).
        on_plane: optional (n, 3) bool, coordinate a of the node held exactly on a box plane.
    Returns:
        (triangles, number of flips).
    """
    tri = np.array(tris, dtype=np.int64, copy=True)
    n = len(points)
    total = 0
    for _ in range(max_rounds):
        u, v, c, d, t1, t2 = edge_pairs(tri, n)
        ok = (c != d) if allowed is None else (c != d) & allowed(t1, t2)
        deg = np.bincount(tri.reshape(-1), minlength=n)
        ok &= (deg[u] > 3) & (deg[v] > 3)
        n1, n2 = _normals(points[tri[t1]]), _normals(points[tri[t2]])
        ok &= np.sum(n1 * n2, axis=1) > min_cos
        new1 = np.stack([u, d, c], 1)
        new2 = np.stack([d, v, c], 1)
        m1, m2 = _normals(points[new1]), _normals(points[new2])
        ok &= (np.sum(m1 * m2, 1) > min_cos) & (np.sum(m1 * (n1 + n2), 1) > 0) & (np.sum(m2 * (n1 + n2), 1) > 0)
        if on_plane is not None:
            ok &= ~(in_one_box_plane(points, on_plane, new1) | in_one_box_plane(points, on_plane, new2))
        q = cell_quality(points, tri)
        gain = np.minimum(cell_quality(points, new1), cell_quality(points, new2)) - np.minimum(q[t1], q[t2])
        cand = np.flatnonzero(ok & (gain > tol))
        if cand.size == 0:
            break
        # a closed surface: its interior edges u-v are all of its edges
        flipped = apply_flips(tri, (u, v, c, d, t1, t2), cand[np.argsort(-gain[cand])], np.stack([u, v], 1))
        total += flipped
        if flipped == 0:
            break
    return tri, total


def apply_flips(tri: np.ndarray, pairs, order: np.ndarray, edges: np.ndarray) -> int:
    """Flip, in place, the edges u-v of the rows `order` of pairs = (u, v, c, d, t1, t2) (from
    `edge_pairs`), in that order, to c-d: t1 becomes (u, d, c), t2 (d, v, c). A flip is skipped when
    one of its triangles already changed in this call or when the edge c-d exists (it would make
    the surface non-manifold). edges: (e, 2) every edge of tri. Returns the number of flips."""
    u, v, c, d, t1, t2 = pairs
    n = int(tri.max()) + 1
    existing = set((np.minimum(edges[:, 0], edges[:, 1]) * n + np.maximum(edges[:, 0], edges[:, 1])).tolist())
    used = np.zeros(len(tri), bool)
    flipped = 0
    for g in order:
        a, b = t1[g], t2[g]
        key = min(c[g], d[g]) * n + max(c[g], d[g])
        if used[a] or used[b] or key in existing:
            continue
        used[a] = used[b] = True
        existing.add(key)
        tri[a], tri[b] = (u[g], d[g], c[g]), (d[g], v[g], c[g])
        flipped += 1
    return flipped


def plane_chords(points: np.ndarray, tris: np.ndarray, on_plane: np.ndarray):
    """`edge_pairs` rows (u, v, c, d, t1, t2) of the edges whose ends lie on one box plane while
    both their triangles lie strictly on one side of it: the surface touches the plane along a
    segment that is no trace. Seen beside a shallow cut cap: a chord skipping a trace node, with a
    degree-3 node tenting over the sliver between chord and trace, one of its triangles folded
    (the surface then crossed itself there). Flipping the chord removes it.

    Args:
        points: (n, 3). tris: (t, 3). on_plane: (n, 3) bool, coordinate a held exactly on a box plane.
    """
    u, v, c, d, t1, t2 = edge_pairs(tris, len(points))
    chord = np.zeros(len(u), bool)
    for a in range(3):
        plane = points[u, a]
        same = on_plane[u, a] & on_plane[v, a] & (points[v, a] == plane)
        side_c, side_d = np.sign(points[c, a] - plane), np.sign(points[d, a] - plane)
        chord |= same & (side_c == side_d) & (side_c != 0)
    return tuple(x[chord] for x in (u, v, c, d, t1, t2))


def star_ring(tris: np.ndarray, node: int) -> tuple[np.ndarray, list[int]] | None:
    """(the ids of the node's triangles, its ring of neighbours in their orientation: triangle
    (node, ring[i], ring[i + 1])), or None where the star is no closed disc (a node on the border of
    an open surface, or a pinched star)."""
    star = np.flatnonzero((tris == node).any(axis=1))
    if not len(star):
        return None
    following = {}
    for t in star:
        a, b, c = tris[t].tolist()
        u, v = (b, c) if a == node else (c, a) if b == node else (a, b)
        if u in following:
            return None
        following[u] = v
    ring = [next(iter(following))]
    for _ in range(len(following) - 1):
        ring.append(following.get(ring[-1], -1))
    if following.get(ring[-1]) != ring[0] or len(set(ring)) != len(ring):
        return None
    return star, ring


def hole_fillings(tris: np.ndarray, node: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ways to remove `node` from a surface: (ids of the triangles removed, triangles filling the
    hole), the hole being the node's star, or its star and the triangle beyond one ring edge, filled
    by a fan from each polygon vertex (orientation kept). Fillings with an edge or a triangle the
    surface already has elsewhere are left out (it would no longer be a manifold). Empty where
    `star_ring` is None."""
    found = star_ring(tris, node)
    if found is None:
        return []
    star, ring = found
    holes = [(star, ring)]
    near = np.flatnonzero(np.isin(tris, ring).any(axis=1))  # every triangle looked at below, apexes' added
    local = tris[near]
    for i, (a, b) in enumerate(zip(ring, ring[1:] + ring[:1])):
        beyond = near[(local == a).any(axis=1) & (local == b).any(axis=1) & ~(local == node).any(axis=1)]
        if len(beyond) != 1:
            continue  # a border edge of an open surface
        apex = int(np.setdiff1d(tris[beyond[0]], (a, b))[0])
        if apex not in ring:
            holes.append((np.append(star, beyond), ring[: i + 1] + [apex] + ring[i + 1:]))
    if len(holes) > 1:
        near = np.flatnonzero(np.isin(tris, sorted({v for _, polygon in holes for v in polygon})).any(axis=1))
        local = tris[near]
    fillings = []
    for removed, polygon in holes:
        k = len(polygon)
        around = near[np.isin(local, polygon).any(axis=1)]
        around = around[~np.isin(around, removed)]
        for j in range(k):
            fan = np.array([(polygon[j], polygon[(j + i) % k], polygon[(j + i + 1) % k]) for i in range(1, k - 1)])
            diagonals = [(polygon[j], polygon[(j + i) % k]) for i in range(2, k - 1)]
            if any(((tris[around] == p).any(axis=1) & (tris[around] == q).any(axis=1)).any() for p, q in diagonals):
                continue
            if (np.sort(fan, axis=1)[:, None] == np.sort(tris[around], axis=1)[None]).all(axis=2).any():
                continue  # a triangle the surface has back to back: a pocket of zero volume
            fillings.append((removed, fan))
    return fillings


def drop_unused_nodes(points: np.ndarray, tris: np.ndarray, *per_node: np.ndarray):
    """(points, tris, *per_node) without the nodes no triangle uses, renumbered."""
    used = np.unique(tris)
    remap = np.full(len(points), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (points[used], remap[tris], *(a[used] for a in per_node))


def plane_flags(points: np.ndarray, box) -> np.ndarray:
    """(n, 3) bool: coordinate a is exactly on a box plane k * L_a (set so by construction)."""
    L = np.asarray(box, dtype=float)
    return points == np.round(points / L) * L


def touching_plane_nodes(points: np.ndarray, tris: np.ndarray, on_plane: np.ndarray, box) -> np.ndarray:
    """(n, 3) bool: node on the box plane k L_a that has no neighbour strictly on one of its sides.

    Such a node touches the plane without the surface crossing it (a cap collapsed away, a bump
    snapped onto it): after wrapping it exists on one face only, without its periodic translate.
    """
    L = np.asarray(box, dtype=float)
    edges, _ = half_edges(tris, len(points))
    u, v = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    out = np.zeros(on_plane.shape, bool)
    for a in range(3):
        plane = np.round(points[:, a] / L[a]) * L[a]
        offset = points[v, a] - plane[u]
        above = np.zeros(len(points), bool)
        below = np.zeros(len(points), bool)
        above[u[offset > 0]] = True
        below[u[offset < 0]] = True
        out[:, a] = on_plane[:, a] & ~(above & below)
    return out


def snap_candidates(points, tris, on_plane, axis: int, value: float, tol: float) -> np.ndarray:
    """Vertices within tol of the plane x_axis = value to snap onto it, chosen greedily (closest
    first) so that no triangle gets all three vertices on the plane."""
    dist = np.abs(points[:, axis] - value)
    cand = np.flatnonzero((dist < tol) & ~on_plane[:, axis])
    if cand.size == 0:
        return cand
    flag = on_plane[:, axis] & (points[:, axis] == value)
    vt = [[] for _ in range(len(points))]
    near = np.flatnonzero(np.isin(tris, cand).any(axis=1))
    for t in near:
        for k in tris[t]:
            vt[k].append(t)
    chosen = []
    for i in cand[np.argsort(dist[cand])]:
        if all(np.count_nonzero(flag[tris[t]]) < 2 for t in vt[i]):
            flag[i] = True
            chosen.append(i)
    return np.asarray(chosen, np.int64)


def cut_plane(points, tris, on_plane, axis: int, value: float):
    """Split the triangles crossing the plane x_axis = value; new vertices lie on the plane
    (exactly), linearly interpolated (the caller projects them onto the level set).

    Args:
        points: (n, 3). tris: (t, 3). on_plane: (n, 3) bool plane flags.
    Returns:
        (points, tris, on_plane, new (k,) ids of the new vertices).
    """
    n = len(points)
    x = points[:, axis]
    s = np.where(on_plane[:, axis] & (x == value), 0, np.sign(x - value)).astype(np.int64)
    edges, te = half_edges(tris, n)
    cross = s[edges[:, 0]] * s[edges[:, 1]] < 0
    if not cross.any():
        return points, tris, on_plane, np.zeros(0, np.int64)
    e = edges[cross]
    pa, pb = points[e[:, 0]], points[e[:, 1]]
    t = (value - pa[:, axis]) / (pb[:, axis] - pa[:, axis])
    new = pa + t[:, None] * (pb - pa)
    flags = on_plane[e[:, 0]] & on_plane[e[:, 1]]
    new = np.where(flags, pa, new)  # shared planes keep their exact coordinate
    new[:, axis] = value
    flags[:, axis] = True
    new_id = np.full(len(edges), -1, np.int64)
    new_id[cross] = n + np.arange(len(e))
    m = new_id[te]
    keep = (m < 0).all(axis=1)
    out = [tris[keep]]
    for r in np.flatnonzero(~keep):
        a = tris[r]
        k = int(np.flatnonzero(m[r] >= 0)[0])
        if (m[r] >= 0).sum() == 1:  # the opposite vertex is on the plane
            v0, v1, v2 = a[k], a[(k + 1) % 3], a[(k + 2) % 3]
            mk = m[r, k]
            out.append(np.array([[v0, mk, v2], [mk, v1, v2]]))
            continue
        # two crossing edges: rotate the lone vertex to position 1 (edges k, k+1 cross)
        k = (int(np.flatnonzero(m[r] < 0)[0]) + 1) % 3
        v0, v1, v2 = a[k], a[(k + 1) % 3], a[(k + 2) % 3]
        m0, m1 = m[r, k], m[r, (k + 1) % 3]
        out.append(np.array([[m0, v1, m1], [v0, m0, m1], [v0, m1, v2]]))
    points = np.vstack([points, new])
    on_plane = np.vstack([on_plane, flags])
    return points, np.vstack(out).astype(np.int64), on_plane, n + np.arange(len(e))


def triangle_cells(points: np.ndarray, tris: np.ndarray, box) -> np.ndarray:
    """(t, 3) int periodic cell of each triangle (floor of its centroid / L)."""
    L = np.asarray(box, dtype=float)
    return np.floor(points[tris].mean(axis=1) / L).astype(np.int64)


def straddling(points: np.ndarray, tris: np.ndarray, box) -> np.ndarray:
    """(t,) bool: triangles whose vertices are not all in the closed cell of their centroid."""
    L = np.asarray(box, dtype=float)
    c = triangle_cells(points, tris, box)
    lo, hi = c[:, None, :] * L, (c[:, None, :] + 1) * L
    p = points[tris]
    return ((p < lo) | (p > hi)).any(axis=(1, 2))


def in_one_box_plane(points, on_plane, tris) -> np.ndarray:
    """(t,) bool: triangles whose three vertices lie on one box plane (same axis, same value).
    on_plane: (n, 3) bool, coordinate a of the node held exactly on a box plane."""
    flags = on_plane[tris].all(axis=1)
    p = points[tris]
    return (flags & (p[:, 0] == p[:, 1]) & (p[:, 1] == p[:, 2])).any(axis=1)


def _collapse_shapes_ok(points, tris, on_plane, pairs, n: int, min_cos: float, min_quality: float,
                        max_length: np.ndarray | None) -> np.ndarray:
    """(c, 2) bool: whether collapsing pairs[:, 0] <- pairs[:, 1] (column 0) or pairs[:, 1] <-
    pairs[:, 0] (column 1) keeps the moved triangles' shape (`collapse_edges`' geometric checks)."""
    keep = np.concatenate([pairs[:, 0], pairs[:, 1]])
    drop = np.concatenate([pairs[:, 1], pairs[:, 0]])
    by, off = _stars(tris, n)
    rows, owner = _star_rows(by, off, drop)
    old = tris[rows]
    moved = ~np.any(old == keep[owner][:, None], axis=1)  # the two triangles on the edge vanish
    old, owner = old[moved], owner[moved]
    new = np.where(old == drop[owner][:, None], keep[owner][:, None], old)
    bad = in_one_box_plane(points, on_plane, new)  # a piece beyond a plane would fold flat onto it
    bad |= np.sum(_normals(points[old]) * _normals(points[new]), axis=1) < min_cos
    bad |= cell_quality(points, new) < min_quality
    if max_length is not None:  # the ring's farthest node from the kept one
        far = np.linalg.norm(points[new] - points[keep[owner]][:, None], axis=2).max(axis=1)
        bad |= far > np.concatenate([max_length, max_length])[owner]
    return (np.bincount(owner, bad, minlength=len(keep)) == 0).reshape(2, -1).T


def collapse_edges(points, tris, on_plane, short: np.ndarray, max_length: np.ndarray | None = None, *,
                   min_cos: float = 0.5, min_quality: float = 0.2):
    """Collapse the marked edges (shortest first) by removing one end vertex into the other.

    The removed vertex's box planes must be planes of the kept one, so traces and box edges stay
    put. A collapse is skipped when it would break the manifold (the ends share a neighbour other
    than the two opposite vertices, or an opposite vertex drops to degree 3), turn a triangle by
    more than acos(min_cos), leave one below min_quality or lay one flat on a box plane (the piece
    beyond it would vanish with its trace). One vertex star changes at most once per call; the
    caller iterates. With max_length, a collapse that would make an edge longer than max_length
    is skipped (refinement would split it again: the mesh would coarsen).

    Args:
        points: (n, 3). tris: (t, 3). on_plane: (n, 3) bool. short: (e,) bool over ``half_edges(tris, n)[0]``.
        max_length: optional (e,) longest edge a collapse of each edge may create.
    Returns:
        (points, tris, on_plane) with the removed vertices dropped, and the number of collapses.
    """
    n = len(points)
    edges, _ = half_edges(tris, n)
    cand = np.flatnonzero(short)
    if cand.size == 0:
        return points, tris, on_plane, 0
    length = np.linalg.norm(points[edges[cand, 0]] - points[edges[cand, 1]], axis=1)
    # A collapse is only tried where no earlier one touched its ring, so its triangles are the
    # input's: the shape checks are evaluated for every candidate at once.
    shape_ok = _collapse_shapes_ok(points, tris, on_plane, edges[cand], n, min_cos, min_quality,
                                   None if max_length is None else max_length[cand])
    pos = np.full(len(edges), -1)
    pos[cand] = np.arange(len(cand))
    # plain Python sets: the stars hold ~6 triangles, where NumPy calls cost more than the work
    tri = tris.tolist()
    star = [[] for _ in range(n)]
    for t, (a, b, c) in enumerate(tri):
        star[a].append(t), star[b].append(t), star[c].append(t)
    planes = [frozenset(np.flatnonzero(row).tolist()) for row in on_plane]
    alive = np.ones(len(tri), bool)
    touched = np.zeros(n, bool)
    removed = np.zeros(n, bool)
    done = 0
    for e in cand[np.argsort(length)]:
        u, v = int(edges[e, 0]), int(edges[e, 1])
        for keep, drop in ((u, v), (v, u)):
            if not planes[drop] <= planes[keep] or any(points[drop, a] != points[keep, a] for a in planes[drop]):
                continue  # a trace / box-edge vertex only merges into one on the same planes
            around = [t for t in star[drop] if alive[t]]
            ring_drop = {w for t in around for w in tri[t]}
            if any(touched[w] for w in ring_drop):
                continue
            on_edge = [t for t in around if keep in tri[t]]
            if len(on_edge) != 2:
                continue
            opposite = {w for t in on_edge for w in tri[t]} - {keep, drop}
            ring_keep = {w for t in star[keep] if alive[t] for w in tri[t]}
            if len(opposite) != 2 or (ring_keep & ring_drop) - {keep, drop} != opposite:
                continue  # the link condition: the collapse would pinch the surface
            if min(sum(alive[t] for t in star[w]) for w in opposite) <= 3:
                continue
            if not shape_ok[pos[e], int(keep != u)]:
                continue
            moved = [t for t in around if t not in on_edge]
            for t in moved:
                tri[t] = [keep if w == drop else w for w in tri[t]]
                star[keep].append(t)
            alive[on_edge] = False
            touched[list(ring_drop | ring_keep)] = True
            removed[drop] = True
            done += 1
            break
    if done == 0:
        return points, tris, on_plane, 0
    keep_ids = np.flatnonzero(~removed)
    remap = np.full(n, -1, np.int64)
    remap[keep_ids] = np.arange(len(keep_ids))
    return points[keep_ids], remap[np.asarray(tri, np.int64)[alive]], on_plane[keep_ids], done


def boundary_edges(tris: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges of an open surface used by one triangle only.

    Returns:
        (edges (b, 2) in their triangle's orientation, tri (b,) that triangle, slot (b,): the edge is
        (tri[slot], tri[slot + 1])).
    """
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    once = np.flatnonzero(counts[inv] == 1)
    return e[once], once % len(tris), once // len(tris)


class TraceMismatch(ValueError):
    """The open boundaries of a surface on two opposite box planes cannot be made translates."""


def _find(parent: list, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _nearest_segment(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points q (k, 2): index of the nearest segment a-b (m, 2) and the parameter along it."""
    ab = b - a
    t = np.einsum("kmd,md->km", q[:, None] - a[None], ab) / np.maximum(np.einsum("md,md->m", ab, ab), 1e-300)
    t = np.clip(t, 0.0, 1.0)
    d = np.linalg.norm(q[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    j = np.argmin(d, axis=1)
    return j, t[np.arange(len(q)), j]


def match_opposite_traces(points, tris, on_plane, box, axes):
    """Make an open surface's boundary on x_a = L the exact translate of its boundary on x_a = 0.

    A percolating inclusion's surface, closed off beyond the box and cut by the planes x_a = 0 and
    L, ends on two traces of one periodic curve, discretised independently. Per axis in `axes`,
    nodes of the two traces that are mutual nearest neighbours within half a trace segment become
    one periodic pair (the x_a = L node takes the x_a = 0 node's other coordinates); every other
    trace node is inserted into the opposite trace's nearest segment (its triangle split in two).
    Nodes on a box edge pair up along both of its planes.

    Args:
        points: (n, 3) unwrapped along the other axes. tris: (t, 3) open surface inside
            [0, L_a] along each a in axes. on_plane: (n, 3) bool. box: (3,). axes: the axes.
    Returns:
        (points, tris, on_plane): opposite traces equal as point sets and as segments.
    Raises:
        TraceMismatch: a box-edge node without its partner, or traces that still differ.
    """
    L = np.asarray(box, float)
    points, tris, on_plane = points.copy(), tris.copy(), on_plane.copy()
    for a in axes:  # plane coordinates exactly 0 or L
        points[on_plane[:, a], a] = np.round(points[on_plane[:, a], a] / L[a]) * L[a]
    tris = remove_trace_backtracks(points, tris, on_plane, box, axes)
    parent = list(range(len(points)))

    def trace(a, value):
        e, t, s = boundary_edges(tris, len(points))
        on = on_plane[e, a].all(axis=1) & (points[e, a] == value).all(axis=1)
        return e[on], t[on], s[on]

    for a in axes:
        other = [k for k in range(3) if k != a]
        (e0, t0, s0), (e1, t1, s1) = trace(a, 0.0), trace(a, L[a])
        if not len(e0) and not len(e1):
            continue
        if not len(e0) or not len(e1):
            raise TraceMismatch(f"the surface ends on x_{a} = {'L' if len(e1) else '0'} only")
        sides = []
        for e in (e0, e1):
            nodes = np.unique(e)
            seg = np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1)
            spacing = np.full(len(points), np.inf)
            np.minimum.at(spacing, e[:, 0], seg)
            np.minimum.at(spacing, e[:, 1], seg)
            sides.append((nodes, points[nodes][:, other], spacing[nodes]))
        (n0, u0, h0), (n1, u1, h1) = sides
        d01, j01 = cKDTree(u1).query(u0)
        _, j10 = cKDTree(u0).query(u1)
        pair = (j10[j01] == np.arange(len(n0))) & (d01 < 0.5 * np.minimum(h0, h1[j01]))
        for i, j in zip(n0[pair], n1[j01[pair]]):
            parent[_find(parent, int(j))] = _find(parent, int(i))
        single0 = np.ones(len(n0), bool)
        single0[pair] = False
        single1 = np.ones(len(n1), bool)
        single1[j01[pair]] = False
        inserts = []  # (triangle, slot, parameter, new node)
        for nodes, single, e, t, s, value in ((n0, single0, e1, t1, s1, L[a]), (n1, single1, e0, t0, s0, 0.0)):
            src = nodes[single]
            if not len(src):
                continue
            if (on_plane[src].sum(axis=1) > 1).any():
                raise TraceMismatch(f"a trace node on a box edge has no partner across x_{a}")
            j, par = _nearest_segment(points[src][:, other], points[e[:, 0]][:, other], points[e[:, 1]][:, other])
            new = np.arange(len(points), len(points) + len(src))
            q = points[src].copy()
            q[:, a] = value
            points = np.vstack([points, q])
            on_plane = np.vstack([on_plane, on_plane[src]])
            for i, k in zip(src, new):
                parent.append(int(k))
                parent[int(k)] = _find(parent, int(i))
            inserts += list(zip(t[j].tolist(), s[j].tolist(), par.tolist(), new.tolist()))
        tris = _split_boundary_edges(tris, inserts)
    # one position per class of periodic copies: the other coordinates of its first member
    roots = np.array([_find(parent, i) for i in range(len(points))])
    for k in range(3):
        free = ~(on_plane[:, k] & np.isin(k, axes))
        points[free, k] = points[roots[free], k]
    for a in axes:
        e0 = trace(a, 0.0)[0]
        e1 = trace(a, L[a])[0]
        key = lambda e: {tuple(sorted(map(tuple, np.delete(points[pair], a, axis=1).tolist()))) for pair in e}  # noqa: E731
        if key(e0) != key(e1):
            raise TraceMismatch(f"the traces on x_{a} = 0 and x_{a} = L still differ after matching")
    return points, tris, on_plane


# a trace turning back at a node by over 120 degrees along an edge under half its other edge: a
# zigzag of the cut (a smooth trace turns a few tens of degrees per segment)
_BACKTRACK_COS, _BACKTRACK_RATIO = -0.5, 0.5


def remove_trace_backtracks(points, tris, on_plane, box, axes, passes: int = 5) -> np.ndarray:
    """Collapse the shorter edge at every node where a trace on a box plane x_a = 0 or L turns back
    on itself (a fold of the surface along the plane, a fraction of a segment long): inserting the
    opposite trace's nodes into a zigzag cannot make the two traces equal. Nodes on a box edge stay;
    a collapse that would leave the fan around the kept node folded is skipped. Returns the
    triangles (collapsed nodes are left unreferenced)."""
    L = np.asarray(box, float)
    tris = tris.copy()
    for _ in range(passes):
        e = boundary_edges(tris, len(points))[0]
        drop = {}
        for a in axes:
            other = [k for k in range(3) if k != a]
            for value in (0.0, L[a]):
                ea = e[on_plane[e, a].all(axis=1) & (points[e, a] == value).all(axis=1)]
                nxt, prv = dict(ea.tolist()), {j: i for i, j in ea.tolist()}
                for v in nxt:
                    u, w = prv.get(v), nxt[v]
                    if u is None or on_plane[v].sum() > 1 or v in drop or {u, w} & drop.keys():
                        continue
                    d1, d2 = (points[v] - points[u])[other], (points[w] - points[v])[other]
                    n1, n2 = np.linalg.norm(d1), np.linalg.norm(d2)
                    if d1 @ d2 < _BACKTRACK_COS * n1 * n2 and min(n1, n2) < _BACKTRACK_RATIO * max(n1, n2):
                        drop[v] = u if n1 < n2 else w
        if not drop:
            break
        for v, keep in drop.items():
            around = np.flatnonzero((tris == v).any(axis=1))
            moved = np.where(tris[around] == v, keep, tris[around])
            alive = (moved[:, 0] != moved[:, 1]) & (moved[:, 1] != moved[:, 2]) & (moved[:, 2] != moved[:, 0])
            t = moved[alive]
            normal = np.cross(points[t[:, 1]] - points[t[:, 0]], points[t[:, 2]] - points[t[:, 0]])
            if (normal @ normal.sum(axis=0) <= 0).any():
                continue
            tris[around] = moved
        tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])]
    return tris


def _split_boundary_edges(tris: np.ndarray, inserts: list) -> np.ndarray:
    """Split boundary edge `slot` of triangle t at the nodes inserted there (ordered by parameter):
    (i, j, k) -> (i, m1, k), (m1, m2, k), ..., (mr, j, k)."""
    if not inserts:
        return tris
    by_tri: dict[int, list] = {}
    for t, s, par, m in inserts:
        by_tri.setdefault(t, []).append((s, par, m))
    out, drop = [], []
    for t, items in by_tri.items():
        if len({s for s, _, _ in items}) > 1:
            raise TraceMismatch("a triangle with two edges on one trace (a flat piece in the box plane)")
        s = items[0][0]
        i, j, k = tris[t, s], tris[t, (s + 1) % 3], tris[t, (s + 2) % 3]
        chain = [i] + [m for _, _, m in sorted(items, key=lambda x: x[1])] + [j]
        out += [[chain[q], chain[q + 1], k] for q in range(len(chain) - 1)]
        drop.append(t)
    keep = np.ones(len(tris), bool)
    keep[drop] = False
    return np.vstack([tris[keep], np.asarray(out, np.int64)])
