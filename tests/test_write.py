"""Mesh container, file round trips (meshio read-back), atomic writes, plots."""

import json
import os
import re
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from jaxmesh._mesh import Mesh, face_names, structured_mesh
from jaxmesh._plot import mid_plane_section, plot_mesh, plot_quality_histogram
from jaxmesh.io import _write
from jaxmesh.io._write import write_mesh


def _mesh(dim):
    """Structured periodic mesh with inclusion 1 at the centre and inclusion 2 at the origin corner."""
    m = structured_mesh((6,) * dim if dim == 2 else (4,) * dim)
    c = m.points[m.cells].mean(axis=1)
    m.inclusion_id[np.linalg.norm(c - 0.5, axis=1) < 0.3] = 1
    m.inclusion_id[np.linalg.norm(c, axis=1) < 0.3] = 2
    m.metadata.update(h=0.25, note="test")
    return m


def _rows(a):
    """Rows as a sorted set of tuples (block order and row order do not matter)."""
    return sorted(map(tuple, np.asarray(a).tolist()))


@pytest.fixture(params=[2, 3], ids=["2d", "3d"])
def mesh(request):
    return _mesh(request.param)


def test_mesh_properties_and_boundary_nodes(mesh):
    d = mesh.dim
    assert mesh.n_points == len(mesh.points) and mesh.n_cells == len(mesh.cells)
    assert mesh.phase.dtype == np.int8 and set(np.unique(mesh.phase)) == {0, 1}
    nodes = mesh.boundary_nodes()
    assert len(nodes) == (8 if d == 2 else 26)
    n1 = round(mesh.n_points ** (1 / d))  # nodes per axis
    for name in face_names(d):
        assert len(nodes[name]) == n1 ** (d - 1)
        a, side = "xyz".index(name[0]), name[1:] == "max"
        np.testing.assert_array_equal(mesh.points[nodes[name], a], side * mesh.box[a])
    corner = "xmax_ymin" if d == 2 else "xmax_ymin_zmax"
    assert len(nodes[corner]) == 1
    np.testing.assert_array_equal(mesh.points[nodes[corner][0]], [1, 0] if d == 2 else [1, 0, 1])
    if d == 3:
        assert len(nodes["xmin_ymin"]) == n1
    assert "Mesh(dim=" in repr(mesh)


