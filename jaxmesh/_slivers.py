"""Tet quality optimisation and sliver removal (paper 4.7) by local operations that never touch a
surface triangle; surface nodes move only when a `_surface_slide.SurfaceSlide` lets them slide
(interface nodes on their level set, box-face nodes in their plane with their periodic copy). NumPy only.

(a) smoothing: interior vertices (and sliding surface nodes, in their tangent planes) move to
raise the worst and the mean quality of their stars (many at once: sets of vertices that share no tet);
(b) flips: edge removal (3-2, 4-4, 5-6, 6-8, 7-10) and 2-3 flips whose removed faces are not surface
triangles, applied when they raise the worst quality of the tets they replace;
(c) Steiner points: a new interior vertex in a local Delaunay cavity bounded by the surface.
"""

from __future__ import annotations

import numpy as np

from ._mesh import facet_table
from ._quality import TET_EDGES, cross3, dihedral_angles
from ._volume_recover import in_sorted, triangle_keys

__all__ = ["min_dihedral", "tet_quality", "colour_classes", "smooth_vertices", "improve_topology",
           "insert_steiner"]


_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])  # face k is opposite vertex k


def min_dihedral(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(m,) the worst dihedral angle of each tet in degrees: min(angle, 180 - angle) over its edges."""
    if not len(cells):
        return np.zeros(0)
    d = dihedral_angles(points, cells)
    return np.minimum(d, 180.0 - d).min(axis=1)


def _stars(cells: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex -> cells (tets or triangles), CSR (cell ids sorted by vertex, offsets (n + 1,))."""
    corners, offsets = _star_corners(cells, n)
    return corners // cells.shape[1], offsets


def _star_corners(cells: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """`_stars` as flat corner ids (cell * k + the vertex's local index), offsets (n + 1,)."""
    flat = cells.ravel()
    return np.argsort(flat, kind="stable"), np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n))])


# ----------------------------------------------------------------------------- optimisation-based smoothing
def _norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def _six_volumes(p: np.ndarray) -> np.ndarray:
    """Six times the signed volumes of tets p (m, 4, 3)."""
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], cross3(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))


def tet_quality(p: np.ndarray) -> np.ndarray:
    """Signed radius ratio 3 r_in / r_circ of tets p (m, 4, 3): negative when inverted, 0 when flat."""
    # coordinate-major (4, 3, m): every product below is on contiguous rows, no stacking (1.5x faster)
    return _quality_cm(np.ascontiguousarray(np.moveaxis(np.asarray(p, dtype=float), 0, -1)))


def _quality_cm(x: np.ndarray, opposite_area2: np.ndarray | None = None) -> np.ndarray:
    """`tet_quality` of coordinate-major tets x (4, 3, m) (or a sequence of four (3, m) vertex arrays).
    opposite_area2: optional (m,) twice the area of the face x[1] x[2] x[3], when known."""
    a, b, c = x[1] - x[0], x[2] - x[0], x[3] - x[0]
    bc, ca, ab = _cross_rows(b, c), _cross_rows(c, a), _cross_rows(a, b)
    six_v = _dot_rows(a, bc)
    if opposite_area2 is None:
        opposite = _cross_rows(x[2] - x[1], x[3] - x[1])
        opposite_area2 = np.sqrt(_dot_rows(opposite, opposite))
    area2 = opposite_area2 + sum(np.sqrt(_dot_rows(v, v)) for v in (bc, ca, ab))  # 2 x area
    num = _dot_rows(a, a) * bc + _dot_rows(b, b) * ca + _dot_rows(c, c) * ab
    # r_in = 6V / (2 A2), r_circ = |num| / (2 * 6V)  =>  3 r_in / r_circ = 6 (6V)^2 / (A2 |num|)
    den = np.maximum(area2 * np.sqrt(_dot_rows(num, num)), np.finfo(float).tiny)
    return 6.0 * six_v * np.abs(six_v) / den


