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
from ._mesh import Mesh, facet_table
from ._quality import signed_volumes

# the 12 triangles of the box, outward: corner c = 4 i + 2 j + k sits at (i Lx, j Ly, k Lz)
_BOX_TRIANGLES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                           [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def levelset_surface(values: np.ndarray, box, periodic: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of phi = 0 over [0, L]^3 from a grid (sample i at x = i L / n), normals towards
    phi > 0; open where an inclusion is cut by the box. Empty when phi keeps one sign. The layer at
    x = L repeats the one at x = 0 (periodic) or the last one (not periodic)."""
    values = np.asarray(values, dtype=float)
    if values.min() >= 0 or values.max() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    grid = np.pad(values, [(0, 1)] * 3, mode="wrap" if periodic else "edge")
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
    sv, sf = levelset_surface(np.asarray(microstructure.dn1), box, microstructure.periodic)
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
    negative = signed_volumes(verts, tets) < 0
    tets[negative] = tets[negative][:, [1, 0, 2, 3]]
    verts, tets = _settle_on_box(verts, tets, box, 2.0 * epsilon * float(np.linalg.norm(box)))
    used = np.unique(tets)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, tets = verts[used], remap[tets]
    ids = np.asarray(microstructure.label(verts[tets].mean(axis=1)), dtype=np.int64)
    meta = {"backend": "tetwild", "volume": {"surface_points": len(sv), "surface_triangles": len(sf),
                                             "epsilon": float(epsilon)}}
    return Mesh(points=verts, cells=tets, inclusion_id=ids, box=tuple(box), periodic=False, metadata=meta)


def _solid(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) bool: tets positive and not flat by the validator's measure (V above 1e-9 l_max^3)."""
    p = points[tets]
    longest = np.linalg.norm(p[:, [0, 0, 0, 1, 1, 2]] - p[:, [1, 2, 3, 2, 3, 3]], axis=2).max(axis=1)
    return signed_volumes(points, tets) > 1e-9 * longest**3


def _flat_on_a_plane(points: np.ndarray, tets: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(m,) bool: tets whose four nodes lie exactly on one box plane."""
    flat = np.zeros(len(tets), bool)
    for a in range(3):
        for value in (0.0, box[a]):
            flat |= (points[tets, a] == value).all(axis=1)
    return flat


def _settle_on_box(verts: np.ndarray, tets: np.ndarray, box: np.ndarray, reach: float):
    """Box nodes onto their planes (`_snap_to_box`), keeping every tet solid: tets left flat on one
    plane (slivers inside fTetWild's envelope) are dropped; snaps that would flatten or invert another
    tet are undone, then retried one node at a time. Returns (points, tets), fTetWild's own if that fails."""
    target = _snap_to_box(verts, tets, box, reach)
    snapped, undone = target.copy(), np.zeros(len(verts), bool)
    for _ in range(20):
        kept = tets[~_flat_on_a_plane(snapped, tets, box)]  # re-derived: an undone node can lift a sliver
        bad = ~_solid(snapped, kept)
        if not bad.any():
            break
        nodes = np.unique(kept[bad])
        snapped[nodes] = verts[nodes]
        undone[nodes] = True
    else:
        return verts, tets
    for i in np.flatnonzero(undone & (target != verts).any(axis=1)):  # one at a time: most fit alone
        star = tets[(tets == i).any(axis=1)]
        before = snapped[i].copy()
        snapped[i] = target[i]
        if not _solid(snapped, star[~_flat_on_a_plane(snapped, star, box)]).all():
            snapped[i] = before
    kept = tets[~_flat_on_a_plane(snapped, tets, box)]
    return (snapped, kept) if _solid(snapped, kept).all() else (verts, tets)


def _snap_to_box(points: np.ndarray, tets: np.ndarray, box: np.ndarray, reach: float) -> np.ndarray:
    """Boundary nodes within `reach` of a box plane moved onto it: fTetWild keeps the box surface only
    within its envelope, and a face node 1e-4 off its plane is a boundary facet off the box."""
    table = facet_table(tets, len(points))
    on_boundary = np.unique(table.facets[table.counts == 1])
    out = points.copy()
    for a in range(3):
        x = out[on_boundary, a]
        x = np.where(np.abs(x) <= reach, 0.0, x)
        out[on_boundary, a] = np.where(np.abs(x - box[a]) <= reach, box[a], x)
    return out