def test_boundary_facets_are_outward_and_cover_faces(mesh):
    d = mesh.dim
    for f, (name, facets) in enumerate(mesh.boundary_facets().items()):
        p = mesh.points[facets]
        e = p[:, 1:] - p[:, :1]
        normal = np.stack([e[:, 0, 1], -e[:, 0, 0]], -1) if d == 2 else np.cross(e[:, 0], e[:, 1])
        outward = np.zeros(d)
        outward[f // 2] = 1.0 if f % 2 else -1.0
        assert np.all(normal @ outward > 0), name
        measure = np.linalg.norm(normal, axis=1) / (1 if d == 2 else 2)
        assert measure.sum() == pytest.approx(1.0)


def test_mesh_constructor_rejects_bad_input():
    m = structured_mesh((2, 2))
    with pytest.raises(ValueError, match="cells"):
        Mesh(m.points, m.cells[:, :2], m.inclusion_id, m.box)
    with pytest.raises(ValueError, match="inclusion_id"):
        Mesh(m.points, m.cells, m.inclusion_id[:-1], m.box)
    with pytest.raises(ValueError, match="box"):
        Mesh(m.points, m.cells, m.inclusion_id, (1.0, -1.0))
    with pytest.raises(ValueError, match="points"):
        Mesh(np.zeros((4, 4)), m.cells, m.inclusion_id, m.box)


def test_to_meshio(mesh):
    mm = mesh.to_meshio()
    assert mm.cells[0].type == ("triangle" if mesh.dim == 2 else "tetra")
    np.testing.assert_array_equal(mm.cell_data["inclusion_id"][0], mesh.inclusion_id)
    np.testing.assert_array_equal(mm.cell_data["phase"][0], mesh.phase)
    assert set(mm.point_sets) == set(mesh.boundary_nodes())


def test_vtu_and_vtk_round_trip(mesh, tmp_path):
    for ext in ("vtu", "vtk"):
        path = mesh.write(tmp_path / f"m.{ext}")
        back = meshio.read(path)
        np.testing.assert_allclose(back.points[:, : mesh.dim], mesh.points)
        np.testing.assert_array_equal(back.cells[0].data, mesh.cells)
        np.testing.assert_array_equal(back.cell_data["inclusion_id"][0], mesh.inclusion_id)
        np.testing.assert_array_equal(back.cell_data["phase"][0], mesh.phase)
        nodes = mesh.boundary_nodes()
        for name in face_names(mesh.dim):
            np.testing.assert_array_equal(np.flatnonzero(back.point_data[f"boundary_{name}"]), nodes[name])
    assert sorted(os.listdir(tmp_path)) == ["m.vtk", "m.vtu"]  # no temporary left over


def test_gmsh41_round_trip_physical_groups_and_periodic(mesh, tmp_path):
    d = mesh.dim
    path = write_mesh(mesh, tmp_path / "m.msh")
    assert path.read_text().startswith("$MeshFormat\n4.1 0 8\n")
    back = meshio.read(path)
    # Nodes are grouped by entity in the file; node_id maps them back to mesh.points.
    node_id = back.point_data["node_id"].astype(int)
    assert sorted(node_id) == list(range(mesh.n_points))
    np.testing.assert_array_equal(back.points[:, :d], mesh.points[node_id])
    back.points = back.points[np.argsort(node_id)]
    back.cells = [meshio.CellBlock(b.type, node_id[b.data]) for b in back.cells]
    back.point_data["gmsh:dim_tags"] = back.point_data["gmsh:dim_tags"][np.argsort(node_id)]
    # Physical names: one per inclusion id (tag id + 1, dim d) and one per box face (dim d - 1).
    expected = {"matrix": [1, d], "inclusion_1": [2, d], "inclusion_2": [3, d]}
    expected.update({n: [i + 1, d - 1] for i, n in enumerate(face_names(d))})
    assert {k: list(map(int, v)) for k, v in back.field_data.items()} == expected
    cell_type = "triangle" if d == 2 else "tetra"
    phys = back.cell_data["gmsh:physical"]
    for k in (0, 1, 2):
        blocks = [b.data for b, p in zip(back.cells, phys) if b.type == cell_type and p[0] == k + 1]
        assert _rows(np.concatenate(blocks)) == _rows(mesh.cells[mesh.inclusion_id == k])
    facets = mesh.boundary_facets()
    facet_type = "line" if d == 2 else "triangle"
    for i, name in enumerate(face_names(d)):
        blocks = [b.data for b, p in zip(back.cells, phys) if b.type == facet_type and b.dim == d - 1
                  and p[0] == i + 1]
        assert _rows(np.concatenate(blocks)) == _rows(facets[name])
        # meshio turns physical names into cell sets.
        assert sum(len(s) for s in back.cell_sets[name] if s is not None) == len(facets[name])
    # Periodic links: slave = max face, master = min face, affine = translation, node pairs.
    assert len(back.gmsh_periodic) == d
    for a, (edim, (slave, master), affine, slave_master) in enumerate(back.gmsh_periodic):
        assert (edim, slave, master) == (d - 1, 2 * a + 2, 2 * a + 1)
        t = np.eye(4)
        t[a, 3] = mesh.box[a]
        np.testing.assert_allclose(np.asarray(affine).reshape(4, 4), t)
        np.testing.assert_array_equal(node_id[slave_master], mesh.periodic_pairs[a][:, ::-1])
    # Node entities: corners on dim-0 entities, interior nodes on the volume entities.
    dim_tags = back.point_data["gmsh:dim_tags"]
    corner = mesh.boundary_nodes()["xmin_ymin" if d == 2 else "xmin_ymin_zmin"][0]
    assert dim_tags[corner, 0] == 0
    on_box = np.zeros(mesh.n_points, bool)
    for name in face_names(d):
        on_box[mesh.boundary_nodes()[name]] = True
    assert np.all(dim_tags[~on_box, 0] == d) and np.all(dim_tags[on_box, 0] < d)


def test_abaqus_round_trip_sets(mesh, tmp_path):
    back = meshio.read(write_mesh(mesh, tmp_path / "m.inp"))
    np.testing.assert_allclose(back.points[:, : mesh.dim], mesh.points)
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells)
    for k, name in [(0, "matrix"), (1, "inclusion_1"), (2, "inclusion_2")]:
        np.testing.assert_array_equal(np.sort(back.cell_sets[name][0]), np.flatnonzero(mesh.inclusion_id == k))
    nodes = mesh.boundary_nodes()
    assert set(back.point_sets) == {k for k, v in nodes.items() if len(v)}
    for name, ids in back.point_sets.items():
        np.testing.assert_array_equal(np.sort(ids), nodes[name])


