"""Sliver removal (paper 4.7) by local operations that never touch a surface triangle. NumPy only.

(a) vertex moves: a free vertex of a sliver is pushed away from its opposite face (the ball-vertex
idea, done geometrically) or moved to the centroid of its star, accepted when the worst dihedral
angle of its star improves and every tet stays positive (fixed topology keeps the surface);
(b) 2-3 and 3-2 flips whose removed faces are not surface triangles, accepted when they raise
the worst dihedral angle of the cells they replace.
"""

from __future__ import annotations

import numpy as np

from ._quality import TET_EDGES, dihedral_angles, signed_volumes
from ._volume_recover import triangle_keys

__all__ = ["min_dihedral", "sliver_mask", "improve_vertices", "flip_slivers"]


def min_dihedral(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(m,) the worst dihedral angle of each tet in degrees: min(angle, 180 - angle) over its edges."""
    if not len(cells):
        return np.zeros(0)
    d = dihedral_angles(points, cells)
    return np.minimum(d, 180.0 - d).min(axis=1)


def sliver_mask(points: np.ndarray, cells: np.ndarray, angle: float) -> np.ndarray:
    """(m,) bool: tets with a dihedral angle below ``angle`` degrees (or above 180 - angle)."""
    return min_dihedral(points, cells) < angle


def _stars(cells: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex -> tets, CSR (tet ids sorted by vertex, offsets (n + 1,))."""
    flat = cells.ravel()
    order = np.argsort(flat, kind="stable")
    offsets = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n))])
    return order // 4, offsets


def _score(points: np.ndarray, cells: np.ndarray) -> float:
    """Worst dihedral angle of a few tets, -inf if one is not positive."""
    if np.any(signed_volumes(points, cells) <= 0):
        return -np.inf
    return float(min_dihedral(points, cells).min())


def improve_vertices(points: np.ndarray, cells: np.ndarray, free: np.ndarray, h: np.ndarray, angle: float = 10.0,
                     passes: int = 3) -> tuple[np.ndarray, int]:
    """Move free vertices of slivers to raise the worst dihedral angle of their stars (fixed topology).

    Args:
        points: (n, 3); cells: (m, 4) positive tets; free: (n,) bool movable vertices;
        h: (n,) target sizes at the vertices; angle: sliver threshold (degrees); passes: sweeps.
    Returns:
        (new points, number of accepted moves).
    """
    points = np.array(points, dtype=float, copy=True)
    by, off = _stars(cells, len(points))
    moves = 0
    for _ in range(passes):
        bad = np.flatnonzero(sliver_mask(points, cells, angle))
        if not len(bad):
            break
        accepted = 0
        for t in bad:
            for v in cells[t]:
                if not free[v]:
                    continue
                star = cells[by[off[v]:off[v + 1]]]
                base = _score(points, star)
                if base >= angle:
                    break
                x0 = points[v].copy()
                opp = cells[t][cells[t] != v]
                a, b, c = points[opp]
                nrm = np.cross(b - a, c - a)
                nrm /= max(np.linalg.norm(nrm), 1e-300)
                if np.dot(x0 - a, nrm) < 0:
                    nrm = -nrm
                height = np.dot(x0 - a, nrm)
                push = max(np.sqrt(2.0 / 3.0) * h[v] - height, 0.0)
                ring = np.unique(star)
                cands = [x0 + s * push * nrm for s in (1.0, 0.5, 0.25)]
                cands.append(points[ring[ring != v]].mean(axis=0))
                best, best_x = base, None
                for x in cands:
                    points[v] = x
                    sc = _score(points, star)
                    if sc > best + 1e-9:
                        best, best_x = sc, x.copy()
                points[v] = x0 if best_x is None else best_x
                if best_x is not None:
                    accepted += 1
        moves += accepted
        if not accepted:
            break
    return points, moves


