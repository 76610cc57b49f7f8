"""Read a mesh file written by jaxmesh (or any simplex mesh of a box) back into a Mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_CELL_TYPES = {2: "triangle", 3: "tetra"}


def read_mesh(path, box=None, periodic: bool = True):
    """Read a triangle (2D) or tetrahedral (3D) mesh file into a :class:`jaxmesh.Mesh`.

    Args:
        path: any format meshio reads (.vtu, .msh, .xdmf, .inp, .vtk); `.npz` as written by jaxmesh.
        box: box lengths; default: the bounding box of the points (origin must be 0).
        periodic: rebuild periodic node pairs by translation (ValueError if the faces do not match).
    Returns:
        Mesh with cell data `inclusion_id` when present (else all 0).
    """
    from .._mesh import Mesh, make_periodic_pairs

    path = Path(path)
    if not path.exists():
        raise ValueError(f"mesh file {str(path)!r} does not exist")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            points, cells = data["points"], data["cells"]
            inclusion_id = data["inclusion_id"] if "inclusion_id" in data else np.zeros(len(cells), np.int64)
    else:
        import meshio

        m = meshio.read(path)
        points = np.asarray(m.points, dtype=np.float64)
        dim = 3 if any(b.type == "tetra" for b in m.cells) else 2
        points = points[:, :dim]
        blocks = [i for i, b in enumerate(m.cells) if b.type == _CELL_TYPES[dim]]
        if not blocks:
            raise ValueError(f"{path}: expected triangle or tetra cells, found {[b.type for b in m.cells]}")
        cells = np.concatenate([m.cells[i].data for i in blocks]).astype(np.int64)
        ids = None
        for key in ("inclusion_id", "gmsh:physical", "medit:ref"):
            if key in m.cell_data:
                ids = np.concatenate([np.asarray(m.cell_data[key][i]) for i in blocks]).astype(np.int64)
                break
        inclusion_id = ids if ids is not None else np.zeros(len(cells), np.int64)
        if ids is not None and key == "gmsh:physical":
            inclusion_id = inclusion_id - 1  # jaxmesh writes physical tag = inclusion id + 1
    lower = points.min(axis=0)
    if np.any(np.abs(lower) > 1e-9 * np.ptp(points, axis=0).max()):
        raise ValueError(f"{path}: expected a box with its origin at 0, the points start at {lower.tolist()}")
    box = tuple(float(v) for v in (points.max(axis=0) if box is None else box))
    if len(box) != points.shape[1]:
        raise ValueError(f"box has {len(box)} lengths, the mesh is {points.shape[1]}D")
    pairs = make_periodic_pairs(points, box) if periodic else {}
    return Mesh(points=points, cells=cells, inclusion_id=inclusion_id, box=box, periodic=periodic,
                periodic_pairs=pairs, metadata={"source": str(path)})