def test_xdmf_xml_round_trip(mesh, tmp_path):
    path = write_mesh(mesh, tmp_path / "m.xdmf")
    assert sorted(os.listdir(tmp_path)) == ["m.xdmf"]  # inline XML: no .h5 companion
    grid = ET.parse(path).getroot().find("Domain/Grid")

    def item(node):
        it = node.find("DataItem")
        assert it.get("Format") == "XML"
        dims = [int(x) for x in it.get("Dimensions").split()]
        return np.array(it.text.split(), dtype=float if it.get("DataType") == "Float" else int).reshape(dims)

    np.testing.assert_array_equal(item(grid.find("Geometry")), mesh.points)  # %.17g: exact
    np.testing.assert_array_equal(item(grid.find("Topology")), mesh.cells)
    attrs = {a.get("Name"): (a.get("Center"), item(a)) for a in grid.findall("Attribute")}
    assert attrs["inclusion_id"][0] == "Cell"
    np.testing.assert_array_equal(attrs["inclusion_id"][1], mesh.inclusion_id)
    np.testing.assert_array_equal(attrs["phase"][1], mesh.phase)
    assert attrs["boundary_xmin"][0] == "Node"
    try:  # meshio's XDMF reader imports h5py even for XML data
        import h5py  # noqa: F401
    except ImportError:
        return
    back = meshio.read(path)
    np.testing.assert_array_equal(back.cell_data["inclusion_id"][0], mesh.inclusion_id)


def test_npz_raw_arrays(mesh, tmp_path):
    path = mesh.write(tmp_path / "m.npz")
    with np.load(path) as z:
        np.testing.assert_array_equal(z["points"], mesh.points)
        np.testing.assert_array_equal(z["cells"], mesh.cells)
        np.testing.assert_array_equal(z["inclusion_id"], mesh.inclusion_id)
        np.testing.assert_array_equal(z["box"], mesh.box)
        assert bool(z["periodic"])
        for a in range(mesh.dim):
            np.testing.assert_array_equal(z[f"periodic_pairs_{a}"], mesh.periodic_pairs[a])
        assert json.loads(str(z["metadata_json"])) == {"h": 0.25, "note": "test"}


def test_formats_and_errors(tmp_path):
    m = _mesh(2)
    with pytest.raises(ValueError, match=r"\.vtu.*\.msh.*\.xdmf.*\.inp.*\.vtk.*\.npz"):
        m.write(tmp_path / "m.stl")
    with pytest.raises(ValueError, match="file_format"):
        m.write(tmp_path / "m.vtu", file_format="stl")
    with pytest.raises(ValueError, match="does not exist"):
        m.write(tmp_path / "missing" / "m.vtu")
    path = m.write(tmp_path / "m.dat", file_format="vtu")  # explicit format wins over the extension
    assert meshio.read(path, file_format="vtu").cells[0].data.shape == m.cells.shape
    assert sorted(os.listdir(tmp_path)) == ["m.dat"]