def _oriented(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    tets = np.array(tets, dtype=np.int64)
    neg = signed_volumes(points, tets) < 0
    tets[neg, :2] = tets[neg, 1::-1]
    return tets


def flip_slivers(points: np.ndarray, cells: np.ndarray, protected: np.ndarray, angle: float = 10.0,
                 passes: int = 3) -> tuple[np.ndarray, int]:
    """2-3 and 3-2 flips around slivers that raise the worst dihedral angle locally.

    Args:
        points: (n, 3); cells: (m, 4) positive tets; protected: sorted keys (`triangle_keys`) of the
            faces that must stay (surface triangles); angle: sliver threshold; passes: sweeps.
    Returns:
        (new cells, number of flips).
    """
    n = len(points)
    cells = np.asarray(cells, dtype=np.int64).copy()
    flips = 0
    for _ in range(passes):
        bad = np.flatnonzero(sliver_mask(points, cells, angle))
        if not len(bad):
            break
        by, off = _stars(cells, n)
        dead = np.zeros(len(cells), bool)
        touched = np.zeros(n, bool)
        new = []

        def around(*verts):
            s = by[off[verts[0]]:off[verts[0] + 1]]
            for v in verts[1:]:
                s = s[np.any(cells[s] == v, axis=1)]
            return s

        def is_protected(faces):
            return np.isin(triangle_keys(np.asarray(faces), n), protected).any()

        done = 0
        for t in bad[np.argsort(min_dihedral(points, cells[bad]))]:
            if dead[t] or touched[cells[t]].any():
                continue
            tet = cells[t]
            applied = False
            for i, j in TET_EDGES:  # 3-2: an edge with exactly three tets around it
                p, q = tet[i], tet[j]
                ring = around(p, q)
                if len(ring) != 3 or dead[ring].any() or touched[cells[ring]].any():
                    continue
                others = np.unique(cells[ring][(cells[ring] != p) & (cells[ring] != q)])
                if len(others) != 3 or is_protected([[p, q, o] for o in others]):
                    continue
                # closed ring: each face (p, q, o) is shared by two of the three tets
                if any(len(around(p, q, o)) != 2 for o in others):
                    continue
                cand = _oriented(points, [[*others, p], [*others, q]])
                v_old = np.abs(signed_volumes(points, cells[ring])).sum()
                if abs(np.abs(signed_volumes(points, cand)).sum() - v_old) > 1e-9 * v_old:
                    continue  # pq does not cross the triangle of the three others
                if _score(points, cand) > _score(points, cells[ring]) + 1e-9:
                    dead[ring] = True
                    touched[np.unique(cells[ring])] = True
                    new.append(cand)
                    applied = True
                    break
            if applied:
                done += 1
                continue
            for k in range(4):  # 2-3: across a face that is not a surface triangle
                face = np.delete(tet, k)
                nb = around(*face)
                nb = nb[nb != t]
                if len(nb) != 1 or dead[nb[0]] or touched[cells[nb[0]]].any() or is_protected([face]):
                    continue
                p, q = tet[k], cells[nb[0]][~np.isin(cells[nb[0]], face)][0]
                a, b, c = face
                cand = _oriented(points, [[a, b, p, q], [b, c, p, q], [c, a, p, q]])
                if np.any(np.abs(signed_volumes(points, cand)) <= 0):
                    continue
                # valid only if pq crosses abc: the three new volumes add up to the old two
                old = np.abs(signed_volumes(points, cells[[t, nb[0]]])).sum()
                if abs(np.abs(signed_volumes(points, cand)).sum() - old) > 1e-9 * old:
                    continue
                if _score(points, cand) > _score(points, cells[[t, nb[0]]]) + 1e-9:
                    dead[[t, nb[0]]] = True
                    touched[np.unique(cells[[t, nb[0]]])] = True
                    new.append(cand)
                    done += 1
                    break
        if not done:
            break
        flips += done
        cells = np.concatenate([cells[~dead]] + new)
    return cells, flips


# ----------------------------------------------------------------------------- optimisation-based smoothing
def tet_quality(p: np.ndarray) -> np.ndarray:
    """Signed radius ratio 3 r_in / r_circ of tets p (m, 4, 3): negative when inverted, 0 when flat."""
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    bc, ca, ab = np.cross(b, c), np.cross(c, a), np.cross(a, b)
    six_v = np.einsum("ij,ij->i", a, bc)
    d, e = p[:, 2] - p[:, 1], p[:, 3] - p[:, 1]
    area2 = (np.linalg.norm(bc, axis=1) + np.linalg.norm(ca, axis=1) + np.linalg.norm(ab, axis=1)
             + np.linalg.norm(np.cross(d, e), axis=1))  # twice the total face area
    num = (np.einsum("ij,ij->i", a, a)[:, None] * bc + np.einsum("ij,ij->i", b, b)[:, None] * ca
           + np.einsum("ij,ij->i", c, c)[:, None] * ab)
    # r_in = 6V / (2 A2), r_circ = |num| / (2 * 6V)  =>  3 r_in / r_circ = 6 (6V)^2 / (A2 |num|)
    den = np.maximum(area2 * np.linalg.norm(num, axis=1), np.finfo(float).tiny)
    return 6.0 * six_v * np.abs(six_v) / den


def _edges(cells: np.ndarray) -> np.ndarray:
    """Unique undirected edges (k, 2) of tets."""
    e = np.sort(cells[:, TET_EDGES].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


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
    """Tets of the stars of verts (CSR from `_stars`) and the index into verts owning each."""
    counts = off[verts + 1] - off[verts]
    owner = np.repeat(np.arange(len(verts)), counts)
    start = np.repeat(off[verts] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return by[start + np.arange(counts.sum())], owner


def _circumcentres_p(p: np.ndarray) -> np.ndarray:
    a = p[:, 1:] - p[:, :1]
    rhs = 0.5 * np.sum(a * a, axis=-1)
    det = np.linalg.det(a)
    a = np.where(np.abs(det)[:, None, None] > 0, a, np.eye(3))
    return p[:, 0] + np.linalg.solve(a, rhs[..., None])[..., 0]


def smooth_vertices(points: np.ndarray, cells: np.ndarray, free: np.ndarray, sweeps: int = 4,
                    seed: int = 0) -> tuple[np.ndarray, int]:
    """Move free vertices to raise the worst quality of their stars (fixed topology).

    Per vertex the candidates are its neighbours' centroid, the volume-weighted circumcentre of its
    star (ODT) and steps up the gradient of its worst tet. A candidate is taken when it raises the
    star's minimum quality, or keeps it and raises the star's mean; every tet stays positive.
    Sets of vertices that share no tet move together (`colour_classes`).

    Args:
        points: (n, 3); cells: (m, 4) positive tets; free: (n,) bool movable vertices; sweeps: passes.
    Returns:
        (new points, number of accepted moves).
    """
    points = np.array(points, dtype=float, copy=True)
    cells = np.asarray(cells, dtype=np.int64)
    n = len(points)
    by, off = _stars(cells, n)
    edges = _edges(cells)
    deg = np.bincount(edges.ravel(), minlength=n).astype(float)
    moves = 0
    for sweep in range(sweeps):
        accepted = 0
        for verts in colour_classes(edges, free & (deg > 0), seed + sweep):
            accepted += _smooth_class(points, cells, by, off, edges, deg, verts)
        moves += accepted
        if accepted == 0:
            break
    return points, moves


def _star_eval(points, cells, rows, owner, local, x, k):
    """Minimum and mean signed quality of each of k stars with its vertex at x (k, 3)."""
    p = points[cells[rows]]
    p[np.arange(len(rows)), local] = x[owner]
    q = tet_quality(p)
    qmin = np.full(k, np.inf)
    np.minimum.at(qmin, owner, q)
    qmean = np.bincount(owner, q, minlength=k) / np.maximum(np.bincount(owner, minlength=k), 1)
    return qmin, qmean, q


# Smoothing objective: W * min(star min quality, TAU) + star mean quality, and the min(., TAU) may not
# drop. Stars worse than TAU are pushed up; better ones trade nothing for the mean (0.4 / 0.2 measured best).
TAU, W = 0.4, 0.2


def _smooth_class(points, cells, by, off, edges, deg, verts) -> int:
    k = len(verts)
    rows, owner = _star_rows(by, off, verts)
    local = np.argmax(cells[rows] == verts[owner][:, None], axis=1)
    x0 = points[verts].copy()
    best_min, best_mean, q = _star_eval(points, cells, rows, owner, local, x0, k)
    best_x = x0.copy()
    # worst tet of each star, and a length scale (mean edge length from the vertex)
    worst = np.full(k, -1)
    order = np.lexsort((q, owner))
    first = np.concatenate([[0], np.flatnonzero(np.diff(owner[order])) + 1])
    worst[owner[order[first]]] = rows[order[first]]
    pos = np.full(len(points), -1)
    pos[verts] = np.arange(k)
    scale = np.zeros(k)
    for a, b in ((0, 1), (1, 0)):
        m = pos[edges[:, a]] >= 0
        np.add.at(scale, pos[edges[m, a]], np.linalg.norm(points[edges[m, a]] - points[edges[m, b]], axis=1))
    scale /= np.maximum(deg[verts], 1)
    cands = []
    # neighbours' centroid
    cen = np.zeros((k, 3))
    for a, b in ((0, 1), (1, 0)):
        m = pos[edges[:, a]] >= 0
        np.add.at(cen, pos[edges[m, a]], points[edges[m, b]])
    cands.append(cen / np.maximum(deg[verts], 1)[:, None])
    # ODT: volume-weighted circumcentres of the star
    p = points[cells[rows]]
    vol = np.abs(np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])))
    cc = _circumcentres_p(p)
    w = np.bincount(owner, vol, minlength=k)
    odt = np.stack([np.bincount(owner, vol * cc[:, j], minlength=k) for j in range(3)], 1) / np.maximum(w, 1e-300)[:, None]
    cands.append(odt)
    # gradient of the worst tet's quality with respect to the vertex (central differences)
    pw = points[cells[worst]]
    lw = np.argmax(cells[worst] == verts[:, None], axis=1)
    g = np.zeros((k, 3))
    eps = 1e-4 * scale
    for j in range(3):
        for s in (1.0, -1.0):
            pp = pw.copy()
            pp[np.arange(k), lw, j] += s * eps
            g[:, j] += s * tet_quality(pp)
    g /= np.maximum(np.linalg.norm(g, axis=1), 1e-300)[:, None]
    for step in (0.3, 0.1, 0.03, 0.01):
        cands.append(x0 + step * scale[:, None] * g)
    for x in cands:
        qmin, qmean, _ = _star_eval(points, cells, rows, owner, local, x, k)
        better = (qmin > 0) & (np.minimum(qmin, TAU) >= np.minimum(best_min, TAU)) & (
            W * np.minimum(qmin, TAU) + qmean > W * np.minimum(best_min, TAU) + best_mean + 1e-9)
        best_min = np.where(better, qmin, best_min)
        best_mean = np.where(better, qmean, best_mean)
        best_x[better] = x[better]
    moved = np.any(best_x != x0, axis=1)
    points[verts] = best_x
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


