"""Element quality measures (NumPy only).

The tetrahedron quality is the paper's eq. 4, q = 3 r_in / r_circ (1 for the regular
tetrahedron, 0 for a flat one); triangles use q = 2 r_in / r_circ (1 for the equilateral
triangle). Everything here works on plain arrays, so it serves meshes from any stage.
"""

from __future__ import annotations

import numpy as np

# Edges of a simplex, in the order used by `dihedral_angles`.
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of (..., 3) arrays, the same arithmetic as np.cross without its per-call
    overhead (moveaxis and axis checks), which the per-inclusion loops would pay thousands of times."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _check_simplices(points, cells, name: str = "cells") -> tuple[np.ndarray, np.ndarray]:
    """Coerce and validate (points, cells); ValueError with a hint otherwise."""
    points = np.asarray(points, dtype=float)
    cells = np.asarray(cells)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(
            f"points must be an (n, 2) or (n, 3) array, got shape {points.shape}; "
            "hint: pass mesh.points"
        )
    if cells.ndim != 2 or cells.shape[1] not in (3, 4):
        raise ValueError(
            f"{name} must be an (m, 3) triangle or (m, 4) tetrahedron array, got shape "
            f"{cells.shape}; hint: pass mesh.cells"
        )
    if not np.issubdtype(cells.dtype, np.integer):
        raise ValueError(f"{name} must hold integer vertex ids, got dtype {cells.dtype}")
    if cells.size and (cells.min() < 0 or cells.max() >= len(points)):
        raise ValueError(
            f"{name} refer to vertex ids in [{cells.min()}, {cells.max()}] but there are "
            f"{len(points)} points"
        )
    if cells.shape[1] == 4 and points.shape[1] != 3:
        raise ValueError("tetrahedra need 3D points, got 2D points")
    return points, cells.astype(np.int64, copy=False)


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _triangle_areas(p: np.ndarray) -> np.ndarray:
    """Unsigned areas of triangles p (m, 3, k), k = 2 or 3."""
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    if p.shape[-1] == 2:
        return 0.5 * np.abs(_cross2(a, b))
    return 0.5 * np.linalg.norm(cross3(a, b), axis=-1)


def signed_volumes(points, cells) -> np.ndarray:
    """Signed measure of every cell: area for triangles (2D), volume for tetrahedra.

    Args:
        points: (n, d) coordinates, d = 2 or 3.
        cells: (m, d+1) vertex ids.
    Returns:
        (m,) float; positive for positively oriented (counter-clockwise / right-handed) cells.

    Example: ``signed_volumes(mesh.points, mesh.cells).sum()`` is the box volume.
    """
    points, cells = _check_simplices(points, cells)
    p = points[cells]
    e = p[:, 1:] - p[:, :1]  # (m, d, d) edge vectors from vertex 0
    if cells.shape[1] == 3:
        if points.shape[1] != 2:
            raise ValueError("signed areas need 2D points; for surface triangles use min_angles")
        return 0.5 * _cross2(e[:, 0], e[:, 1])
    return np.einsum("ij,ij->i", e[:, 0], cross3(e[:, 1], e[:, 2])) / 6.0


# A cell is flat when |V| <= FLAT_REL_VOLUME * l_max^d, l_max its longest edge (the regular
# tetrahedron has 0.118, a sliver at this bound dihedral angles near 1e-3 deg), or when its smallest
# angle is below FLAT_ANGLE_DEG: a cap-shaped cell (an angle near 180 deg) has a volume ~ its small
# angles, not their product, and a triangle of 0.002 deg passed the volume bound alone.
FLAT_REL_VOLUME = 1e-6
FLAT_ANGLE_DEG = 0.01


def longest_edges(corners: np.ndarray) -> np.ndarray:
    """(m,) length of each cell's longest edge, from its corners (m, k, d) = points[cells]."""
    i, j = np.triu_indices(corners.shape[1], 1)
    return np.linalg.norm(corners[:, i] - corners[:, j], axis=-1).max(axis=1)


def relative_volumes(points, cells) -> np.ndarray:
    """(m,) signed V / l_max^d: scale-free, compared with FLAT_REL_VOLUME to call a cell flat."""
    points, cells = _check_simplices(points, cells)
    lmax = longest_edges(points[cells])
    return signed_volumes(points, cells) / np.maximum(lmax, np.finfo(float).tiny) ** points.shape[1]


def flat_mask(rel: np.ndarray, angles: np.ndarray, rel_volume: float = FLAT_REL_VOLUME,
              angle: float = FLAT_ANGLE_DEG) -> np.ndarray:
    """(m,) bool: |V| <= rel_volume l_max^d (rel = V / l_max^d), or not inverted and its smallest angle
    below `angle` degrees (an inverted cell's angles are those of its mirror image)."""
    return (np.abs(rel) <= rel_volume) | ((rel >= -rel_volume) & (angles < angle))


