"""Make the surface triangulations locally Delaunay before the volume step. NumPy only.

A box face lies on the convex hull of all nodes, so the tetrahedralisation restricted to a face is
the 2D Delaunay triangulation of the face nodes: a face triangle that is not 2D Delaunay can never
appear, and recovering it by splitting edges is slow and may not finish. Lawson flips of the edges
inside one region of a face (never a box edge, never a trace edge, where the region changes) fix
that at no cost in nodes; on the curved interfaces the same flips (the intrinsic criterion) remove
most of the triangles that other surface nodes encroach. The 0-faces are flipped and copied onto the L-faces by the periodic pairs,
so the periodic identity stays exact.
"""

from __future__ import annotations

import numpy as np

from ._quality import cross3
from ._surface_mesh import BOX_FACE, INTERFACE, SurfaceMesh
from ._surface_ops import in_one_box_plane


def _angle_at(apex: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    u, v = p - apex, q - apex
    cross = np.linalg.norm(cross3(u, v), axis=-1) if u.shape[1] == 3 else np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    return np.arctan2(cross, np.einsum("ij,ij->i", u, v))


def _signed_area(uv: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = uv[tris[:, 0]], uv[tris[:, 1]], uv[tris[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])


def _normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    return cross3(b - a, c - a)


def lawson_flips(points: np.ndarray, tris: np.ndarray, region: np.ndarray, *, max_rounds: int = 200,
                 max_normal_turn_deg: float = 30.0, on_plane: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Flip edges that are not locally Delaunay (opposite angles summing to more than pi).

    Only edges shared by exactly two of `tris` with the same `region` are candidates; a flip is
    kept only if both new triangles turn their normal by less than `max_normal_turn_deg` from
    the pair's mean normal and the new edge does not exist yet (no fold, stays manifold). On a plane
    this is the 2D Delaunay criterion, on a curved surface its intrinsic analogue.

    Args:
        points: (n, 3) nodes; tris: (t, 3) consistently oriented; region: (t,) ids.
        on_plane: optional (n, 3) bool, coordinate a of the node exactly on a box plane: a flip that
            would make a triangle with all three nodes on one box plane is refused.
    Returns:
        (flipped triangles (t, 3), same orientation and region per row; number of flips).
    """
    tris = np.array(tris, dtype=np.int64)
    n = len(points)
    min_cos = np.cos(np.radians(max_normal_turn_deg))
    total = 0
    for _ in range(max_rounds):
        t = len(tris)
        a = tris.reshape(-1)
        b = tris[:, [1, 2, 0]].reshape(-1)
        opposite = tris[:, [2, 0, 1]].reshape(-1)
        key = np.minimum(a, b) * n + np.maximum(a, b)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        count = np.diff(np.concatenate([[0], np.nonzero(np.diff(ks))[0] + 1, [len(ks)]]))
        run_start = np.concatenate([[0], np.cumsum(count)[:-1]])
        pair = run_start[count == 2]
        h1, h2 = order[pair], order[pair + 1]  # the two half-edges of an interior edge
        t1, t2 = h1 // 3, h2 // 3
        same = region[t1] == region[t2]
        h1, h2, t1, t2 = h1[same], h2[same], t1[same], t2[same]
        ia, ib, ic, id_ = a[h1], b[h1], opposite[h1], opposite[h2]
        excess = _angle_at(points[ic], points[ia], points[ib]) + _angle_at(points[id_], points[ia], points[ib]) - np.pi
        bad = np.nonzero(excess > 1e-9)[0]
        if len(bad):
            new1 = np.stack([ia[bad], id_[bad], ic[bad]], 1)
            new2 = np.stack([id_[bad], ib[bad], ic[bad]], 1)
            mean = _normals(points, tris[t1[bad]]) + _normals(points, tris[t2[bad]])
            mean /= np.linalg.norm(mean, axis=1, keepdims=True) + 1e-300
            ok = np.ones(len(bad), bool)
            for new in (new1, new2):
                nn = _normals(points, new)
                ok &= np.einsum("ij,ij->i", nn, mean) > min_cos * np.linalg.norm(nn, axis=1)
            new_key = np.minimum(ic[bad], id_[bad]) * n + np.maximum(ic[bad], id_[bad])
            ok &= ~np.isin(new_key, ks)
            if on_plane is not None:
                ok &= ~(in_one_box_plane(points, on_plane, new1) | in_one_box_plane(points, on_plane, new2))
            bad = bad[ok]
        if not len(bad):
            break
        bad = bad[np.argsort(-excess[bad])]
        used = np.zeros(t, bool)
        chosen = []
        for e in bad:  # an independent set: each triangle flipped at most once per round
            if not used[t1[e]] and not used[t2[e]]:
                used[t1[e]] = used[t2[e]] = True
                chosen.append(e)
        chosen = np.asarray(chosen)
        # a->b in t1 (opposite c), b->a in t2 (opposite d): quad a, d, b, c -> diagonal c-d
        tris[t1[chosen]] = np.stack([ia[chosen], id_[chosen], ic[chosen]], 1)
        tris[t2[chosen]] = np.stack([id_[chosen], ib[chosen], ic[chosen]], 1)
        total += len(chosen)
    return tris, total


def delaunay_interfaces(surface: SurfaceMesh) -> tuple[SurfaceMesh, int]:
    """Lawson-flip the interface triangles of each inclusion.

    A trace edge belongs to one interface triangle only (the surface is cut there), so it is never
    a candidate: traces and their periodic copies are left alone. Nor is a flip that would lay an
    interface triangle flat on a box plane (three trace nodes, where the interface grazes the
    plane): the box face holds that triangle too, and the two regions it then separates conflict.
    """
    tris = surface.triangles.copy()
    on = np.nonzero(surface.kind == INTERFACE)[0]
    box, points = np.asarray(surface.box, dtype=float), surface.points
    on_plane = (points == 0.0) | (points == box)  # box-plane nodes lie exactly on it
    tris[on], flips = lawson_flips(points, tris[on], surface.sides[on, 0], on_plane=on_plane)
    out = SurfaceMesh(surface.points, tris, surface.sides, surface.kind, surface.node_inclusion, surface.box,
                      surface.periodic_pairs, dict(surface.metadata), surface.periodic)
    return out, flips


def _flip_face(points: np.ndarray, face_tris: np.ndarray, regions: np.ndarray, axis: int) -> tuple[np.ndarray, int]:
    """Lawson flips of one planar box face x_axis = const, its orientation kept; (triangles, flips)."""
    uv = points[:, [i for i in range(3) if i != axis]]
    sign = np.sign(_signed_area(uv, face_tris))
    ccw = np.where(sign[:, None] < 0, face_tris[:, [0, 2, 1]], face_tris)
    flipped, count = lawson_flips(np.column_stack([uv, np.zeros(len(uv))]), ccw, regions)
    orient = np.sign(np.sum(sign))  # the face's orientation (outward normal) in the uv frame
    return (flipped if orient > 0 else flipped[:, [0, 2, 1]]), count


def delaunay_box_faces(surface: SurfaceMesh) -> tuple[SurfaceMesh, int]:
    """Lawson-flip the box faces to 2D Delaunay: the three master faces, copied onto the opposite
    faces (periodic), or each of the six faces on its own (not periodic).

    Returns:
        (SurfaceMesh with the same nodes and triangle count, number of flips on the flipped faces).
    """
    points, tris = surface.points, surface.triangles.copy()
    sides, kind = surface.sides.copy(), surface.kind
    box = np.asarray(surface.box, dtype=float)
    flips = 0
    if not surface.periodic:
        for axis in range(3):
            for value in (0.0, box[axis]):
                on = np.nonzero((kind == BOX_FACE) & np.all(points[tris][:, :, axis] == value, axis=1))[0]
                tris[on], count = _flip_face(points, tris[on], sides[on, 0], axis)
                flips += count
        out = SurfaceMesh(points, tris, sides, kind, surface.node_inclusion, surface.box, {},
                          dict(surface.metadata), False)
        return out, flips
    for axis in range(3):
        pairs = surface.periodic_pairs.get(axis)
        if pairs is None or not len(pairs):
            continue
        other = [i for i in range(3) if i != axis]
        uv = points[:, other]
        on = [
            np.nonzero((kind == BOX_FACE) & np.all(points[tris][:, :, axis] == value, axis=1))[0]
            for value in (0.0, box[axis])
        ]
        flipped, count = _flip_face(points, tris[on[0]], sides[on[0], 0], axis)
        flips += count
        if not count:
            continue
        tris[on[0]] = flipped
        # the L-face: the translate of the 0-face, facing the other way
        to_upper = np.full(len(points), -1, dtype=np.int64)
        to_upper[pairs[:, 0]] = pairs[:, 1]
        ccw = flipped if np.sum(_signed_area(uv, flipped)) > 0 else flipped[:, [0, 2, 1]]
        upper = to_upper[ccw]
        if np.any(upper < 0) or len(on[1]) != len(on[0]):
            raise ValueError(f"box face x_{axis} = 0 does not match x_{axis} = L through the periodic pairs")
        upper_sign = np.sign(np.sum(_signed_area(uv, tris[on[1]])))
        tris[on[1]] = upper if upper_sign > 0 else upper[:, [0, 2, 1]]
        sides[on[1]] = sides[on[0]]
    out = SurfaceMesh(points, tris, sides, kind, surface.node_inclusion, surface.box,
                      surface.periodic_pairs, dict(surface.metadata), surface.periodic)
    return out, flips