def _ring(cells: np.ndarray, ring: np.ndarray, p: int, q: int) -> list[int] | None:
    """The vertices around edge pq in cyclic order, or None if the tets do not close around it."""
    nxt = {}
    for t in cells[ring]:
        a, b = (int(v) for v in t if v != p and v != q)
        nxt.setdefault(a, []).append(b)
        nxt.setdefault(b, []).append(a)
    if len(nxt) != len(ring) or any(len(v) != 2 for v in nxt.values()):
        return None
    order = [next(iter(nxt))]
    prev = None
    while True:
        a, b = nxt[order[-1]]
        step = b if a == prev else a
        if step == order[0]:
            break
        prev = order[-1]
        order.append(step)
    return order if len(order) == len(ring) else None


def _edge_removal(points: np.ndarray, cells: np.ndarray, ring: np.ndarray, p: int, q: int):
    """Best replacement of the tets around edge pq (2n - 4 tets, Shewchuk's edge removal).

    Returns (tets (2n - 4, 4), their worst quality) or None when the ring is open or too large.
    """
    order = _ring(cells, ring, p, q)
    if order is None or len(order) not in _TRIANGULATIONS:
        return None
    o = np.array(order)
    if signed_volumes(points, np.array([[p, q, o[0], o[1]]]))[0] < 0:
        o = o[::-1]  # ring oriented so that (p, q, o_i, o_i+1) is positive: then (a, b, c, q) is
    tri = o[_TRIANGULATIONS[len(o)]]  # (k, n - 2, 3)
    k = len(tri)
    up = np.concatenate([tri, np.full(tri.shape[:2] + (1,), q)], axis=2)
    down = np.concatenate([tri[..., [0, 2, 1]], np.full(tri.shape[:2] + (1,), p)], axis=2)
    tets = np.concatenate([up, down], axis=1)  # (k, 2n - 4, 4)
    qual = tet_quality(points[tets.reshape(-1, 4)]).reshape(k, -1).min(axis=1)
    best = int(np.argmax(qual))
    return tets[best], float(qual[best])