def _cross_rows(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross product of coordinate-major vectors (3, m)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _dot_rows(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _edges(cells: np.ndarray) -> np.ndarray:
    """Unique undirected edges (k, 2) of tets."""
    e = np.sort(cells[:, TET_EDGES].reshape(-1, 2), axis=1)
    n = int(e.max(initial=0)) + 1
    key = np.unique(e[:, 0] * n + e[:, 1])  # packed int64: np.unique(axis=0) sorts a structured copy, ~5x slower
    return np.stack([key // n, key % n], axis=1)


def colour_classes(edges: np.ndarray, active: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Split the active vertices into sets with no edge inside a set (Luby rounds, vectorised).

    Two vertices of one set never share a tet, so their stars can move at the same time.
    """
    rng = np.random.default_rng(seed)
    prio = rng.random(len(active))
    left = active.copy()
    out = []
    a, b = edges[:, 0], edges[:, 1]
    while left.any():
        best = np.where(left, prio, -1.0)
        nb_max = np.full(len(active), -1.0)  # the highest priority among the remaining neighbours
        np.maximum.at(nb_max, a, best[b])
        np.maximum.at(nb_max, b, best[a])
        pick = left & (prio > nb_max)
        out.append(np.flatnonzero(pick))
        left &= ~pick
    return out


def _star_rows(by: np.ndarray, off: np.ndarray, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells of the stars of verts (CSR from `_stars`) and the index into verts owning each."""
    counts = off[verts + 1] - off[verts]
    owner = np.repeat(np.arange(len(verts)), counts)
    start = np.repeat(off[verts] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return by[start + np.arange(counts.sum())], owner


def _circumcentres_p(p: np.ndarray) -> np.ndarray:
    """Circumcentres of tets p (m, 4, 3); a flat tet gives its centroid (finite, meaningless).

    Closed form p0 + (|a|^2 b x c + |b|^2 c x a + |c|^2 a x b) / (2 a . b x c), faster than
    batched 3x3 solves on the smoothing stars."""
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    bc = cross3(b, c)
    six_v = np.einsum("ij,ij->i", a, bc)
    num = (np.einsum("ij,ij->i", a, a)[:, None] * bc + np.einsum("ij,ij->i", b, b)[:, None] * cross3(c, a)
           + np.einsum("ij,ij->i", c, c)[:, None] * cross3(a, b))
    flat = np.abs(six_v) <= 1e-300
    return np.where(flat[:, None], p.mean(axis=1), p[:, 0] + num / (2 * np.where(flat, 1.0, six_v))[:, None])


def smooth_vertices(points: np.ndarray, cells: np.ndarray, free: np.ndarray, sweeps: int = 4,
                    seed: int = 0, slide=None) -> tuple[np.ndarray, int]:
    """Move free vertices to raise the worst and the mean quality of their stars (fixed topology).

    Per vertex the candidates are its neighbours' centroid, the volume-weighted circumcentre of its
    star (ODT), steps up the gradient of its worst tet and up the gradient of the star's mean. The
    best candidate by W min(q_min, TAU) + q_mean of the star is taken when min(q_min, TAU) does not
    drop and every tet stays positive. Sets of vertices that share no tet move together
    (`colour_classes`).

    With `slide` (a `_surface_slide.SurfaceSlide`) its surface nodes move too: candidates are taken
    in their tangent planes, a move must also keep their surface triangles' angles
    (`SurfaceSlide.keeps_triangles`), a box-face node moves with its periodic copy (one joint star),
    and after each sweep the moved interface nodes are projected back onto their level set
    (`SurfaceSlide.project`, which undoes what the projection would invert).

    Args:
        points: (n, 3); cells: (m, 4) positive tets; free: (n,) bool movable vertices; sweeps: passes.
        slide: optional SurfaceSlide (surface nodes that may slide on their level set or box plane).
    Returns:
        (new points, number of accepted moves).
    """
    points = np.array(points, dtype=float, copy=True)
    cells = np.asarray(cells, dtype=np.int64)
    n = len(points)
    corners, off = _star_corners(cells, n)
    by = corners // 4
    edges = _edges(cells)
    both = np.concatenate([edges, edges[:, ::-1]])
    neighbours = both[np.argsort(both[:, 0], kind="stable"), 1]  # vertex -> neighbours, CSR like _stars
    deg = np.bincount(both[:, 0], minlength=n)
    nb_off = np.concatenate([[0], np.cumsum(deg)])
    movable = free if slide is None else free | slide.mask
    colour_edges = edges if slide is None else slide.contract(edges)
    moves = 0
    for sweep in range(sweeps):
        before = points.copy() if slide is not None else None
        accepted = 0
        for verts in colour_classes(colour_edges, movable & (deg > 0), seed + sweep):
            accepted += _smooth_class(points, cells, corners, off, neighbours, nb_off, verts, slide)
        if slide is not None:
            accepted -= slide.project(points, before, cells, by, off)
        moves += accepted
        if accepted <= 0:
            break
    return points, moves


# Per local index of the moving vertex, the other three in an order that keeps the tet's orientation
# when the moving vertex goes first (an even permutation).
_FIXED_AFTER = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _star_eval(fixed, opposite, owner, starts, x):
    """Minimum and mean signed quality of each star with its vertex at x (k, 3), and every row's.

    fixed (3, 3, r): per star tet the other three vertices, coordinate-major, positive after the
    moving vertex (`_FIXED_AFTER`); opposite (r,): twice their triangle's area, which the move
    keeps; owner (r,) sorted, each star's rows beginning at starts (k,). The moving vertex goes
    first, so the tets are not copied per candidate.
    """
    q = _quality_cm((x[owner].T, fixed[0], fixed[1], fixed[2]), opposite)
    qmin = np.minimum.reduceat(q, starts)  # ufunc.at is ~10x slower
    qmean = np.add.reduceat(q, starts) / np.diff(np.append(starts, len(q)))
    return qmin, qmean, q


# Smoothing objective: W * min(star min quality, TAU) + star mean quality, and the min(., TAU) may not
# drop. Stars worse than TAU are pushed up; better ones trade nothing for the mean (0.4 / 0.2 measured best).
TAU, W = 0.4, 0.2
# Gradient steps, fractions of the mean edge length at the vertex (measured: finer lists gain nothing).
WORST_STEPS, MEAN_STEPS = (0.3, 0.03), (0.1, 0.03, 0.01)


def _joint_stars(corners, off, neighbours, nb_off, points, verts, slide):
    """Star rows of verts (tet ids, owner index into verts sorted, the local index of the vertex that
    moves in each tet, the shift that brings the tet into the owner's frame or None) and neighbour
    positions (with owner). A sliding 0-face node's star joins its periodic copy's, shifted by -L e_a.
    corners, off: `_star_corners` of the tets."""
    star, owner = _star_rows(corners, off, verts)
    nbr, nb_owner = _star_rows(neighbours, nb_off, verts)
    nb_points = points[nbr]
    has = np.zeros(0, np.int64) if slide is None else np.flatnonzero(slide.partner[verts] >= 0)
    if not len(has):
        return star // 4, owner, star % 4, None, nb_points, nb_owner
    copies = slide.partner[verts[has]]
    cstar, cown = _star_rows(corners, off, copies)
    cnbr, cnb_own = _star_rows(neighbours, nb_off, copies)
    shift = np.concatenate([np.zeros((len(star), 3)), slide.shift[verts[has[cown]]]])
    star, owner = np.concatenate([star, cstar]), np.concatenate([owner, has[cown]])
    order = np.argsort(owner, kind="stable")  # `_star_eval` reduces over runs of one owner
    nb_points = np.concatenate([nb_points, points[cnbr] - slide.shift[verts[has[cnb_own]]]])
    nb_owner = np.concatenate([nb_owner, has[cnb_own]])
    star = star[order]
    return star // 4, owner[order], star % 4, shift[order], nb_points, nb_owner


def _smooth_class(points, cells, corners, off, neighbours, nb_off, verts, slide=None) -> int:
    k = len(verts)
    rows, owner, local, shift, nb_points, nb_owner = _joint_stars(corners, off, neighbours, nb_off, points, verts,
                                                                  slide)
    x0 = points[verts].copy()
    p0 = points[cells[rows]] if shift is None else points[cells[rows]] - shift[:, None, :]
    fixed = np.ascontiguousarray(np.transpose(p0[np.arange(len(rows))[:, None], _FIXED_AFTER[local]], (1, 2, 0)))
    face = _cross_rows(fixed[1] - fixed[0], fixed[2] - fixed[0])
    opposite = np.sqrt(_dot_rows(face, face))
    starts = np.flatnonzero(np.diff(owner, prepend=-1))
    best_min, best_mean, q = _star_eval(fixed, opposite, owner, starts, x0)
    base_mean = best_mean
    best_x = x0.copy()
    # worst tet of each star, and a length scale (mean edge length from the vertex)
    at_min = np.flatnonzero(q == best_min[owner])
    worst = at_min[np.unique(owner[at_min], return_index=True)[1]]  # first worst row per star
    deg = np.maximum(np.bincount(nb_owner, minlength=k), 1)
    scale = np.bincount(nb_owner, _norm(nb_points - x0[nb_owner]), minlength=k) / deg
    cands = []
    # neighbours' centroid
    cands.append(np.stack([np.bincount(nb_owner, nb_points[:, j], minlength=k) for j in range(3)], 1) / deg[:, None])
    # ODT: volume-weighted circumcentres of the star
    vol = np.abs(_six_volumes(p0))
    cc = _circumcentres_p(p0)
    w = np.bincount(owner, vol, minlength=k)
    odt = np.stack([np.bincount(owner, vol * cc[:, j], minlength=k) for j in range(3)], 1) / np.maximum(w, 1e-300)[:, None]
    cands.append(odt)
    # gradient of the worst tet's quality with respect to the vertex (central differences)
    pw, lw = p0[worst], local[worst]
    g = np.zeros((k, 3))
    eps = 1e-4 * scale
    for j in range(3):
        for s in (1.0, -1.0):
            pp = pw.copy()
            pp[np.arange(k), lw, j] += s * eps
            g[:, j] += s * tet_quality(pp)
    sliding = None if slide is None else slide.tangent_frame(points, verts)
    if sliding is not None:  # steps along the surface: the gradients' normal parts would be projected away
        g = sliding.tangential(g)
    g /= np.maximum(np.linalg.norm(g, axis=1), 1e-300)[:, None]
    for step in WORST_STEPS:
        cands.append(x0 + step * scale[:, None] * g)
    gm = np.zeros((k, 3))  # gradient of the star's mean quality (forward differences)
    for j in range(3):
        x = x0.copy()
        x[:, j] += eps
        gm[:, j] = _star_eval(fixed, opposite, owner, starts, x)[1] - base_mean
    if sliding is not None:
        gm = sliding.tangential(gm)
    gm /= np.maximum(np.linalg.norm(gm, axis=1), 1e-300)[:, None]
    for step in MEAN_STEPS:
        cands.append(x0 + step * scale[:, None] * gm)
    for x in cands:
        if sliding is not None:
            x = x0 + sliding.tangential(x - x0)
        qmin, qmean, _ = _star_eval(fixed, opposite, owner, starts, x)
        better = (qmin > 0) & (np.minimum(qmin, TAU) >= np.minimum(best_min, TAU)) & (
            W * np.minimum(qmin, TAU) + qmean > W * np.minimum(best_min, TAU) + best_mean + 1e-9)
        if sliding is not None and better.any():
            better &= sliding.keeps_triangles(x)
        best_min = np.where(better, qmin, best_min)
        best_mean = np.where(better, qmean, best_mean)
        best_x[better] = x[better]
    moved = np.any(best_x != x0, axis=1)
    points[verts] = best_x
    if shift is not None:  # the periodic copies follow (in-plane moves: exact translates)
        has = np.flatnonzero(slide.partner[verts] >= 0)
        points[slide.partner[verts[has]]] = best_x[has] + slide.shift[verts[has]]
    return int(moved.sum())


# ----------------------------------------------------------------------------- topological improvement
def _polygon_triangulations(n: int) -> np.ndarray:
    """All triangulations of a convex n-gon (vertices 0..n-1), (k, n - 2, 3), triangles in ring order."""
    def rec(vs):
        if len(vs) < 3:
            return [[]]
        out = []
        a, b = vs[0], vs[-1]
        for i in range(1, len(vs) - 1):  # the triangle on edge (a, b) has apex vs[i]
            for left in rec(vs[: i + 1]):
                for right in rec(vs[i:]):
                    out.append([(a, vs[i], b)] + left + right)
        return out
    return np.array(rec(list(range(n))), dtype=np.int64).reshape(-1, n - 2, 3)


_TRIANGULATIONS = {n: _polygon_triangulations(n) for n in range(3, 8)}


def _triangle_index(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct triangles (c, 3) of all triangulations of an n-gon and each triangulation as
    indices into them (k, n - 2): each candidate tet is evaluated once."""
    tris = _TRIANGULATIONS[n]
    uniq, inv = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
    return uniq, inv.reshape(tris.shape[:2])


_TRIANGLE_INDEX = {n: _triangle_index(n) for n in _TRIANGULATIONS}


def _sorted_keys(items: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Packed keys of sorted vertex tuples (rows of items (m, k, d)), sorted, and the row of each."""
    s = np.sort(items, axis=2).reshape(-1, items.shape[2])
    key = s[:, 0]
    for j in range(1, s.shape[1]):
        key = key * n + s[:, j]
    order = np.argsort(key, kind="stable")
    return key[order], order // items.shape[1]


# Edge rings of this size or more are only tried around tets below TAU: on the coarse Table-1 mesh the
# rings of 5-7 gave a fraction of a percent of the removals, all around such tets, at most of the cost.
_LARGE_RING = 5


def _edge_candidates(points, cells, q, edges, protected, tkeys, towner, worst=None, batch: int = 16384):
    """Edge removals around the given edges (k, 2): (gain, removed tets (k, n), new tets) per ring size.

    worst: optional (k,) bool, the edges of tets below TAU; rings of _LARGE_RING tets or more are
    tried only around those. Edges go in batches: a ring of 7 has 35 candidate triangles and 70
    candidate tets, and all edges of the bad tets at once held ~2 GB on a 1M-tet mesh.
    """
    n = len(points)
    key = edges[:, 0] * n + edges[:, 1]
    lo, hi = np.searchsorted(tkeys, key), np.searchsorted(tkeys, key, side="right")
    qbar = q.mean()
    out = []
    for size in _TRIANGLE_INDEX:
        sel_all = np.flatnonzero((hi - lo == size) & (True if worst is None or size < _LARGE_RING else worst))
        parts = [_ring_removals(points, cells, q, qbar, edges[sel], lo[sel], size, protected, towner)
                 for sel in np.array_split(sel_all, -(-len(sel_all) // batch))] if len(sel_all) else []
        parts = [x for x in parts if x is not None]
        if parts:
            out.append(tuple(np.concatenate(col) for col in zip(*parts)))
    return out


def _ring_removals(points, cells, q, qbar, edges, lo, size, protected, towner):
    """`_edge_candidates` for edges (k, 2) with rings of `size` tets starting at towner[lo]; None if none apply."""
    n = len(points)
    tris, index = _TRIANGLE_INDEX[size]
    p, r = edges[:, 0], edges[:, 1]
    ring_tets = towner[lo[:, None] + np.arange(size)]  # (k, size)
    c = cells[ring_tets]
    pairs = c[(c != p[:, None, None]) & (c != r[:, None, None])].reshape(len(edges), size, 2)
    ring, ok = _chain(pairs)
    # faces (p, r, o) around the edge must not be surface triangles
    faces = np.stack([np.broadcast_to(p[:, None], ring.shape), np.broadcast_to(r[:, None], ring.shape), ring], -1)
    ok &= ~_protected_rows(faces, protected, n)
    if not ok.any():
        return None
    p, r, ring, ring_tets = p[ok], r[ok], ring[ok], ring_tets[ok]
    flip = _six_volumes(points[np.stack([p, r, ring[:, 0], ring[:, 1]], 1)]) < 0
    ring[flip] = ring[flip, ::-1]  # (p, r, o_i, o_i+1) positive: then (a, b, c, r) is positive
    tri = ring[:, tris]  # (k, c, 3): every triangle of the ring, with r above and p below
    k, c = tri.shape[:2]
    up = np.concatenate([tri, np.broadcast_to(r[:, None, None], (k, c, 1))], -1)
    down = np.concatenate([tri[..., [0, 2, 1]], np.broadcast_to(p[:, None, None], (k, c, 1))], -1)
    score = np.minimum(tet_quality(points[up.reshape(-1, 4)]), tet_quality(points[down.reshape(-1, 4)]))
    qual = score.reshape(k, c)[:, index].min(axis=2)  # (k, triangulations)
    chosen = index[np.argmax(qual, axis=1)]  # (k, size - 2) triangle ids of the max-min triangulation
    rows = np.arange(k)[:, None]
    tets = np.concatenate([up[rows, chosen], down[rows, chosen]], axis=1)
    gain = _flip_gain(q[ring_tets], tet_quality(points[tets.reshape(-1, 4)]).reshape(k, -1), qbar)
    good = gain > 0
    return gain[good], ring_tets[good], tets[good]


def _flip_gain(old: np.ndarray, new: np.ndarray, qbar: float) -> np.ndarray:
    """Gain of replacing tets of qualities old (k, a) by new (k, b); <= 0 means no.

    Where the worst old tet is below TAU the worst must rise (gain 1 + rise: these go first);
    otherwise the worst must stay above TAU and the mesh's mean quality must rise: the new tets'
    sum exceeds the old one's by more than qbar (the current mean) per added tet.
    """
    old_min, new_min = old.min(axis=1), new.min(axis=1)
    rise = new_min - old_min
    dsum = new.sum(axis=1) - old.sum(axis=1) - (new.shape[1] - old.shape[1]) * qbar
    return np.where(old_min < TAU, np.where(rise > 1e-9, 1.0 + rise, -1.0),
                    np.where((new_min >= TAU) & (dsum > 1e-9), dsum, -1.0))


def _protected_rows(faces: np.ndarray, protected: np.ndarray, n: int) -> np.ndarray:
    """(k,) bool: some triangle of faces (k, j, 3) is protected."""
    keys = triangle_keys(faces.reshape(-1, 3), n).reshape(faces.shape[:2])
    return in_sorted(keys, protected).any(axis=1)


def _chain(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Order the link edges (k, s, 2) around an edge into a cycle (k, s); ok is False where they do
    not close into one cycle of s distinct vertices (an edge on the box faces, say)."""
    k, s, _ = pairs.shape
    rows = np.arange(k)
    ring = np.zeros((k, s), dtype=np.int64)
    used = np.zeros((k, s), bool)
    ring[:, 0], ring[:, 1] = pairs[:, 0, 0], pairs[:, 0, 1]
    used[:, 0] = True
    ok = np.ones(k, bool)
    for step in range(2, s + 1):
        cur = ring[:, step - 1]
        hit = ~used & ((pairs[..., 0] == cur[:, None]) | (pairs[..., 1] == cur[:, None]))
        ok &= hit.any(axis=1)
        j = np.argmax(hit, axis=1)
        used[rows, j] = True
        a, b = pairs[rows, j, 0], pairs[rows, j, 1]
        nxt = np.where(a == cur, b, a)
        if step < s:
            ring[:, step] = nxt
        else:
            ok &= nxt == ring[:, 0]  # the last link edge closes the cycle
    srt = np.sort(ring, axis=1)
    ok &= np.all(srt[:, 1:] != srt[:, :-1], axis=1)
    return ring, ok


def _face_candidates(points, cells, q, bad, protected, fkeys, fowner):
    """2-3 flips across the faces of the bad tets: (gain, removed pairs (k, 2), new tets (k, 3, 4))."""
    n = len(points)
    faces = cells[bad][:, _FACES].reshape(-1, 3)
    t = np.repeat(bad, 4)
    apex = cells[bad].reshape(-1)  # face k of a tet is the one opposite its vertex k
    key = triangle_keys(faces, n)
    lo, hi = np.searchsorted(fkeys, key), np.searchsorted(fkeys, key, side="right")
    ok = (hi - lo == 2) & ~in_sorted(key, protected)
    faces, t, apex, lo = faces[ok], t[ok], apex[ok], lo[ok]
    a, b = fowner[lo], fowner[lo + 1]
    nb = np.where(a == t, b, a)
    other = cells[nb].sum(axis=1) - faces.sum(axis=1)  # the neighbour's vertex off the face
    f = faces
    cand = np.stack([np.stack([f[:, 0], f[:, 1], apex, other], 1), np.stack([f[:, 1], f[:, 2], apex, other], 1),
                     np.stack([f[:, 2], f[:, 0], apex, other], 1)], 1)  # (k, 3, 4)
    neg = _six_volumes(points[cand[:, 0]]) < 0
    cand[neg] = cand[neg][:, :, [1, 0, 2, 3]]  # the three share the orientation when apex-other crosses the face
    pair = np.stack([t, nb], 1)
    gain = _flip_gain(q[pair], tet_quality(points[cand.reshape(-1, 4)]).reshape(-1, 3), q.mean())
    good = gain > 0
    return gain[good], pair[good], cand[good]


def improve_topology(points: np.ndarray, cells: np.ndarray, protected: np.ndarray, threshold: float = 0.4,
                     passes: int = 4, near: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Edge removals (3-2, 4-4) around tets of quality below threshold; the larger ones (5-6, 6-8,
    7-10) and 2-3 flips around tets below TAU only (elsewhere they almost never gain: `_LARGE_RING`).

    Candidates are evaluated for all bad tets at once; the best gains are applied first, each only
    when none of its tets was removed by an earlier one in the pass (then its ring is unchanged).
    A change must raise the worst quality of the tets it replaces, or, where that is above TAU
    already, raise the mean quality of the mesh (`_flip_gain`). Faces that are surface triangles
    (protected keys, `triangle_keys`) are never removed. `near`: optional (n,) bool; only bad tets
    with a vertex in it are worked on (a local clean-up after Steiner points).

    Returns:
        (new cells, number of changes).
    """
    n = len(points)
    cells = np.asarray(cells, dtype=np.int64).copy()
    protected = np.unique(np.asarray(protected, dtype=np.int64))  # sorted: `in_sorted`
    total = 0
    for _ in range(passes):
        q = tet_quality(points[cells])
        low = q < threshold
        if near is not None:
            low &= near[cells].any(axis=1)
        bad = np.flatnonzero(low)
        if not len(bad):
            break
        tkeys, towner = _sorted_keys(cells[:, TET_EDGES], n)
        fkeys, fowner = _sorted_keys(cells[:, _FACES], n)
        edges = np.sort(cells[bad][:, TET_EDGES].reshape(-1, 2), axis=1)
        worst = np.repeat(q[bad] < TAU, 6)
        key = edges[:, 0] * n + edges[:, 1]
        order = np.lexsort((~worst, key))  # per edge, a worst tet's copy first
        first = np.ones(len(key), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        edges, worst = edges[order][first], worst[order][first]
        cands = _edge_candidates(points, cells, q, edges, protected, tkeys, towner, worst)
        cands.append(_face_candidates(points, cells, q, bad[q[bad] < TAU], protected, fkeys, fowner))
        gains = np.concatenate([c[0] for c in cands])
        if not len(gains):
            break
        ops = [(g, i, j) for i, c in enumerate(cands) for j, g in enumerate(c[0])]
        dead = np.zeros(len(cells), bool)
        new = []
        for _, i, j in sorted(ops, key=lambda o: -o[0]):
            gone = cands[i][1][j]
            if dead[gone].any():
                continue
            dead[gone] = True
            new.append(cands[i][2][j])
        total += len(new)
        cells = np.concatenate([cells[~dead], np.concatenate(new)])
    return cells, total


# ----------------------------------------------------------------------------- Steiner points
def _neighbours(cells: np.ndarray, protected: np.ndarray, n: int) -> np.ndarray:
    """(m, 4) the tet across face k of each tet, -1 where that face is a surface triangle (its key in
    the sorted `protected`) or on the mesh's boundary."""
    table = facet_table(cells, n)
    two, owners = table.pairs()
    open_ = ~in_sorted(triangle_keys(table.facets[two], n), protected)
    ends = np.full((len(table.counts), 2), -1, np.int64)
    ends[two[open_]] = owners[open_]
    ends = ends[table.cell_facet]  # (m, 4, 2): the owners of each tet's face k (cell_facet: opposite vertex k)
    return np.where(ends[..., 0] == np.arange(len(cells))[:, None], ends[..., 1], ends[..., 0])


def _cavity(across, centres, radius2, dead, seed, x, member):
    """Bowyer-Watson cavity of x grown from tet seed across faces that are not protected (`_neighbours`):
    tets whose circumsphere (centres, squared radii) holds x. Returns the tet ids, or None if it meets
    a tet changed in this pass. Grown a layer at a time: near small features the cavities of
    circumcentres hold hundreds of tets, where one Python step per tet cost most of the sliver stage.
    member: (m,) False scratch flags, left False."""
    cav = layer = np.array([seed])
    member[seed] = True
    try:
        while len(layer):
            nb = np.unique(across[layer].ravel())
            nb = nb[nb >= 0]
            nb = nb[~member[nb]]
            nb = nb[np.sum((x - centres[nb]) ** 2, axis=1) < radius2[nb] * (1 - 1e-12)]
            if dead[nb].any():
                return None
            member[nb] = True
            cav, layer = np.concatenate([cav, nb]), nb
        return cav
    finally:
        member[cav] = False


def _fill_cavity(points, cells, cav, x, protected):
    """Tets joining the cavity's boundary faces to x (as vertex len(points)), or None when they do not
    tile the cavity exactly or a surface triangle lies inside it."""
    n = len(points)
    keys = triangle_keys(cells[cav][:, _FACES].reshape(-1, 3), n)
    uniq, count = np.unique(keys, return_counts=True)
    if in_sorted(uniq[count == 2], protected).any():
        return None
    t, k = np.nonzero(np.isin(keys, uniq[count == 1]).reshape(-1, 4))
    star = cells[cav][t].copy()
    star[np.arange(len(t)), k] = n  # orientation kept: positive iff x sees the face from inside
    p = np.concatenate([points, x[None]])
    vol = _six_volumes(p[star])
    if vol.min() <= 0 or abs(vol.sum() - _six_volumes(points[cells[cav]]).sum()) > 1e-9 * vol.sum():
        return None
    return star


def insert_steiner(points: np.ndarray, cells: np.ndarray, protected: np.ndarray, bad: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split bad tets by a new interior vertex with a local Delaunay cavity that never crosses a
    surface triangle. Candidates: the circumcentre and centroid of the tet and of its neighbours
    across non-surface faces; the best is kept when it raises the cavity's worst quality.

    For slivers whose four vertices are on the surface (no vertex can move, no flip applies).

    Args:
        points, cells; protected: `triangle_keys` (n = len(points)) of the surface triangles;
        bad: ids of the tets to split.
    Returns:
        (points with the new vertices appended, cells, ids of the new vertices).
    """
    n = len(points)
    cells = np.asarray(cells, dtype=np.int64)
    protected = np.unique(np.asarray(protected, dtype=np.int64))  # sorted: `in_sorted`
    across = _neighbours(cells, protected, n)
    centres = _circumcentres_p(points[cells])
    radius2 = np.sum((points[cells[:, 0]] - centres) ** 2, axis=1)
    dead, member = np.zeros(len(cells), bool), np.zeros(len(cells), bool)
    new, added = [], []
    for t in (int(v) for v in bad):
        if dead[t]:
            continue
        seeds = [t] + [int(s) for s in across[t] if s >= 0]
        best = None
        for s in seeds:
            p = points[cells[s]]
            for x in (centres[s], p.mean(axis=0)):
                cav = _cavity(across, centres, radius2, dead, t, x, member)
                star = None if cav is None else _fill_cavity(points, cells, cav, x, protected)
                if star is None:
                    continue
                star[star == n] = n + len(added)
                gain = _quality_with(points, new, x, star) - tet_quality(points[cells[cav]]).min()
                if gain > 1e-9 and (best is None or gain > best[0]):
                    best = (gain, cav, star, x)
        if best is None:
            continue
        _, cav, star, x = best
        dead[cav] = True
        new.append((star, x))
        added.append(n + len(added))
    if not added:
        return points, cells, np.zeros(0, np.int64)
    points = np.concatenate([points, np.array([x for _, x in new])])
    return points, np.concatenate([cells[~dead]] + [s for s, _ in new]), np.array(added)


def _quality_with(points, new, x, star):
    """Worst quality of star whose new vertex x follows the vertices added so far (ids >= len(points))."""
    n = len(points)
    extra = np.array([y for _, y in new] + [x])  # not appended to points: that copies all of them per candidate
    p = np.where((star < n)[..., None], points[np.minimum(star, n - 1)], extra[np.maximum(star - n, 0)])
    return tet_quality(p).min()

