"""Surface-triangle recovery for the volume step (paper 4.6), NumPy only (never imports jax).

A surface triangle missing from a Delaunay tetrahedralisation is not Delaunay: some node lies in
every sphere through its three vertices, in particular in its smallest circumscribed ball. The
recovery removes free (interior) nodes from those balls and, where surface nodes encroach, splits
the triangle's longest edge at its midpoint (projected back onto the level set for interface
edges, kept on the plane and mirrored on the periodic partner faces for box edges), updating the
SurfaceMesh consistently.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from ._errors import MeshingError
from ._quality import cross3
from ._surface_mesh import INTERFACE, SurfaceMesh

__all__ = [
    "triangle_keys",
    "missing_triangles",
    "point_triangle_distance",
    "encroached_free_nodes",
    "split_edges",
    "levelset_projector",
]


def triangle_keys(tris: np.ndarray, n: int) -> np.ndarray:
    """One int64 key per triangle (sorted vertex ids packed base n); needs n**3 < 2**62."""
    s = np.sort(np.asarray(tris, dtype=np.int64), axis=1)
    if n**3 >= 2**62:
        raise ValueError(f"triangle_keys: {n} points do not fit a packed int64 key; hint: mesh fewer than 1.6M nodes")
    return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]


def tet_face_keys(cells: np.ndarray, n: int) -> np.ndarray:
    """Sorted unique keys of the 4 faces of every tet (m, 4)."""
    faces = np.asarray(cells, dtype=np.int64)[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3)
    return np.unique(triangle_keys(faces, n))


def missing_triangles(triangles: np.ndarray, cells: np.ndarray, n: int) -> np.ndarray:
    """(t,) bool: surface triangles that are not a face of any tet."""
    return ~in_sorted(triangle_keys(triangles, n), tet_face_keys(cells, n))  # the face keys are sorted unique


def in_sorted(keys, sorted_keys: np.ndarray) -> np.ndarray:
    """np.isin(keys, sorted_keys) by binary search (np.isin sorts sorted_keys again on every call)."""
    keys = np.asarray(keys)
    if not len(sorted_keys):
        return np.zeros(keys.shape, bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[at] == keys


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Euclidean distance from points p (k, 3) to triangles (a, b, c) (k, 3) each (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = np.finfo(float).tiny
    # interior by default, then overwrite with the vertex / edge regions (later rules win)
    denom = np.where(np.abs(va + vb + vc) > tiny, va + vb + vc, tiny)
    v, w = vb / denom, vc / denom
    q = a + v[:, None] * ab + w[:, None] * ac
    e_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t = (d4 - d3) / np.where(e_bc, (d4 - d3) + (d5 - d6), 1.0)
    q = np.where(e_bc[:, None], b + t[:, None] * (c - b), q)
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = d2 / np.where(e_ac, d2 - d6, 1.0)
    q = np.where(e_ac[:, None], a + t[:, None] * ac, q)
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = d1 / np.where(e_ab, d1 - d3, 1.0)
    q = np.where(e_ab[:, None], a + t[:, None] * ab, q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    return np.linalg.norm(p - q, axis=1)


def distance_to_surface(points: np.ndarray, surface: SurfaceMesh, radius: np.ndarray,
                        chunk: int = 8192, pair_batch: int = 1 << 19) -> np.ndarray:
    """Distance from points (k, 3) to the nearest surface triangle where it is < radius (k,), else inf.

    Triangles are grouped by octave of their reach (largest centroid-vertex distance), one KD-tree
    each: with one global reach, the large box-face triangles of a graded surface made every point
    pair with thousands of small interface triangles (the likely cause of a 200-inclusion RVE running
    out of 24 GB). Points go in chunks and candidate pairs in batches, so memory stays bounded.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    radius = np.broadcast_to(np.asarray(radius, dtype=float), (len(points),))
    tri = surface.triangles
    out = np.full(len(points), np.inf)
    if not len(points) or not len(tri):
        return out
    P = surface.points[tri]  # (t, 3, 3)
    cen = P.mean(axis=1)
    reach = np.linalg.norm(P - cen[:, None], axis=-1).max(axis=1)
    octave = np.floor(np.log2(np.maximum(reach, 1e-300) / max(reach.max(), 1e-300)))
    octave = np.maximum(octave, -20).astype(np.int64)
    for o in np.unique(octave):
        group = np.flatnonzero(octave == o)
        tree, group_reach = cKDTree(cen[group]), float(reach[group].max())
        for start in range(0, len(points), chunk):
            stop = min(start + chunk, len(points))
            lists = tree.query_ball_point(points[start:stop], radius[start:stop] + group_reach, return_sorted=False)
            lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            if not lens.any():
                continue
            pi = np.repeat(np.arange(start, stop), lens)
            ti = group[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])]
            del lists
            for b in range(0, len(pi), pair_batch):
                p_b, t_b = pi[b:b + pair_batch], ti[b:b + pair_batch]
                d = point_triangle_distance(points[p_b], P[t_b, 0], P[t_b, 1], P[t_b, 2])
                first = np.flatnonzero(np.r_[True, p_b[1:] != p_b[:-1]])  # p_b is sorted
                rows = p_b[first]
                out[rows] = np.minimum(out[rows], np.minimum.reduceat(d, first))
    out[out >= radius] = np.inf  # the contract: exact below radius only (independent of the grouping)
    return out


