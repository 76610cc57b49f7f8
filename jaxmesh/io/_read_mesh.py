"""Read a mesh file written by jaxmesh (or any simplex mesh of a box) back into a Mesh."""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path

import numpy as np

from ._write import INPUT_READING_TAG, input_reading, region_of_name

_CELL_TYPES = {2: "triangle", 3: "tetra"}


def read_mesh(path, box=None, periodic: bool = True):
    """Read a triangle (2D) or tetrahedral (3D) mesh file into a :class:`jaxmesh.Mesh`.

    Args:
        path: any format meshio reads (.vtu, .msh, .xdmf, .inp, .vtk); `.npz` as written by jaxmesh;
            .xdmf with inline XML data (as jaxmesh writes it) is read here, without h5py; a .msh
            written by jaxmesh comes back in the mesh's node order (its `node_id` data).
        box: box lengths; default: the bounding box of the points (origin must be 0).
        periodic: rebuild periodic node pairs by translation (ValueError if the faces do not match).
    Returns:
        Mesh with cell data `inclusion_id` when present (.inp: from its element sets matrix and
        inclusion_K; else all 0); metadata["input_reading"]: how jaxmesh read the input it meshed
        (roll_samples / roll_offset, redistanced, box_layers_closed; {} when as given or not written by jaxmesh; .vtk
        files do not carry it).
    """
    from .._mesh import Mesh, make_periodic_pairs

    path = Path(path)
    if not path.exists():
        raise ValueError(f"mesh file {str(path)!r} does not exist")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if not {"points", "cells"} <= set(data.files):
                raise ValueError(f"{path}: expected a mesh .npz as jaxmesh writes it (arrays points, cells), got "
                                 f"{sorted(data.files)}; hint: an input file (phi or labels) goes to --geometry")
            points, cells = data["points"], data["cells"]
            inclusion_id = data["inclusion_id"] if "inclusion_id" in data else np.zeros(len(cells), np.int64)
            reading = input_reading(json.loads(str(data["metadata_json"]))) if "metadata_json" in data else {}
    elif path.suffix.lower() == ".xdmf" and _inline_xml(path):
        points, cells, inclusion_id, reading = _read_xdmf_xml(path)
    else:
        m = _read_with_meshio(path)
        points = np.asarray(m.points, dtype=np.float64)
        dim = 3 if any(b.type == "tetra" for b in m.cells) else 2
        points = points[:, :dim]
        blocks = [i for i, b in enumerate(m.cells) if b.type == _CELL_TYPES[dim]]
        if not blocks:
            raise ValueError(f"{path}: expected triangle or tetra cells, found {[b.type for b in m.cells]}")
        cells = np.concatenate([m.cells[i].data for i in blocks]).astype(np.int64)
        ids = _ids_from_cell_data(m.cell_data, blocks)
        if ids is None:
            ids = _ids_from_cell_sets(m.cell_sets, blocks, [len(m.cells[i].data) for i in blocks])
        inclusion_id = ids if ids is not None else np.zeros(len(cells), np.int64)
        points, cells = _in_written_order(points, cells, m.point_data.get("node_id"))
        reading = _reading_of(path, m.field_data)
    lower = points.min(axis=0)
    if np.any(np.abs(lower) > 1e-9 * np.ptp(points, axis=0).max()):
        raise ValueError(f"{path}: expected a box with its origin at 0, the points start at {lower.tolist()}")
    box = tuple(float(v) for v in (points.max(axis=0) if box is None else box))
    if len(box) != points.shape[1]:
        raise ValueError(f"box has {len(box)} lengths, the mesh is {points.shape[1]}D")
    pairs = make_periodic_pairs(points, box) if periodic else {}
    return Mesh(points=points, cells=cells, inclusion_id=inclusion_id, box=box, periodic=periodic,
                periodic_pairs=pairs, metadata={"source": str(path), "input_reading": reading})


# Cell-data keys that carry the inclusion id, with what jaxmesh's writers add to it.
_ID_KEYS = {"inclusion_id": 0, "gmsh:physical": 1, "medit:ref": 0}


def _ids_from_cell_data(cell_data, blocks: list[int]) -> np.ndarray | None:
    for key, offset in _ID_KEYS.items():
        if key in cell_data:
            return np.concatenate([np.asarray(cell_data[key][i]) for i in blocks]).astype(np.int64) - offset
    return None


