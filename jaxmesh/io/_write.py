"""Writing meshes: .vtu, .msh (Gmsh 4.1 ASCII), .xdmf, .inp (Abaqus), .vtk, .npz — always atomically.

Every writer goes through `atomic_path`: the file is written under a temporary name in the
target folder (same extension, so meshio recognises it) and renamed over the target only when
complete, so a failed write never leaves a partial file behind.
"""

from __future__ import annotations

import io
import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .._mesh import CELL_TYPES, FACET_TYPES, box_features, face_names, on_box_planes

FORMATS = {".vtu": "vtu", ".msh": "gmsh", ".xdmf": "xdmf", ".inp": "abaqus", ".vtk": "vtk", ".npz": "npz"}
_ALIASES = {"msh": "gmsh", "gmsh41": "gmsh", "inp": "abaqus", "vtu": "vtu", "gmsh": "gmsh", "xdmf": "xdmf",
            "abaqus": "abaqus", "vtk": "vtk", "npz": "npz"}
_GMSH_TYPES = {"line": 1, "triangle": 2, "tetra": 4}


@contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path next to `path` (same suffix); rename it onto `path` on success.

    On any exception the temporary file is removed and `path` is left untouched.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"folder {str(path.parent)!r} does not exist; hint: create it before writing {path.name}")
    tmp = path.parent / f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def resolve_format(path: Path, file_format: str | None) -> str:
    if file_format is None:
        fmt = FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise ValueError(f"cannot tell the mesh format from {path.name!r}: supported extensions are "
                             f"{', '.join(FORMATS)}; hint: pass file_format=")
        return fmt
    fmt = _ALIASES.get(str(file_format).lower().lstrip("."))
    if fmt is None:
        raise ValueError(f"unknown file_format {file_format!r}: supported are {', '.join(sorted(set(_ALIASES)))}")
    return fmt


def _boundary_flags(mesh) -> dict[str, np.ndarray]:
    """Point data: one int8 flag per box face plus a bitmask (bit 2 * axis + side)."""
    on = on_box_planes(mesh.points, mesh.box)  # (n, d, 2)
    flat = on.reshape(len(on), -1)
    out = {f"boundary_{name}": flat[:, f].astype(np.int8) for f, name in enumerate(face_names(mesh.dim))}
    out["boundary_mask"] = (flat.astype(np.int64) << np.arange(flat.shape[1])).sum(axis=1).astype(np.int32)
    return out


def _points3(mesh) -> np.ndarray:
    """VTK-family formats want 3 coordinates: pad 2D points with z = 0."""
    if mesh.dim == 3:
        return mesh.points
    return np.column_stack([mesh.points, np.zeros(mesh.n_points)])


def input_reading(metadata: dict) -> dict:
    """How the mesh's input was read, as the files carry it: {"roll_samples", "roll_offset"} when the
    grid was rolled, {"redistanced": True} when redistanced, {"box_layers_closed": True} when a plain
    box's layers along its planes were closed; {} when read as given. `jaxmesh validate
    --geometry` reads the input the same way (`read_mesh` puts it in metadata["input_reading"])."""
    meta = metadata or {}
    out = {}
    if meta.get("roll"):
        out["roll_samples"] = [int(k) for k in meta["roll"]["samples"]]
        out["roll_offset"] = [float(v) for v in meta["roll"]["offset"]]
    if (meta.get("parameters") or {}).get("redistance"):
        out["redistanced"] = True
    if (meta.get("parameters") or {}).get("close_box_layers"):
        out["box_layers_closed"] = True
    return out


INPUT_READING_TAG = "jaxmesh_input"  # the .msh section, .xdmf Information and .inp comment that hold it


def _vtu_field_data(path: Path, reading: dict) -> None:
    """Add the input reading as numeric FieldData (meshio's VTU writer drops field_data), one array
    per key: ParaView shows them under the dataset's field data."""
    if not reading:
        return
    arrays = "".join(
        f'<DataArray type="{"Float64" if isinstance(v[0], float) else "Int64"}" Name="{INPUT_READING_TAG}_{k}" '
        f'NumberOfTuples="{len(v)}" format="ascii">{" ".join(repr(x) for x in v)}</DataArray>'
        for k, v in ((k, v if isinstance(v, list) else [int(v)]) for k, v in reading.items()))
    text = path.read_bytes()
    head = b"<UnstructuredGrid>"
    if text.count(head) != 1:
        raise RuntimeError(f"{path}: expected one <UnstructuredGrid> in meshio's VTU output")
    path.write_bytes(text.replace(head, head + f"<FieldData>{arrays}</FieldData>".encode()))