def flat_cells(points, cells) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(m,) bool flat (`flat_mask`), (m,) signed V / l_max^d and (m,) smallest angles in degrees
    (`smallest_angles`)."""
    rel = relative_volumes(points, cells)
    angles = smallest_angles(points, cells)
    return flat_mask(rel, angles), rel, angles


def cell_quality(points, cells) -> np.ndarray:
    """Radius-ratio quality: q = d * r_in / r_circ, 1 for regular cells, 0 for flat ones.

    Orientation is ignored (uses |volume|); check orientation with `signed_volumes`.

    Args:
        points: (n, d) coordinates.
        cells: (m, 3) triangles (2D or 3D points) or (m, 4) tetrahedra.
    Returns:
        (m,) float in [0, 1].

    Example: ``(cell_quality(mesh.points, mesh.cells) < 0.3).mean()``.
    """
    points, cells = _check_simplices(points, cells)
    p = points[cells]
    tiny = np.finfo(float).tiny
    if cells.shape[1] == 3:
        la = np.linalg.norm(p[:, 1] - p[:, 2], axis=-1)
        lb = np.linalg.norm(p[:, 2] - p[:, 0], axis=-1)
        lc = np.linalg.norm(p[:, 0] - p[:, 1], axis=-1)
        area = _triangle_areas(p)
        # r_in = A / s, r_circ = abc / (4A)  =>  2 r_in / r_circ = 16 A^2 / (2 s abc)
        s = 0.5 * (la + lb + lc)
        q = 8.0 * area**2 / np.maximum(s * la * lb * lc, tiny)
        return np.clip(q, 0.0, 1.0)
    a, b, c = (p[:, k] - p[:, 0] for k in (1, 2, 3))
    six_v = np.abs(np.einsum("ij,ij->i", a, cross3(b, c)))
    face_area = sum(_triangle_areas(p[:, f]) for f in ([1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]))
    r_in = 0.5 * six_v / np.maximum(face_area, tiny)  # 3V / sum(areas)
    num = (
        np.sum(a * a, -1)[:, None] * cross3(b, c)
        + np.sum(b * b, -1)[:, None] * cross3(c, a)
        + np.sum(c * c, -1)[:, None] * cross3(a, b)
    )
    r_circ = np.linalg.norm(num, axis=-1) / np.maximum(2.0 * six_v, tiny)
    q = np.where(six_v > 0, 3.0 * r_in / np.maximum(r_circ, tiny), 0.0)
    return np.clip(q, 0.0, 1.0)


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle between vectors (..., k) in degrees, via atan2 (accurate near 0 and 180)."""
    if u.shape[-1] == 2:
        cross = np.abs(_cross2(u, v))
    else:
        cross = np.linalg.norm(cross3(u, v), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(u * v, axis=-1)))


def dihedral_angles(points, tets) -> np.ndarray:
    """Interior dihedral angles of tetrahedra at their six edges, in degrees.

    Args:
        points: (n, 3) coordinates.
        tets: (m, 4) vertex ids.
    Returns:
        (m, 6) angles at edges (0,1), (0,2), (0,3), (1,2), (1,3), (2,3); 70.53 deg for the
        regular tetrahedron, near 0 or 180 for slivers.
    """
    points, tets = _check_simplices(points, tets, "tets")
    if tets.shape[1] != 4:
        raise ValueError(f"dihedral_angles needs (m, 4) tetrahedra, got shape {tets.shape}")
    p = points[tets]
    out = np.empty((len(tets), 6))
    for e, (i, j) in enumerate(TET_EDGES):
        k, l = (v for v in range(4) if v not in (i, j))
        u = p[:, j] - p[:, i]
        u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), np.finfo(float).tiny)
        # The two faces at edge ij contain k and l: project them off the edge direction.
        vk = p[:, k] - p[:, i]
        vl = p[:, l] - p[:, i]
        vk = vk - np.sum(vk * u, -1)[:, None] * u
        vl = vl - np.sum(vl * u, -1)[:, None] * u
        out[:, e] = _angle(vk, vl)
    return out


def min_angles(points, tris) -> np.ndarray:
    """Smallest interior angle of each triangle, in degrees (60 for equilateral).

    Args:
        points: (n, 2) or (n, 3) coordinates.
        tris: (m, 3) vertex ids.
    Returns:
        (m,) float.
    """
    points, tris = _check_simplices(points, tris, "tris")
    if tris.shape[1] != 3:
        raise ValueError(f"min_angles needs (m, 3) triangles, got shape {tris.shape}")
    p = points[tris]
    angles = [_angle(p[:, (i + 1) % 3] - p[:, i], p[:, (i + 2) % 3] - p[:, i]) for i in range(3)]
    return np.min(np.stack(angles, axis=-1), axis=-1)


