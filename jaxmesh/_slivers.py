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