def _reading_of(path: Path, field_data: dict) -> dict:
    """The input reading a file written by jaxmesh carries (`_write.input_reading`): .vtu field data,
    the .msh section or the .inp comment line that meshio skips; {} when it carries none."""
    prefix = INPUT_READING_TAG + "_"
    reading = {k.removeprefix(prefix): np.asarray(v).ravel().tolist() for k, v in field_data.items()
               if k.startswith(prefix)}
    for flag in ("redistanced", "box_layers_closed"):
        if flag in reading:
            reading[flag] = bool(reading[flag][0])
    if reading or path.suffix.lower() not in (".msh", ".inp"):
        return reading
    with open(path, "rb") as fh:  # .inp: in the first lines; .msh: the last section
        if path.suffix.lower() == ".msh":
            fh.seek(max(0, fh.seek(0, os.SEEK_END) - 4096))
        lines = [line.strip() for line in fh.read(4096).decode(errors="replace").splitlines()]
    for i, line in enumerate(lines):
        if line == f"${INPUT_READING_TAG}" and i + 1 < len(lines):
            return json.loads(lines[i + 1])
        if line.startswith(f"** {INPUT_READING_TAG} "):
            return json.loads(line.removeprefix(f"** {INPUT_READING_TAG} "))
    return {}


def _read_with_meshio(path: Path):
    """meshio.read, its failures as ValueError: on a file it cannot parse it prints and calls sys.exit(1)."""
    import meshio

    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            return meshio.read(path)
    except ModuleNotFoundError as err:  # meshio's XDMF reader imports h5py, not a dependency here
        raise ValueError(f"{path}: reading it needs the package {err.name!r}, which is not installed; hint: "
                         f"pip install {err.name}") from None
    except (SystemExit, Exception) as err:
        detail = " ".join(said.getvalue().split()) or f"{type(err).__name__}: {err}"
        raise ValueError(f"{path}: meshio could not read it as a mesh ({detail}); hint: jaxmesh writes .vtu, "
                         ".msh, .xdmf, .inp, .vtk and .npz meshes") from None


def _ids_from_cell_sets(cell_sets: dict, blocks: list[int], sizes: list[int]) -> np.ndarray | None:
    """inclusion_id from element sets named 'matrix' / 'inclusion_K' (jaxmesh's .inp), or None."""
    named = {region_of_name(name): per_block for name, per_block in cell_sets.items()}
    named.pop(None, None)
    if not named:
        return None
    ids = np.zeros(sum(sizes), np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    for k, per_block in named.items():
        for position, block in enumerate(blocks):
            if block < len(per_block) and per_block[block] is not None:
                ids[offsets[position] + np.asarray(per_block[block], np.int64)] = k
    return ids


def _in_written_order(points: np.ndarray, cells: np.ndarray, node_id) -> tuple[np.ndarray, np.ndarray]:
    """Undo the .msh writer's renumbering by entity block: node k of the file was node_id[k] of the mesh."""
    if node_id is None:
        return points, cells
    order = np.asarray(node_id).round().astype(np.int64)
    if not np.array_equal(np.sort(order), np.arange(len(points))):
        return points, cells  # not a permutation: not jaxmesh's numbering
    restored = np.empty_like(points)
    restored[order] = points
    return restored, order[cells]


def _inline_xml(path: Path) -> bool:
    """Whether an XDMF file keeps all its data inline (Format="XML"), as jaxmesh writes it."""
    import xml.etree.ElementTree as ET

    try:
        items = list(ET.parse(path).getroot().iter("DataItem"))
    except ET.ParseError as err:
        raise ValueError(f"{path}: not an XDMF (XML) file: {err}") from None
    return all(item.get("Format", "XML") == "XML" for item in items)


def _read_xdmf_xml(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(points, cells, inclusion_id, input reading) of an inline-XML XDMF file with one grid of triangles or tetrahedra
    (meshio's reader needs h5py even for inline data)."""
    import xml.etree.ElementTree as ET

    grid = ET.parse(path).getroot().find("Domain/Grid")
    if grid is None or grid.find("Geometry/DataItem") is None or grid.find("Topology/DataItem") is None:
        raise ValueError(f"{path}: expected an XDMF Domain/Grid with a Geometry and a Topology")

    def values(item, dtype):
        shape = [int(v) for v in item.get("Dimensions").split()]
        return np.array(item.text.split(), dtype=dtype).reshape(shape)

    points = values(grid.find("Geometry/DataItem"), np.float64)
    cells = values(grid.find("Topology/DataItem"), np.int64)
    ids = next((values(a.find("DataItem"), np.int64).ravel() for a in grid.findall("Attribute")
                if a.get("Name") == "inclusion_id" and a.get("Center") == "Cell"), None)
    info = next((i.get("Value") for i in grid.findall("Information") if i.get("Name") == INPUT_READING_TAG), None)
    return (points, cells, np.zeros(len(cells), np.int64) if ids is None else ids,
            {} if info is None else json.loads(info))