def smallest_angles(points, cells) -> np.ndarray:
    """(m,) each cell's smallest angle in degrees: a triangle's interior angle, a tet's dihedral angle."""
    points, cells = _check_simplices(points, cells)
    return dihedral_angles(points, cells).min(axis=1) if cells.shape[1] == 4 else min_angles(points, cells)


def quality_report(mesh, *, bins: int = 20, threshold: float = 0.3) -> dict:
    """Counts and quality statistics of a mesh, as a JSON-serialisable dict.

    Args:
        mesh: a `jaxmesh.Mesh` (or any object with points (n, d), cells (m, d+1) and
            optionally inclusion_id (m,)).
        bins: number of equal histogram bins on [0, 1].
        threshold: the "bad element" quality threshold (paper: 0.3).
    Returns:
        dict with n_points, n_cells, dim, cells per inclusion, q_min/q_mean/q_percentiles,
        n_below / frac_below threshold, min dihedral (3D, with the count of tets below 10 deg) or
        min angle (2D) in degrees, hist_edges / hist_counts, and the worst cell (`worst_cell`).

    Example: ``json.dumps(quality_report(mesh))``.
    """
    if bins < 1:
        raise ValueError(f"bins must be a positive integer, got {bins}")
    points, cells = _check_simplices(mesh.points, mesh.cells)
    dim = points.shape[1]
    q = cell_quality(points, cells)
    edges = np.linspace(0.0, 1.0, bins + 1)
    counts, _ = np.histogram(q, bins=edges)
    report: dict = {
        "dim": int(dim),
        "n_points": int(len(points)),
        "n_cells": int(len(cells)),
        "threshold": float(threshold),
        "hist_edges": [round(float(x), 12) for x in edges],
        "hist_counts": [int(c) for c in counts],
    }
    ids = getattr(mesh, "inclusion_id", None)
    if ids is not None:
        uniq, cnt = np.unique(np.asarray(ids), return_counts=True)
        report["cells_per_inclusion"] = {str(int(u)): int(c) for u, c in zip(uniq, cnt)}
        report["n_inclusions"] = int(np.sum(uniq > 0))
    if len(cells) == 0:
        report.update(q_min=None, q_mean=None, q_percentiles={}, n_below=0, frac_below=0.0)
        return report
    pct = (1, 5, 25, 50, 75, 95)
    report.update(
        q_min=float(q.min()),
        q_mean=float(q.mean()),
        q_max=float(q.max()),
        q_percentiles={f"p{p}": float(v) for p, v in zip(pct, np.percentile(q, pct))},
        n_below=int(np.sum(q < threshold)),
        frac_below=float(np.mean(q < threshold)),
    )
    if cells.shape[1] == 4:
        dih = dihedral_angles(points, cells)
        report["min_dihedral_deg"] = float(dih.min())
        report["max_dihedral_deg"] = float(dih.max())
        report["n_dihedral_below_10"] = int(np.sum(dih.min(axis=1) < 10.0))
    else:
        report["min_angle_deg"] = float(min_angles(points, cells).min())
    report["worst_cell"] = worst_cell(points, cells, q, ids, getattr(mesh, "box", None))
    return report


def worst_cell(points: np.ndarray, cells: np.ndarray, q: np.ndarray, ids=None, box=None) -> dict:
    """Where the lowest-quality cell is: index, q, centroid, inclusion id, whether a vertex lies on an
    interface (shared with a cell of another label), and its nearest box plane (axis, side 0 or L,
    distance of the closest vertex). Says where to look when a mesh is valid but has a bad cell."""
    k = int(np.argmin(q))
    corners = points[cells[k]]
    out: dict = {"index": k, "q": float(q[k]), "centroid": [float(v) for v in corners.mean(axis=0)]}
    if ids is not None:
        ids = np.asarray(ids)
        out["inclusion_id"] = int(ids[k])
        other = np.zeros(len(points), bool)
        other[cells[ids != ids[k]].ravel()] = True
        out["on_interface"] = bool(other[cells[k]].any())
    if box is not None:
        L = np.asarray(box, dtype=float)
        gaps = np.minimum(corners, L - corners).min(axis=0)  # per axis, the closest vertex to a plane
        axis = int(np.argmin(gaps))
        side = 0.0 if np.min(corners[:, axis]) <= L[axis] - np.max(corners[:, axis]) else float(L[axis])
        out["nearest_box_plane"] = {"axis": axis, "at": side, "distance": float(max(gaps[axis], 0.0))}
    return out