def region_name(k: int) -> str:
    """Name of region k in the files (element sets, physical groups): 'matrix' or 'inclusion_k'."""
    return "matrix" if k == 0 else f"inclusion_{k}"


def region_of_name(name: str) -> int | None:
    """Inverse of `region_name` (any case); None for another name."""
    label = name.lower()
    if label == "matrix":
        return 0
    number = label.removeprefix("inclusion_")
    return int(number) if number != label and number.isdigit() else None


def write_mesh(mesh, path: str | Path, file_format: str | None = None) -> Path:
    """Write a `jaxmesh.Mesh` atomically, the format chosen by extension (or `file_format`).

    Formats: .vtu (cell data `Mesh.cell_arrays`: inclusion_id, phase, a labelled image's label;
    point data boundary flags), .msh (Gmsh 4.1 ASCII, physical groups per inclusion and per box
    face, $Periodic from periodic_pairs), .xdmf (XML, no h5py), .inp (Abaqus, element sets per
    inclusion, node sets per face/edge/corner), .vtk (legacy VTK), .npz (raw arrays, periodic
    pairs and metadata as JSON).

    Args:
        mesh: the mesh to write.
        path: target file; its folder must exist.
        file_format: one of vtu, gmsh/msh, xdmf, abaqus/inp, vtk, npz; default from the extension.
    Returns:
        the written path.

    Example: ``write_mesh(mesh, "rve.msh")``.
    """
    path = Path(path)
    fmt = resolve_format(path, file_format)
    import meshio

    with atomic_path(path) as tmp:
        if fmt == "npz":
            _write_npz(mesh, tmp)
        elif fmt == "gmsh":
            _write_gmsh41(mesh, tmp)
        elif fmt == "abaqus":
            ids = mesh.inclusion_id
            cell_sets = {region_name(int(k)): [np.flatnonzero(ids == k)] for k in np.unique(ids)}
            point_sets = {k: v for k, v in mesh.boundary_nodes().items() if len(v)}
            m = meshio.Mesh(mesh.points, [(CELL_TYPES[mesh.dim], mesh.cells)],
                            point_sets=point_sets, cell_sets=cell_sets)
            meshio.write(tmp, m, file_format="abaqus")
            _abaqus_comment(tmp, input_reading(mesh.metadata))
        elif fmt == "xdmf":
            _write_xdmf(mesh, tmp)
        else:
            m = meshio.Mesh(_points3(mesh), [(CELL_TYPES[mesh.dim], mesh.cells)],
                            point_data=_boundary_flags(mesh),
                            cell_data={name: [values] for name, values in mesh.cell_arrays().items()})
            meshio.write(tmp, m, file_format=fmt)
            if fmt == "vtu":
                _vtu_field_data(tmp, input_reading(mesh.metadata))
    return path


def _xdmf_item(parent, data: np.ndarray):
    """An inline XML DataItem in meshio's layout (DataType / Precision / Dimensions)."""
    import xml.etree.ElementTree as ET

    data = np.asarray(data)
    kind = "Float" if data.dtype.kind == "f" else "Int"
    item = ET.SubElement(parent, "DataItem", DataType=kind, Dimensions=" ".join(map(str, data.shape)),
                         Format="XML", Precision=str(data.dtype.itemsize))
    buf = io.StringIO()
    np.savetxt(buf, data.reshape(len(data), -1), fmt="%.17g" if kind == "Float" else "%d")
    item.text = "\n" + buf.getvalue()
    return item


def _write_xdmf(mesh, tmp: Path) -> None:
    """XDMF 3 with inline XML data: meshio 5.3.5's writer imports h5py even for XML, so write it here."""
    import xml.etree.ElementTree as ET

    root = ET.Element("Xdmf", Version="3.0")
    grid = ET.SubElement(ET.SubElement(root, "Domain"), "Grid", Name="Grid")
    _xdmf_item(ET.SubElement(grid, "Geometry", GeometryType="XYZ"[: mesh.dim]), mesh.points)
    topo = ET.SubElement(grid, "Topology", TopologyType={2: "Triangle", 3: "Tetrahedron"}[mesh.dim],
                         NumberOfElements=str(mesh.n_cells), NodesPerElement=str(mesh.dim + 1))
    _xdmf_item(topo, mesh.cells)
    for center, data in (("Node", _boundary_flags(mesh)),
                         ("Cell", mesh.cell_arrays())):
        for name, values in data.items():
            att = ET.SubElement(grid, "Attribute", Name=name, AttributeType="Scalar", Center=center)
            _xdmf_item(att, values)
    reading = input_reading(mesh.metadata)
    if reading:
        ET.SubElement(grid, "Information", Name=INPUT_READING_TAG, Value=json.dumps(reading))
    ET.ElementTree(root).write(tmp, xml_declaration=True, encoding="utf-8")