def improve_topology(points: np.ndarray, cells: np.ndarray, protected: np.ndarray, threshold: float = 0.4,
                     passes: int = 4) -> tuple[np.ndarray, int]:
    """Edge removals (3-2, 4-4, 5-6, 6-8, 7-10) and 2-3 flips around tets of quality below threshold.

    A local change is applied when it raises the worst quality of the tets it replaces; faces that are
    surface triangles (protected keys, `triangle_keys`) are never removed.

    Returns:
        (new cells, number of changes).
    """
    n = len(points)
    cells = np.asarray(cells, dtype=np.int64).copy()
    total = 0
    for _ in range(passes):
        q = tet_quality(points[cells])
        bad = np.flatnonzero(q < threshold)
        if not len(bad):
            break
        bad = bad[np.argsort(q[bad])]
        by, off = _stars(cells, n)
        dead = np.zeros(len(cells), bool)
        new_edges: set = set()
        new = []

        def around(*verts):
            s = by[off[verts[0]]:off[verts[0] + 1]]
            for v in verts[1:]:
                s = s[np.any(cells[s] == v, axis=1)]
            return s

        def fresh(*verts):  # no tet created in this pass holds two of these vertices
            return not any((min(a, b), max(a, b)) in new_edges for i, a in enumerate(verts) for b in verts[i + 1:])

        def protected_any(faces):
            return np.isin(triangle_keys(np.asarray(faces), n), protected).any()

        done = 0
        for t in bad:
            if dead[t]:
                continue
            tet = [int(v) for v in cells[t]]
            best = None  # (gain, removed tets, new tets)
            for i, j in TET_EDGES:
                p, r = tet[i], tet[j]
                if not fresh(p, r):
                    continue
                ring = around(p, r)
                if dead[ring].any():
                    continue
                res = _edge_removal(points, cells, ring, p, r)
                if res is None:
                    continue
                old = q[ring].min()
                if res[1] > old + 1e-9 and (best is None or res[1] - old > best[0]):
                    others = np.unique(cells[ring])
                    others = others[(others != p) & (others != r)]
                    if not protected_any([[p, r, o] for o in others]):
                        best = (res[1] - old, ring, res[0])
            for k in range(4):  # 2-3 across a face
                face = [v for m, v in enumerate(tet) if m != k]
                if not fresh(*face):
                    continue
                nb = around(*face)
                nb = nb[nb != t]
                if len(nb) != 1 or dead[nb[0]]:
                    continue
                a, b, c = face
                p, r = tet[k], int(np.setdiff1d(cells[nb[0]], face)[0])
                cand = _oriented(points, [[a, b, p, r], [b, c, p, r], [c, a, p, r]])
                pair = np.array([t, nb[0]])
                qc = tet_quality(points[cand])
                old_vol = np.abs(signed_volumes(points, cells[pair])).sum()
                if qc.min() <= q[pair].min() + 1e-9 or (best is not None and qc.min() - q[pair].min() <= best[0]):
                    continue
                if abs(np.abs(signed_volumes(points, cand)).sum() - old_vol) > 1e-9 * old_vol:
                    continue  # pr does not cross abc
                if not protected_any([face]):
                    best = (qc.min() - q[pair].min(), pair, cand)
            if best is None:
                continue
            _, gone, tets = best
            dead[gone] = True
            new.append(tets)
            for tt in tets:
                for i, j in TET_EDGES:
                    new_edges.add((min(tt[i], tt[j]), max(tt[i], tt[j])))
            done += 1
        if not done:
            break
        total += done
        cells = np.concatenate([cells[~dead]] + new)
    return cells, total