def test_failed_write_leaves_no_file_and_keeps_old_one(tmp_path, monkeypatch):
    m = _mesh(3)

    def broken(filename, mesh, *args, **kwargs):
        with open(filename, "w") as fh:
            fh.write("partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(meshio, "write", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        m.write(tmp_path / "m.vtu")
    assert os.listdir(tmp_path) == []
    target = tmp_path / "m.inp"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        m.write(target)
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["m.inp"]
    # Non-meshio writers too.
    monkeypatch.setattr(_write, "_write_gmsh41", lambda mesh, tmp: (open(tmp, "w").write("x"), 1 / 0))
    with pytest.raises(ZeroDivisionError):
        m.write(tmp_path / "m.msh")
    assert os.listdir(tmp_path) == ["m.inp"]


def test_mid_plane_section_tiles_the_box_section():
    for div in [(5, 5, 5), (4, 4, 4)]:  # odd: plane between nodes; even: plane through a node layer
        m = structured_mesh(div, box=(2.0, 1.0, 1.0))
        polys, owner = mid_plane_section(m.points, m.cells, 0.5)
        area = [0.5 * (p[:, 0] @ np.roll(p[:, 1], -1) - p[:, 1] @ np.roll(p[:, 0], -1)) for p in polys]
        assert np.all(np.asarray(area) > 0)  # counter-clockwise, no degenerate polygon
        assert sum(area) == pytest.approx(2.0, rel=1e-12)
        z = m.points[m.cells[owner], 2]
        assert np.all(z.min(axis=1) < 0.5) and np.all(z.max(axis=1) >= 0.5)


def test_plots_write_png(mesh, tmp_path):
    from matplotlib.image import imread

    out = plot_mesh(mesh, tmp_path / "mesh.png", title="test")
    img = imread(out)
    assert img.shape[0] > 200 and img.shape[1] > 400
    assert img[..., :3].std() > 0.05  # not a blank canvas
    plot_mesh(mesh, tmp_path / "phase.png", color_by="phase")
    hist = plot_quality_histogram(mesh, tmp_path / "q.png")
    assert imread(hist).shape[0] > 100
    assert sorted(os.listdir(tmp_path)) == ["mesh.png", "phase.png", "q.png"]
    with pytest.raises(ValueError, match="PNG"):
        plot_mesh(mesh, tmp_path / "mesh.jpg")
    with pytest.raises(ValueError, match="color_by"):
        plot_mesh(mesh, tmp_path / "x.png", color_by="quality")


def test_gmsh_itself_reads_the_file(mesh, tmp_path):
    """Cross-check with the real Gmsh where its Python API is installed (not a dependency)."""
    gmsh = pytest.importorskip("gmsh")
    path = write_mesh(mesh, tmp_path / "m.msh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        names = {gmsh.model.getPhysicalName(d, t) for d, t in gmsh.model.getPhysicalGroups()}
        assert names == {"matrix", "inclusion_1", "inclusion_2", *face_names(mesh.dim)}
        tags, coords, _ = gmsh.model.mesh.getNodes()
        x = dict(zip(tags, coords.reshape(-1, 3)))
        for a in range(mesh.dim):
            master, slaves, masters, affine = gmsh.model.mesh.getPeriodicNodes(mesh.dim - 1, 2 * a + 2)
            assert master == 2 * a + 1 and len(slaves) == len(mesh.periodic_pairs[a])
            t = np.asarray(affine).reshape(4, 4)
            for s, m in zip(slaves, masters):
                np.testing.assert_allclose(x[s], t[:3, :3] @ x[m] + t[:3, 3], atol=1e-12)
    finally:
        gmsh.finalize()


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf", ".vtk", ".npz", ".inp"])
def test_read_mesh_gives_back_what_was_written(mesh, tmp_path, suffix):
    """`jaxmesh validate` reads meshes through read_mesh: .xdmf failed there with meshio's
    ModuleNotFoundError for h5py, though the file is inline XML; .inp came back all matrix."""
    from jaxmesh.io import read_mesh

    back = read_mesh(write_mesh(mesh, tmp_path / f"m{suffix}"), box=mesh.box)
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-15)
    assert _rows(np.sort(back.cells, axis=1)) == _rows(np.sort(mesh.cells, axis=1))
    order = np.lexsort(np.sort(back.cells, axis=1).T[::-1])  # .inp: ids from its element sets
    expected = np.lexsort(np.sort(mesh.cells, axis=1).T[::-1])
    np.testing.assert_array_equal(back.inclusion_id[order], mesh.inclusion_id[expected])
    assert {a: len(p) for a, p in back.periodic_pairs.items()} == {a: len(p) for a, p in mesh.periodic_pairs.items()}


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf", ".vtk", ".npz", ".inp"])
def test_files_carry_how_the_input_was_read(mesh, tmp_path, suffix):
    """A rolled, redistanced run's mesh file says so (`jaxmesh validate --geometry` reads the input the
    same way); meshio still reads every file; legacy .vtk carries nothing."""
    import dataclasses

    from jaxmesh.io import read_mesh

    d = mesh.dim
    meta = {"roll": {"samples": [3] * d, "offset": [0.125] * d}, "parameters": {"redistance": True}}
    rolled = dataclasses.replace(mesh, metadata=meta)
    path = write_mesh(rolled, tmp_path / f"m{suffix}")
    expected = {} if suffix == ".vtk" else {"roll_samples": [3] * d, "roll_offset": [0.125] * d, "redistanced": True}
    assert read_mesh(path, box=mesh.box).metadata["input_reading"] == expected
    if suffix not in (".npz", ".xdmf"):  # meshio reads .xdmf only with h5py
        cell_type = "tetra" if d == 3 else "triangle"
        assert sum(len(b.data) for b in meshio.read(path).cells if b.type == cell_type) == mesh.n_cells
    as_given = write_mesh(mesh, tmp_path / f"given{suffix}")
    assert read_mesh(as_given, box=mesh.box).metadata["input_reading"] == {}


@pytest.mark.parametrize("name, content, message", [
    ("m.vtu", b"garbage", "meshio could not read it as a mesh (Error: Couldn't read file"),
    ("m.msh", b"garbage", "meshio could not read it as a mesh"),
    ("m.xdmf", b"garbage", "not an XDMF (XML) file"),
])
def test_read_mesh_of_a_damaged_file_is_a_clear_error(tmp_path, name, content, message):
    """meshio prints and calls sys.exit(1) on a file it cannot parse."""
    from jaxmesh.io import read_mesh

    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError, match=re.escape(message)):
        read_mesh(tmp_path / name)


def test_read_mesh_of_an_input_npz_says_it_is_an_input(tmp_path):
    from jaxmesh.io import read_mesh

    np.savez(tmp_path / "rve.npz", phi=np.ones((8, 8)))
    with pytest.raises(ValueError, match="an input file .phi or labels. goes to --geometry"):
        read_mesh(tmp_path / "rve.npz")