def _abaqus_comment(path: Path, reading: dict) -> None:
    """The input reading as a comment line before the nodes (readers skip '**' lines)."""
    if reading:
        text = path.read_text()
        if "\n*NODE" not in text:
            raise RuntimeError(f"{path}: expected a *NODE keyword in meshio's Abaqus output")
        path.write_text(text.replace("\n*NODE", f"\n** {INPUT_READING_TAG} {json.dumps(reading)}\n*NODE", 1))


def _write_npz(mesh, tmp: Path) -> None:
    arrays = {"points": mesh.points, "cells": mesh.cells, **mesh.cell_arrays(),
              "box": np.asarray(mesh.box), "periodic": np.asarray(mesh.periodic),
              "metadata_json": np.asarray(json.dumps(mesh.metadata, default=str))}
    for a, p in (mesh.periodic_pairs or {}).items():
        arrays[f"periodic_pairs_{int(a)}"] = np.asarray(p, dtype=np.int64)
    with open(tmp, "wb") as fh:  # a file handle: np.savez would append .npz to a path
        np.savez_compressed(fh, **arrays)


def _fmt_rows(fh, ints: np.ndarray) -> None:
    if len(ints):
        np.savetxt(fh, ints, fmt="%d")


def _write_gmsh41(mesh, tmp: Path) -> None:
    """Gmsh 4.1 ASCII with box entities (corners, edges, faces), one volume entity per inclusion.

    Entity tags: box features numbered from 1 within each dimension in `box_features` order
    (faces: xmin=1, xmax=2, ymin=3, ...); volume entity and physical tag of inclusion k = k + 1
    (named 'matrix' / 'inclusion_k'); box faces carry physical groups named 'xmin', 'xmax', ...
    Periodic links: max face (slave) <- min face (master), affine = translation by L.
    Node tags are renumbered by entity block; $NodeData "node_id" holds each node's index in
    mesh.points.
    """
    d, pts, box = mesh.dim, mesh.points, np.asarray(mesh.box)
    ids = mesh.inclusion_id
    xyz = np.column_stack([pts, np.zeros((len(pts), 3 - d))])
    feats = box_features(d)
    by_dim = {}  # entity dim -> list of features, tag = position + 1
    for f in feats:
        by_dim.setdefault(d - len(f), []).append(f)
    tag_of = {f: i + 1 for fl in by_dim.values() for i, f in enumerate(fl)}
    vol_ids = [int(k) for k in np.unique(ids)]

    def feat_bbox(f):
        lo, hi = np.zeros(3), np.concatenate([box, np.zeros(3 - d)])
        for a, s in f:
            lo[a] = hi[a] = s * box[a]
        return lo, hi

    # Node classification: box feature given by the planes a node lies on, else a volume.
    on = on_box_planes(pts, box)
    node_dim = np.full(len(pts), d)
    node_tag = np.zeros(len(pts), dtype=np.int64)
    code = np.zeros(len(pts), dtype=np.int64)
    for a in range(d):
        code = code * 3 + np.where(on[:, a, 0], 1, np.where(on[:, a, 1], 2, 0))
    for f in feats:
        c = 0
        fd = dict(f)
        for a in range(d):
            c = c * 3 + (fd[a] + 1 if a in fd else 0)
        sel = code == c
        node_dim[sel], node_tag[sel] = d - len(f), tag_of[f]
    inner = node_dim == d
    big = np.iinfo(np.int64).max
    min_id = np.full(len(pts), big)
    np.minimum.at(min_id, mesh.cells.ravel(), np.repeat(ids, d + 1))
    min_id[min_id == big] = vol_ids[0] if vol_ids else 0
    node_tag[inner] = min_id[inner] + 1

    bfac = mesh.boundary_facets()
    fnames = face_names(d)
    with open(tmp, "w") as fh:
        fh.write("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n")
        phys = [(d, k + 1, region_name(k)) for k in vol_ids] + [(d - 1, i + 1, n) for i, n in enumerate(fnames)]
        fh.write(f"$PhysicalNames\n{len(phys)}\n")
        fh.writelines(f'{pd} {pt} "{pn}"\n' for pd, pt, pn in phys)
        fh.write("$EndPhysicalNames\n$Entities\n")
        n_ent = [len(by_dim.get(k, [])) for k in range(d)] + [len(vol_ids)]
        fh.write(" ".join(str(x) for x in n_ent + [0] * (4 - len(n_ent))) + "\n")
        for k in range(d):
            for f in by_dim.get(k, []):
                lo, hi = feat_bbox(f)
                box_txt = " ".join(f"{x:.16g}" for x in (lo if k == 0 else np.concatenate([lo, hi])))
                physical = "1 " + str(tag_of[f]) if k == d - 1 else "0"
                if k == 0:
                    fh.write(f"{tag_of[f]} {box_txt} {physical}\n")
                    continue
                fset = set(f)  # bounding features: one more constraint
                bounds = [tag_of[g] for g in by_dim.get(k - 1, []) if fset < set(g)]
                fh.write(f"{tag_of[f]} {box_txt} {physical} {len(bounds)} {' '.join(map(str, bounds))}\n")
        for k in vol_ids:
            sel = np.unique(mesh.cells[ids == k])
            lo, hi = xyz[sel].min(0), xyz[sel].max(0)
            box_txt = " ".join(f"{x:.16g}" for x in np.concatenate([lo, hi]))
            fh.write(f"{k + 1} {box_txt} 1 {k + 1} 0\n")
        fh.write("$EndEntities\n$Nodes\n")
        # Node tags follow the entity blocks (1..n in file order): readers that store points in
        # file order (meshio) then agree with the tags used by elements and $Periodic.
        order = np.lexsort((np.arange(len(pts)), node_tag, node_dim))
        new_tag = np.empty(len(pts), dtype=np.int64)
        new_tag[order] = np.arange(1, len(pts) + 1)
        blocks = sorted({(int(a), int(b)) for a, b in zip(node_dim, node_tag)})
        fh.write(f"{len(blocks)} {len(pts)} 1 {len(pts)}\n")
        for bd, bt in blocks:
            sel = order[(node_dim[order] == bd) & (node_tag[order] == bt)]
            fh.write(f"{bd} {bt} 0 {len(sel)}\n")
            _fmt_rows(fh, new_tag[sel][:, None])
            np.savetxt(fh, xyz[sel], fmt="%.17g")
        fh.write("$EndNodes\n$Elements\n")
        eblocks = [(d, k + 1, _GMSH_TYPES[CELL_TYPES[d]], mesh.cells[ids == k]) for k in vol_ids]
        eblocks += [(d - 1, i + 1, _GMSH_TYPES[FACET_TYPES[d]], bfac[n]) for i, n in enumerate(fnames) if len(bfac[n])]
        total = sum(len(b[3]) for b in eblocks)
        fh.write(f"{len(eblocks)} {total} 1 {total}\n")
        start = 1
        for bd, bt, et, conn in eblocks:
            fh.write(f"{bd} {bt} {et} {len(conn)}\n")
            _fmt_rows(fh, np.column_stack([np.arange(start, start + len(conn)), new_tag[conn]]))
            start += len(conn)
        fh.write("$EndElements\n")
        if mesh.periodic and mesh.periodic_pairs:
            links = sorted(mesh.periodic_pairs.items())
            fh.write(f"$Periodic\n{len(links)}\n")
            for a, pairs in links:
                affine = np.eye(4)
                affine[a, 3] = box[a]  # master (x_a = 0) -> slave (x_a = L_a)
                fh.write(f"{d - 1} {tag_of[((a, 1),)]} {tag_of[((a, 0),)]}\n")
                fh.write("16 " + " ".join(f"{x:.16g}" for x in affine.ravel()) + "\n")
                fh.write(f"{len(pairs)}\n")
                _fmt_rows(fh, new_tag[np.asarray(pairs, dtype=np.int64)[:, ::-1]])
            fh.write("$EndPeriodic\n")
        # The jaxmesh node index of every Gmsh node, to map file data back onto mesh.points.
        fh.write(f'$NodeData\n1\n"node_id"\n1\n0\n3\n0\n1\n{len(pts)}\n')
        _fmt_rows(fh, np.column_stack([np.arange(1, len(pts) + 1), order]))
        fh.write("$EndNodeData\n")
        reading = input_reading(mesh.metadata)
        if reading:  # last: Gmsh and meshio skip sections they do not know, simpler readers stop before
            fh.write(f"${INPUT_READING_TAG}\n{json.dumps(reading)}\n$End{INPUT_READING_TAG}\n")