def _circumballs(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest circumscribed balls of triangles P (k, 3, 3): centres (k, 3), radii (k,)."""
    a, b, c = P[:, 0], P[:, 1], P[:, 2]
    u, v = b - a, c - a
    w = cross3(u, v)
    ww = np.maximum(np.einsum("ij,ij->i", w, w), np.finfo(float).tiny)
    cen = a + (cross3(w, u) * np.einsum("ij,ij->i", v, v)[:, None]
               + cross3(v, w) * np.einsum("ij,ij->i", u, u)[:, None]) / (2.0 * ww[:, None])
    return cen, np.linalg.norm(cen - a, axis=1)


def encroached_free_nodes(points: np.ndarray, tris: np.ndarray, free: np.ndarray, scale: float = 1.02) -> np.ndarray:
    """Free nodes (indices) inside the smallest circumscribed ball (radius * scale) of any triangle."""
    if not len(tris) or not free.any():
        return np.zeros(0, dtype=np.int64)
    cen, r = _circumballs(points[tris])
    idx = np.flatnonzero(free)
    lists = cKDTree(points[idx]).query_ball_point(cen, r * scale, return_sorted=False)
    hit = [idx[np.asarray(x, dtype=np.int64)] for x in lists if len(x)]
    return np.unique(np.concatenate(hit)) if hit else np.zeros(0, dtype=np.int64)


def levelset_projector(inclusion_phi: Callable, *, steps: int = 8, rel_eps: float = 1e-7) -> Callable:
    """A NumPy projection onto phi_k = 0 for split midpoints, from inclusion_phi(k, points) -> (m,).

    Newton along the central-difference gradient with the locked (box-plane) components removed.
    Returns project_fn(points (m, 3), inclusion (m,), locked (m, 3) bool) -> (m, 3).

    Example: ``levelset_projector(ms.inclusion_phi)``.
    """

    def project(points, inclusion, locked):
        out = np.array(points, dtype=float, copy=True)
        scale = float(np.abs(out).max(initial=1.0))
        eps = rel_eps * scale
        for k in np.unique(inclusion):
            sel = np.flatnonzero(inclusion == k)
            x = out[sel]
            for _ in range(steps):
                phi = np.asarray(inclusion_phi(int(k), x), dtype=float)
                g = np.stack([(np.asarray(inclusion_phi(int(k), x + eps * e), dtype=float)
                               - np.asarray(inclusion_phi(int(k), x - eps * e), dtype=float)) / (2 * eps)
                              for e in np.eye(3)], axis=1)
                g = np.where(locked[sel], 0.0, g)
                gg = np.einsum("ij,ij->i", g, g)
                ok = gg > 0
                x = x - np.where(ok, phi / np.where(ok, gg, 1.0), 0.0)[:, None] * g
                if np.abs(phi).max(initial=0.0) < 1e-14 * scale:
                    break
            out[sel] = x
        return out

    return project


def _plane_sides(x: np.ndarray, box: np.ndarray, tol: float = 1e-9) -> list[tuple[int, int]]:
    """(axis, side) of every box plane the point x lies on."""
    out = []
    for a in range(3):
        if abs(x[a]) <= tol * box[a]:
            out.append((a, 0))
        elif abs(x[a] - box[a]) <= tol * box[a]:
            out.append((a, 1))
    return out


_SPLIT_AT = (0.5, 0.375, 0.625, 0.25, 0.75)  # chord parameters tried, the midpoint first


def _interface_split_point(project_fn: Callable, pu: np.ndarray, pv: np.ndarray, k_inc: int,
                           common: list[tuple[int, int]], box: np.ndarray, tree: cKDTree) -> np.ndarray | None:
    """A point of inclusion k_inc's level set that splits the chord (pu, pv) inside the box, or None.

    An inclusion that crosses a box plane by less than the surface resolution was meshed as not
    crossing it, yet its level set does: a projected midpoint near that cap lands beyond the plane,
    outside the hull, and recovery diverged (the 200-sphere RVE); near a trace, a long chord's can too.
    The chord points at _SPLIT_AT are projected (the planes both ends lie on, common: (axis, side)
    pairs, pinned and locked) and the first that keeps every free coordinate at least half the chord
    point's distance from the box planes wins. Else the axes it came too near are locked as well and
    the projection redone within those planes, kept where the level set is steep there (it moved at
    most twice as far as the free one; under a grazing cap it would move across the cap and fold the
    surface). Else the free projection farthest inside the box, if by more than 1e-3 of the chord
    (nearer would need elements that much smaller).
    A point within a tiny distance of an existing node never wins: Qhull would drop the duplicate.
    """
    m = pu + np.asarray(_SPLIT_AT)[:, None] * (pv - pu)
    locked = np.zeros(m.shape, dtype=bool)
    for a, s in common:
        m[:, a], locked[:, a] = s * box[a], True
    inc = np.full(len(m), k_inc)
    length = float(np.linalg.norm(pv - pu))
    d_chord = np.minimum(m, box - m)

    def too_near(q, fixed):  # (k, 3): free coordinates nearer a plane than half the chord point's
        return ~fixed & (np.minimum(q, box - q) < 0.5 * d_chord)

    def apart(q):
        return tree.query(q)[0] > 1e-6 * length

    q = np.asarray(project_fn(m, inc, locked), dtype=float)
    near = too_near(q, locked)
    ok = ~near.any(axis=1) & apart(q)
    if ok.any():
        return q[np.argmax(ok)]
    in_plane = np.asarray(project_fn(m, inc, locked | near), dtype=float)
    steep = np.linalg.norm(in_plane - m, axis=1) <= 2.0 * np.linalg.norm(q - m, axis=1)
    ok = ~too_near(in_plane, locked | near).any(axis=1) & apart(in_plane) & steep
    if ok.any():
        return in_plane[np.argmax(ok)]
    clearance = np.where(apart(q), np.where(locked, np.inf, np.minimum(q, box - q)).min(axis=1), -np.inf)
    best = int(np.argmax(clearance))
    return q[best] if clearance[best] > 1e-3 * length else None


def split_edges(surface: SurfaceMesh, edges: np.ndarray, project_fn: Callable | None = None) -> tuple[SurfaceMesh, int]:
    """Split surface edges (box edges at their midpoints) with their periodic images, keeping the surface consistent.

    Every triangle holding a split edge becomes two with the same orientation, sides and kind.
    Interface edges: split at a point of the chord projected onto its inclusion's level set with
    project_fn (box-plane coordinates locked), the midpoint unless that leaves the box or nears a
    box plane (`_interface_split_point`); an edge with no such point inside the box stays unsplit.
    Box-face edges: the midpoint stays on the plane(s) and (periodic surface) every periodic image
    of the edge is split at the translated midpoint; periodic_pairs are extended.

    Args:
        surface: the SurfaceMesh. edges: (k, 2) node ids of surface edges.
        project_fn: project_fn(points (m, 3), inclusion (m,), locked (m, 3)) -> (m, 3), or None.
    Returns:
        (new SurfaceMesh, number of nodes added). Old node and triangle ids of untouched
        triangles are unchanged; new nodes are appended.
    """
    box = np.asarray(surface.box, dtype=float)
    pts = [p for p in surface.points]
    tris, sides, kind = surface.triangles.copy(), surface.sides.copy(), surface.kind.copy()
    inc = list(surface.node_inclusion)
    partner = [dict() for _ in range(3)]  # axis -> {node: its translate on the other face}
    for a, pp in surface.periodic_pairs.items():
        for i, j in np.asarray(pp, dtype=np.int64).reshape(-1, 2):
            partner[a][int(i)], partner[a][int(j)] = int(j), int(i)
    new_pairs = {a: [] for a in range(3)}
    done: set[tuple[int, int]] = set()
    added = 0
    tree = cKDTree(surface.points) if project_fn is not None else None
    for u, v in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        u, v = int(u), int(v)
        if (min(u, v), max(u, v)) in done:
            continue
        pu, pv = np.asarray(pts[u]), np.asarray(pts[v])
        common = sorted(set(_plane_sides(pu, box)) & set(_plane_sides(pv, box)))
        holders = np.flatnonzero((tris == u).any(axis=1) & (tris == v).any(axis=1))
        if len(holders) == 0:
            raise MeshingError("volume", f"recovery asked to split ({u}, {v}), which is not a surface edge")
        iface = holders[kind[holders] == INTERFACE]
        k_inc = int(sides[iface[0], 0]) if len(iface) else 0
        m = 0.5 * (pu + pv)
        for a, s in common:
            m[a] = s * box[a]
        if k_inc > 0 and project_fn is not None:
            m = _interface_split_point(project_fn, pu, pv, k_inc, common, box, tree)
            if m is None:  # left unsplit; the caller sees it in the count
                continue
        # the edge and its periodic images: (u, v, new point) for every subset of the common axes
        images = [(u, v, m)]
        for a, s in (common if surface.periodic else ()):
            for iu, iv, im in list(images):
                if iu not in partner[a] or iv not in partner[a]:
                    raise MeshingError("volume", f"box edge ({iu}, {iv}) on {'xyz'[a]}={'0L'[s]} has no periodic "
                                       "partner; hint: the surface's periodic_pairs must cover every box-face node")
                jm = im.copy()
                jm[a] = box[a] - im[a]  # im[a] is exactly 0 or L: the translate is exact too
                images.append((partner[a][iu], partner[a][iv], jm))
        ids = {}
        for iu, iv, im in images:
            key = (min(iu, iv), max(iu, iv))
            if key in done:
                continue
            done.add(key)
            w = len(pts)
            pts.append(im)
            inc.append(k_inc)
            ids[key] = w
            added += 1
            hold = np.flatnonzero((tris == iu).any(axis=1) & (tris == iv).any(axis=1))
            first, second = tris[hold].copy(), tris[hold].copy()
            first[first == iv] = w  # (.., iu, .., w, ..): same orientation as the parent
            second[second == iu] = w
            tris[hold] = first
            tris = np.concatenate([tris, second])
            sides = np.concatenate([sides, sides[hold]])
            kind = np.concatenate([kind, kind[hold]])
        for a, s in (common if surface.periodic else ()):  # pair the new nodes across axis a
            for iu, iv, im in images:
                ju, jv = partner[a].get(iu), partner[a].get(iv)
                if ju is None or jv is None or im[a] != 0.0:
                    continue
                lo, hi = ids.get((min(iu, iv), max(iu, iv))), ids.get((min(ju, jv), max(ju, jv)))
                if lo is not None and hi is not None:
                    new_pairs[a].append((lo, hi))
                    partner[a][lo], partner[a][hi] = hi, lo
    pairs = {}
    for a in range(3):
        old = np.asarray(surface.periodic_pairs.get(a, np.zeros((0, 2))), dtype=np.int64).reshape(-1, 2)
        extra = np.asarray(new_pairs[a], dtype=np.int64).reshape(-1, 2)
        if len(old) or len(extra) or a in surface.periodic_pairs:
            pairs[a] = np.concatenate([old, extra])
    out = SurfaceMesh(np.asarray(pts), tris, sides, kind, np.asarray(inc), surface.box, pairs, dict(surface.metadata),
                      surface.periodic)
    return out, added
