"""Optional volume backend: fTetWild (pytetwild) on the marching-cubes surface of the level-set grid.

`MeshConfig(backend="tetwild")`, `jaxmesh mesh --backend tetwild`. What it is good at: a valid tet
mesh of the box from a surface that may be damaged or self-intersecting, where the conforming path
stops with an error. What it is not: exactly conforming (fTetWild keeps the input surface only
within an envelope, and simplifies it; a few box nodes may stay off their plane, inside it),
periodic (no node pairs, opposite faces do not match) or labelled by the surfaces (each tet takes
the field's label at its centroid). fTetWild runs on all cores and its result varies run to run.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
from skimage.measure import marching_cubes

from ._errors import MeshingError
from ._mesh import Mesh

# the 12 triangles of the box, outward: corner c = 4 i + 2 j + k sits at (i Lx, j Ly, k Lz)
_BOX_TRIANGLES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                           [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def levelset_surface(values: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of phi = 0 over [0, L]^3 from a periodic grid (sample i at x = i L / n), normals
    towards phi > 0; open where an inclusion is cut by the box. Empty when phi keeps one sign."""
    values = np.asarray(values, dtype=float)
    if values.min() >= 0 or values.max() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    grid = np.pad(values, [(0, 1)] * 3, mode="wrap")  # the layer at x = L repeats the one at x = 0
    spacing = tuple(float(L) / n for L, n in zip(box, values.shape))
    grid = np.where(grid == 0.0, 1e-12 * min(spacing), grid)  # no vertex exactly on a grid node
    verts, faces, _, _ = marching_cubes(grid, 0.0, spacing=spacing, allow_degenerate=False)
    return verts.astype(np.float64), faces.astype(np.int64)


def tetwild_mesh(microstructure, h: float, *, epsilon: float = 1e-3) -> Mesh:
    """Non-periodic tet mesh of the box by fTetWild, labels from the field at the centroids.

    Args:
        microstructure: a 3D Microstructure (its level-set grid `dn1` and `label`).
        h: target edge length (box units). epsilon: fTetWild's envelope, relative to the box diagonal.
    Returns:
        Mesh with periodic=False, cells positively oriented, metadata['backend'] = 'tetwild'.
    """
    try:
        import pytetwild
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise MeshingError("volume", "the tetwild backend needs pytetwild (pip install pytetwild)") from err
    box = np.asarray(microstructure.box, dtype=float)
    sv, sf = levelset_surface(np.asarray(microstructure.dn1), box)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float) * box
    points = np.vstack([sv, corners])
    tris = np.vstack([sf, _BOX_TRIANGLES + len(sv)]).astype(np.int32)
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="jaxmesh_tetwild_") as scratch:
        os.chdir(scratch)  # fTetWild writes __tracked_surface.stl into the working directory
        try:
            verts, tets = pytetwild.tetrahedralize(points, tris, edge_length_abs=float(h), epsilon=float(epsilon),
                                                   quiet=True)
        finally:
            os.chdir(cwd)
    verts, tets = np.asarray(verts, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    if not len(tets):
        raise MeshingError("volume", "fTetWild returned no tetrahedra (hint: a smaller h)")
    six_v = _six(verts[tets])
    tets[six_v < 0] = tets[six_v < 0][:, [1, 0, 2, 3]]
    verts, tets = _settle_on_box(verts, tets, box, 2.0 * epsilon * float(np.linalg.norm(box)))
    used = np.unique(tets)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, tets = verts[used], remap[tets]
    ids = np.asarray(microstructure.label(verts[tets].mean(axis=1)), dtype=np.int64)
    meta = {"backend": "tetwild", "volume": {"surface_points": len(sv), "surface_triangles": len(sf),
                                             "epsilon": float(epsilon)}}
    return Mesh(points=verts, cells=tets, inclusion_id=ids, box=tuple(box), periodic=False, metadata=meta)


def _six(p: np.ndarray) -> np.ndarray:
    """Six times the signed volumes of tets p (m, 4, 3)."""
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))


def _solid(p: np.ndarray) -> np.ndarray:
    """(m,) bool: tets p (m, 4, 3) positive and not flat (6V above 6e-9 of the longest edge cubed)."""
    longest = np.linalg.norm(p[:, [0, 0, 0, 1, 1, 2]] - p[:, [1, 2, 3, 2, 3, 3]], axis=2).max(axis=1)
    return _six(p) > 6e-9 * longest**3


def _settle_on_box(verts: np.ndarray, tets: np.ndarray, box: np.ndarray, reach: float):
    """Box nodes onto their planes (`_snap_to_box`), keeping every tet positive: tets left flat on one
    plane (slivers inside fTetWild's envelope) are dropped; snaps that would flatten or invert another
    tet are undone, then retried one node at a time. Returns (points, tets)."""
    target = _snap_to_box(verts, tets, box, reach)
    snapped, undone = target.copy(), np.zeros(len(verts), bool)
    for _ in range(20):
        kept = tets[~_flat_on_a_plane(snapped[tets], box)]
        bad = ~_solid(snapped[kept])
        if not bad.any():
            break
        nodes = np.unique(kept[bad])
        snapped[nodes] = verts[nodes]
        undone[nodes] = True
    else:
        return verts, tets  # as fTetWild left them
    for i in np.flatnonzero(undone & (target != verts).any(axis=1)):  # one at a time: most fit alone
        star = tets[(tets == i).any(axis=1)]
        local = snapped[star]
        local[star == i] = target[i]
        if _solid(local[~_flat_on_a_plane(local, box)]).all():
            snapped[i] = target[i]
    kept = tets[~_flat_on_a_plane(snapped[tets], box)]
    return (snapped, kept) if _solid(snapped[kept]).all() else (verts, tets)


def _flat_on_a_plane(p: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(m,) bool: tets p (m, 4, 3) whose four nodes lie exactly on one box plane."""
    flat = np.zeros(len(p), bool)
    for a in range(3):
        for value in (0.0, box[a]):
            flat |= (p[:, :, a] == value).all(axis=1)
    return flat


def _snap_to_box(points: np.ndarray, tets: np.ndarray, box: np.ndarray, reach: float) -> np.ndarray:
    """Boundary nodes within `reach` of a box plane moved onto it: fTetWild keeps the box surface only
    within its envelope, and a face node 1e-4 off its plane is a boundary facet off the box."""
    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    uniq, count = np.unique(faces, axis=0, return_counts=True)
    on_boundary = np.unique(uniq[count == 1])
    out = points.copy()
    for a in range(3):
        x = out[on_boundary, a]
        x = np.where(np.abs(x) <= reach, 0.0, x)
        out[on_boundary, a] = np.where(np.abs(x - box[a]) <= reach, box[a], x)
    return out
