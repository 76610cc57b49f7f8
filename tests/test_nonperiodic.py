"""Non-periodic meshes (`MeshConfig(periodic=False)`, `jaxmesh mesh --no-periodic`): inclusions cut
by the box are clipped, not wrapped; each face is meshed on its own; the validator passes. The 2D
mesher's own non-periodic tests are in tests/test_mesh2d.py."""

import json

import jax.numpy as jnp
import meshio
import numpy as np
import pytest

from jaxmesh import MeshConfig, Microstructure, mesh_rve, quality_report, sphere_sdf, validate
from jaxmesh._cli import main
from jaxmesh._generate import gaussian_random_field
from jaxmesh._quality import signed_volumes
from jaxmesh._sizing import interface_sources
from jaxmesh.geometry import _components as comp
from _fields import flat_bottom_ellipsoid

BOX = (1.0, 1.0, 1.0)
# centred; cut by a face, by an edge (two faces), by a corner (three faces)
SPHERES = [((0.5, 0.5, 0.5), 0.15), ((0.03, 0.5, 0.5), 0.2), ((0.97, 0.03, 0.5), 0.18), ((0.02, 0.98, 0.97), 0.2)]


def _clipped_volume(centre, radius, n=240):
    """Volume of the ball inside the unit box: midpoint rule on an n^3 grid over the ball's bounds."""
    c = np.asarray(centre)
    lo, hi = np.clip(c - radius, 0, 1), np.clip(c + radius, 0, 1)
    axes = [lo[a] + (np.arange(n) + 0.5) * (hi[a] - lo[a]) / n for a in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    return float((np.linalg.norm(X - c, axis=-1) < radius).sum() * np.prod((hi - lo) / n))


def _check_plain_box(mesh, ms):
    report = validate(mesh, ms)
    assert report.ok, report.summary()
    assert mesh.metadata["validation"]["ok"]
    assert not mesh.periodic and mesh.periodic_pairs == {}
    vol = signed_volumes(mesh.points, mesh.cells)
    assert vol.min() > 0 and abs(vol.sum() - np.prod(ms.box)) < 1e-9 * np.prod(ms.box)
    return vol


@pytest.fixture(scope="module")
def analytic_case():
    ms = Microstructure.from_functions([sphere_sdf(jnp.array(c), r) for c, r in SPHERES], BOX, (32, 32, 32),
                                       periodic=False)
    return ms, mesh_rve(ms, MeshConfig(iis=0.08, periodic=False, seed=1))


def test_spheres_cut_by_the_box_are_clipped_not_wrapped(analytic_case):
    ms, mesh = analytic_case
    vol = _check_plain_box(mesh, ms)
    for k, (c, r) in enumerate(SPHERES, start=1):
        # the clipped ball less the chord error of the faceted surface, ~ (h / r)^2 / 4: up to 9 % for
        # the small centred sphere, less for the clipped ones (their cuts are flat, hence exact)
        assert 0.88 < vol[mesh.inclusion_id == k].sum() / _clipped_volume(c, r) < 1.005
    # the corner sphere stays at its corner: a wrapped copy would put nodes at the seven others
    corner = mesh.points[np.unique(mesh.cells[mesh.inclusion_id == 4])]
    assert corner[:, 0].max() < 0.25 and corner[:, 1].min() > 0.75 and corner[:, 2].min() > 0.75
    assert quality_report(mesh)["min_dihedral_deg"] >= 10.0


def test_opposite_faces_are_meshed_independently(analytic_case):
    """x = 0 carries the face sphere's disc, x = 1 only the edge sphere's quarter disc: the two faces
    are different triangulations (a periodic mesh would have translates)."""
    _, mesh = analytic_case
    p = mesh.points
    on0, on1 = np.isclose(p[:, 0], 0.0, atol=0), np.isclose(p[:, 0], 1.0, atol=0)
    assert on0.sum() != on1.sum()
    lower = {tuple(q) for q in np.round(p[on0][:, 1:], 12)}
    upper = {tuple(q) for q in np.round(p[on1][:, 1:], 12)}
    assert len(lower ^ upper) > 0.1 * len(lower | upper)


def _non_periodic_field(seed, n=40, count=6):
    """Random non-overlapping spheres, several cut by the box, on a grid that is not periodic; the
    spheres keep clear of tangency with the box planes (a thin layer there is a feature below h)."""
    rng = np.random.default_rng(seed)
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    spheres = [(np.array([0.04, rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7)]), 0.17)]
    while len(spheres) < count:
        c, r = rng.uniform(0.0, 1.0, 3), rng.uniform(0.1, 0.16)
        clear = all(np.linalg.norm(c - c2) > r + r2 + 0.08 for c2, r2 in spheres)
        off_tangent = np.all(np.abs(np.minimum(c, 1 - c) - r) > 0.04)
        if clear and off_tangent:
            spheres.append((c, r))
    phi = np.min([np.linalg.norm(X - c, axis=-1) - r for c, r in spheres], axis=0)
    return phi, spheres


@pytest.mark.parametrize("seed", [0, 3])
def test_non_periodic_levelset_grid(seed):
    phi, _ = _non_periodic_field(seed)
    with pytest.raises(ValueError, match="periodic"):  # the field is really not periodic
        Microstructure.from_levelset(phi)
    ms = Microstructure.from_levelset(phi, periodic=False)
    mesh = mesh_rve(ms, MeshConfig(iis=0.1, periodic=False, seed=seed))
    _check_plain_box(mesh, ms)
    assert quality_report(mesh)["min_dihedral_deg"] >= 10.0
    with pytest.raises(ValueError, match="MeshConfig.periodic"):
        mesh_rve(ms, MeshConfig(iis=0.1))


def test_cli_no_periodic(tmp_path, capsys):
    phi, _ = _non_periodic_field(1, n=32, count=4)
    path = tmp_path / "phi.npy"
    np.save(path, phi)
    out, report = tmp_path / "plain.msh", tmp_path / "r.json"
    assert main(["mesh", str(path), "-o", str(out), "--iis", "0.12", "--no-periodic", "--report", str(report)]) == 0
    assert json.loads(report.read_text())["metadata"]["validation"]["ok"] is True
    assert "$Periodic" not in out.read_text()
    assert len(meshio.read(out).cells_dict["tetra"]) > 100
    assert main(["validate", str(out), "--geometry", str(path), "--no-periodic"]) == 0
    assert main(["mesh", str(path), "-o", str(tmp_path / "p.vtu"), "--iis", "0.12"]) == 2  # refused as periodic
    assert "periodic=False" in capsys.readouterr().err
    assert not (tmp_path / "p.vtu").exists()


def test_cli_no_periodic_2d(tmp_path):
    n = 64
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, indexing="ij"), -1)
    phi = np.minimum(np.linalg.norm(X - [0.05, 0.5], axis=-1) - 0.2, np.linalg.norm(X - [0.6, 0.97], axis=-1) - 0.15)
    path, out = tmp_path / "phi2d.npy", tmp_path / "plain2d.vtu"
    np.save(path, phi)
    assert main(["mesh", str(path), "-o", str(out), "--h", "0.04", "--no-periodic"]) == 0
    mesh = meshio.read(out)
    p = mesh.points[np.unique(mesh.cells_dict["triangle"][mesh.cell_data_dict["inclusion_id"]["triangle"] == 1])]
    assert p[:, 0].max() < 0.3  # the disc cut by x = 0 has no copy at x = 1
    assert main(["validate", str(out), "--geometry", str(path), "--no-periodic"]) == 0


def test_a_piece_the_box_cuts_thinner_than_a_grid_step():
    """A ball mostly beyond z = 0 leaves a cap 0.6 grid steps thick in the box: its marching cubes
    samples at a quarter of that, and the window must still hold the interpolant's overhang."""
    from jaxmesh._surface import as_size_fn, mesh_inclusion

    n = 48
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    ms = Microstructure.from_levelset(np.linalg.norm(X - [0.5, 0.5, -0.288], axis=-1) - 0.3, periodic=False)
    inc = ms.inclusions[0]
    assert inc.upper[2] - inc.lower[2] < 1 / n
    out = mesh_inclusion(inc, as_size_fn(0.05, ms.box, periodic=False), ms.box, periodic=False)
    p, t = out["points"], out["triangles"]
    assert len(t) > 100 and p.min() >= 0.0 and p.max() <= 1.0
    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    rim = uniq[count == 1]  # the cap is open only along its trace on z = 0
    assert len(rim) > 10 and (p[rim, 2] == 0.0).all() and (count <= 2).all()


@pytest.mark.parametrize("order", ["cubic", "linear"])
def test_grid_levelset_goes_on_linearly_beyond_the_samples(order):
    """Samples stop a step before x = L. Beyond the border samples the field is their linear
    continuation: a slab whose flat top lies between the last sample and z = L keeps that top there,
    to a small fraction of a step, with no overshoot and no crease (replicated border nodes bent the
    B-spline in the last cell: an overshoot under a flat top, a right-angle crease where a surface
    crosses a plane)."""
    n = 24
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    top = (n - 1) / n + 0.4 / n  # between the last sample and z = L
    phi = np.maximum(np.abs(X[..., :2] - 0.5).max(-1) - 0.2, X[..., 2] - top)
    phi = np.maximum(phi, 0.3 - X[..., 2])
    ms = Microstructure.from_levelset(phi, periodic=False, order=order)
    assert len(ms.inclusions) == 1 and ms.inclusions[0].upper[2] == 1.0
    z = np.linspace((n - 2) / n, 1.0 + 1.0 / n, 61)
    col = np.stack([np.full_like(z, 0.5), np.full_like(z, 0.5), z], 1)
    assert np.allclose(ms.phi(col), z - top, atol=0.05 / n, rtol=0)  # replicated nodes: 2 steps off
    # the size function sees that top: crossings in the last cell are sources (none before)
    sources = np.asarray(interface_sources(ms)[0])
    assert abs(sources[:, 2].max() - top) < 1e-6
    # a plane crossing z = 0 at 45 degrees: its level set stays straight through the first cell
    tilted = (X[..., 0] - X[..., 2] - 0.5) / np.sqrt(2.0)
    tilted = np.maximum(tilted, np.abs(X[..., 1] - 0.5) - 0.2)
    tilted = np.maximum(tilted, 0.25 - X[..., 0])
    ms = Microstructure.from_levelset(tilted, periodic=False, order=order)
    row = np.stack([0.5 + np.linspace(-1.0, 1.5, 26) / n, np.full(26, 0.5), np.linspace(-1.0, 1.5, 26) / n], 1)
    row[:, 0] -= 0.05  # off the zero set, inside the slab's straight part: phi = -0.05 / sqrt(2)
    assert np.allclose(ms.phi(row), -0.05 / np.sqrt(2.0), atol=0.05 / n, rtol=0)  # replicated: 0.7 steps


def test_the_continuation_beyond_a_box_edge_has_no_product_term():
    """Beyond an edge or corner each ghost node is its nearest grid node plus that node's outward
    slopes times the steps beyond. Continued axis after axis it also had k_x k_y times the mixed
    difference, which turns a field that is positive with outward slopes positive at the edge
    negative again two steps beyond it: a phantom lobe, on which the Newton projection of a
    plain-box surface stalled (`benchmarks/sweep_shapes.py`'s numpy_grf_s303, redistanced)."""
    field = np.full((6, 6), 9.0)  # a window of a 4 x 4 grid; its ghost nodes are overwritten
    field[2, 2], field[3, 2], field[2, 3], field[3, 3] = -2.0, 0.5, 0.5, 1.0
    ghosts = comp.extrapolate_beyond_domain(field, (0, 0), (4, 4))
    k = np.arange(1, 3)
    np.testing.assert_allclose(ghosts[3 + k[:, None], 3 + k[None, :]], 1.0 + 0.5 * k[:, None] + 0.5 * k[None, :])
    np.testing.assert_allclose(ghosts[3 + k, 2], 0.5 + 2.5 * k)  # beyond one plane only: as before
    assert (ghosts[3:, 3:] > 0).all()  # axis after axis: -5 at two steps beyond both planes
    x = np.arange(-2, 7)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    linear = 1.5 * X - 0.7 * Y + 0.3 * Z + 2.0
    given = np.where((np.abs(np.stack([X, Y, Z]) - 2) > 2).any(0), 99.0, linear)  # nodes 0..4 are the grid
    np.testing.assert_allclose(comp.extrapolate_beyond_domain(given, (-2, -2, -2), (5, 5, 5)), linear, atol=1e-12)


def test_bounds_hold_the_zero_set_in_the_last_cell():
    """A ball whose centre lies beyond z = L reaches the last sample and widens up to z = L: the
    inclusion's bounds, from which `label` decides what to evaluate, must hold that part too (from
    the grid crossings alone they fell a grid step short: the validator saw labels against the field)."""
    n = 64
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    phi = np.linalg.norm(X - np.array([0.1, 0.5, 1.179]), axis=-1) - 0.2  # cut by x = 0 too
    ms = Microstructure.from_levelset(phi, periodic=False)
    assert len(ms.inclusions) == 1 and ms.inclusions[0].upper[2] == 1.0
    pts = np.stack(np.meshgrid(np.linspace(0.0, 0.3, 121), np.linspace(0.35, 0.65, 61),
                               np.linspace((n - 1) / n, 1.0, 9), indexing="ij"), -1).reshape(-1, 3)
    inside = ms.phi(pts) < 0
    np.testing.assert_array_equal(ms.label(pts), inside.astype(np.int64))


def _lobes_meeting_beyond_the_samples(n: int, dim: int, apart: float) -> np.ndarray:
    """Two balls (r 0.17, centres at x = 1.1, `apart` along y): they overlap for x > 0.966 when
    0.21 apart, for x > 1.02 when 0.3 apart."""
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(*[x] * dim, indexing="ij"), -1)
    rest = [0.45] * (dim - 2)
    return np.minimum(np.linalg.norm(X - [1.1, 0.5 - apart / 2, *rest], axis=-1) - 0.17,
                      np.linalg.norm(X - [1.1, 0.5 + apart / 2, *rest], axis=-1) - 0.17)


def test_parts_that_meet_in_the_last_cell_are_one_inclusion():
    """Two parts apart at the last sample plane that meet between it and x = L: the field there is
    one zero set, so they are one inclusion (as two, each continued its own level set past the last
    sample, both reached below zero at x = L and their traces crossed on the box face: the faces
    stage stopped, as on a thresholded Gaussian field read as a plain box). Parts that meet only
    beyond x = L stay two."""
    joined = Microstructure.from_levelset(_lobes_meeting_beyond_the_samples(20, 2, 0.21), periodic=False)
    assert len(joined.inclusions) == 1
    assert joined.phi(np.array([[1.0, 0.5]]))[0] < 0 < joined.phi(np.array([[0.95, 0.5]]))[0]
    apart = Microstructure.from_levelset(_lobes_meeting_beyond_the_samples(20, 2, 0.3), periodic=False)
    assert len(apart.inclusions) == 2
    assert [inc.lower[1] < 0.5 for inc in apart.inclusions] == [True, False]  # ids in raster order
    ms = Microstructure.from_levelset(_lobes_meeting_beyond_the_samples(20, 3, 0.21), periodic=False)
    assert len(ms.inclusions) == 1
    mesh = mesh_rve(ms, MeshConfig(iis=0.1, periodic=False, seed=2))
    _check_plain_box(mesh, ms)
    face = mesh.points[np.unique(mesh.cells[mesh.inclusion_id == 1])]
    assert np.isclose(face[:, 0], 1.0).sum() > 3  # the inclusion reaches the face


@pytest.mark.parametrize("redistance", [False, True])
def test_parts_that_meet_across_a_grid_square_are_refused_as_touching(redistance):
    """Read as a plain box, this thresholded Gaussian field (`benchmarks/sweep_shapes.py`'s
    numpy_grf_s301) holds two components (5 and 6) whose samples are diagonal in one grid square,
    the square's other two samples >= 0: face-connected labelling keeps them apart, yet their level
    sets interpolated there meet (0.017 steps apart as given, overlapping redistanced). Their surfaces
    crossed (the surfaces stage stopped on 8 intersecting triangle pairs after minutes); they are
    refused at once as touching, by id and place. Periodic, the field is one component and loads."""
    field = gaussian_random_field((1.0, 1.0, 1.0), (40, 40, 40), 0.12, seed=301)
    phi = field - np.quantile(field, 0.25)  # thresholded as users write it: not a distance
    with pytest.raises(ValueError, match=r"closer across one grid cell .* inclusions 5 and 6: "
                                         + ("overlap" if redistance else r"gap ~ 0\.01") + r".* near x = \(0\.8"):
        Microstructure.from_levelset(phi, periodic=False, redistance=redistance)
    assert len(Microstructure.from_levelset(phi, periodic=False, redistance=redistance,
                                            check_gaps=False).inclusions) == 8
    assert len(Microstructure.from_levelset(phi, periodic=True, redistance=redistance).inclusions) == 1


def test_cli_a_trace_beside_a_box_edge(tmp_path):
    """`jaxmesh mesh --no-periodic` of a sphere (r 0.2, 64^3) crossing x = 0 and z = 0 whose trace on
    x = 0 passes 0.38 grid steps above the edge x = z = 0. At 139985b (replicated border nodes) the
    command run from a shell stopped in the volume recovery (507 surface triangles missing); the same
    code meshed it valid inside pytest, so this guards the input, it does not pin that failure."""
    n, r, cx = 64, 0.2, 0.1
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    centre = np.array([cx, 0.5, np.sqrt(r * r - cx * cx) + 0.38 / n])
    path, report = tmp_path / "phi.npy", tmp_path / "r.json"
    np.save(path, np.linalg.norm(X - centre, axis=-1) - r)
    assert main(["mesh", str(path), "-o", str(tmp_path / "m.vtu"), "--no-periodic", "--report", str(report)]) == 0
    assert json.loads(report.read_text())["metadata"]["validation"]["ok"] is True


def test_a_trace_beside_a_box_edge_meshes_valid():
    """A sphere crossing x = 0 and z = 0 whose trace on x = 0 passes 0.4 grid steps above the edge
    (x = 0, z = 0), and 0.2 steps (crossing) below it: a thin matrix wedge along the edge (valid before
    the border samples were continued linearly too)."""
    n = 32
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    r, cx = 0.25, 0.12
    for offset in (0.4 / n, -0.2 / n):
        centre = np.array([cx, 0.5, np.sqrt(r * r - cx * cx) + offset])
        phi = np.linalg.norm(X - centre, axis=-1) - r
        ms = Microstructure.from_levelset(phi, periodic=False)
        mesh = mesh_rve(ms, MeshConfig(iis=0.1, periodic=False))
        _check_plain_box(mesh, ms)
        assert quality_report(mesh)["min_dihedral_deg"] >= 5.0


def _mesh_a_sphere_beyond_the_box(centre, radius: float, depth: float, n: int = 32):
    """Plain n^3 box: a sphere centred outside it reaching `depth` grid steps in, and one r 0.2 inside.
    The piece in the box (inclusion 2) must mesh valid with some volume and min dihedral >= 5 deg."""
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    piece = np.linalg.norm(X - np.asarray(centre), axis=-1) - (radius + depth / n)
    ms = Microstructure.from_levelset(np.minimum(piece, np.linalg.norm(X - 0.55, axis=-1) - 0.2), periodic=False)
    mesh = mesh_rve(ms, MeshConfig(periodic=False))
    vol = _check_plain_box(mesh, ms)
    assert vol[mesh.inclusion_id == 2].sum() > 0
    assert quality_report(mesh)["min_dihedral_deg"] >= 5.0
    return ms


@pytest.mark.parametrize("depth", [0.15, 0.3])
def test_a_sliver_the_box_cuts_along_an_edge_meshes_valid(depth):
    """A sphere centred beyond the edge y = z = 0 reaches `depth` grid steps into the box: a rod along
    the edge, under half a step across. Its traces run along the edge, so the size function is refined
    to their distance from it; before (the rod sized like the box around it, its surface several times
    finer than h), the volume recovery diverged."""
    ms = _mesh_a_sphere_beyond_the_box((0.5, -0.1, -0.1), float(np.hypot(0.1, 0.1)), depth)
    rod = ms.inclusions[1]
    assert (np.asarray(rod.upper) - rod.lower)[1:].max() < 0.5 / 32


def test_a_shallow_cap_the_box_cuts_off_meshes_valid():
    """A sphere centred beyond z = 0 reaches 0.3 grid steps into the box: the interpolant makes the cap a
    flat lens with a thin wedge at its rim, its normals just beyond 15 degrees of the plane's. Sized like
    the box (box gaps within 15 degrees only), the volume recovery diverged at the rim; within 20 degrees
    the lens gets elements as thin as it."""
    _mesh_a_sphere_beyond_the_box((0.5, 0.5, -0.1), 0.1, 0.3)


@pytest.mark.parametrize("steps", [0.15, 0.3])
def test_a_sphere_passing_a_fraction_of_a_step_from_an_edge_meshes_valid(steps):
    """A sphere's distance sampled without wrapping, cut by the planes x = L and z = L and passing `steps`
    grid steps from their edge: the matrix layer beside the edge lies within the last grid cell, where no
    grid edge crosses the interface. Before sources on the box edges (`edge_gap_sources`) its box faces
    kept the box's h and the volume recovery diverged; before `gradient_scale` ignored the wrap-around
    jump, the field was divided by 19.5 and the surfaces failed. At 0.15 steps the field continued beyond
    the last sample crosses the edge by a sliver thinner than half a step (test_sizing's edge_gap_sources
    test); without a source there its surfaces missed the crossing."""
    n, R = 48, 0.1
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    a = (R + steps / n) / np.sqrt(2)
    ms = Microstructure.from_levelset(np.linalg.norm(x - np.array([1 - a, 0.5, 1 - a]), axis=-1) - R,
                                      periodic=False)
    mesh = mesh_rve(ms, MeshConfig(periodic=False))
    _check_plain_box(mesh, ms)
    assert quality_report(mesh)["min_dihedral_deg"] >= 10.0


def test_a_cap_whose_surface_folds_beside_its_trace_meshes_valid(monkeypatch):
    """A sphere cap 0.036 deep behind the plane x = 0 (from the sweep's numpy_spheres_s2 as a plain box) at a
    uniform h = 0.05: the default sampling leaves a node tenting over a chord of the trace, its triangle
    folded against the level set; the pocket under it holds no Delaunay tetrahedron and the volume
    recovery diverged. The chord is flipped after the cut (`flip_plane_chords`); without that flip the
    tenting node is removed (`remove_fold_nodes`); without both the fold stays (a folded inclusion is
    then sampled again, tests/test_faces.py)."""
    import jaxmesh._surface as surface

    n = 48
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    ms = Microstructure.from_levelset(np.linalg.norm(x - np.array([-0.0545, 0.1091, 0.4298]), axis=-1) - 0.0909,
                                      periodic=False)

    def cap_surface():
        return surface.mesh_inclusion(ms.inclusions[0], surface.as_size_fn(0.05, ms.box, False), ms.box,
                                      surface.SurfaceConfig(), periodic=False)

    assert cap_surface()["folds"] == 0
    with monkeypatch.context() as patch:
        patch.setattr(surface, "flip_plane_chords", lambda points, tris, on_plane, phi_fn: tris)
        assert cap_surface()["folds"] == 0  # removing the tenting node clears it as well
        patch.setattr(surface, "remove_fold_nodes", lambda points, tris, on_plane, *_: (points, tris, on_plane))
        assert cap_surface()["folds"] == 1
    mesh = mesh_rve(ms, MeshConfig(h=0.05, periodic=False))
    _check_plain_box(mesh, ms)


def test_labels_the_box_splits_mesh_one_inclusion_per_part():
    """A periodic label image read as a plain box: the box cuts label 1 into two parts (x near 0 and
    x near 1) and label 2 into four (an edge); each part is meshed as its own inclusion."""
    n = 32
    x = (np.arange(n) + 0.5) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    lab = np.zeros((n, n, n), np.int64)
    for k, (c, r) in enumerate([((0.0, 0.5, 0.5), 0.2), ((0.0, 0.0, 0.5), 0.22), ((0.55, 0.55, 0.25), 0.15)], 1):
        d = X - np.asarray(c)
        lab[np.linalg.norm(d - np.round(d), axis=-1) < r] = k  # periodic images
    assert len(Microstructure.from_labels(lab).inclusions) == 3  # periodic: each label one region
    ms = Microstructure.from_labels(lab, periodic=False)
    assert [(i.description["label"], i.description.get("part")) for i in ms.inclusions] == [
        (1, 1), (1, 2), (2, 1), (2, 2), (2, 3), (2, 4), (3, 1)]
    mesh = mesh_rve(ms, MeshConfig(iis=0.1, periodic=False))
    _check_plain_box(mesh, ms)
    assert quality_report(mesh)["n_inclusions"] == 7


def test_a_part_the_box_cuts_too_thin_is_refused_as_touching_the_box():
    """A fibre along y on the plane x = 0, 2.4 grid steps thick: periodic, it is whole and loads; on a
    plain box its part beside x = 1 is under a step thick, and the error says that this part touches the
    box and that meshing periodic keeps it whole. A speck inside the box gets no such note."""
    n = 24
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    dx = X[..., 0] - np.round(X[..., 0])
    fibre = np.sqrt(dx**2 + (X[..., 2] - 0.5) ** 2) - 1.2 / n
    phi = np.minimum(fibre, np.linalg.norm(X - 0.5, axis=-1) - 0.2)
    assert len(Microstructure.from_levelset(phi, periodic=True).inclusions) == 2
    with pytest.raises(ValueError, match=r"steps thick.* Here inclusion 3 touches the box: .*mesh it periodic") as err:
        Microstructure.from_levelset(phi, periodic=False)
    assert "inclusion 1:" not in str(err.value) and "inclusion 2:" not in str(err.value)
    speck = np.linalg.norm(X - 0.5, axis=-1) - 0.2
    speck[3, 3, 3] = -0.01
    with pytest.raises(ValueError, match="negative samples") as err:
        Microstructure.from_levelset(speck, periodic=False)
    assert "touches the box" not in str(err.value)


def test_cli_close_box_layers_meets_the_plane_at_an_angle(tmp_path, capsys):
    """A matrix layer 0.02 steps thick under a flat bottom: as given the mesh is valid but holds a wedge
    of tets between the interface and the plane (q below 0.1); with --close-box-layers the bottom
    reaches the plane, the interface meets it at an angle, and validate reads the input closed as the
    mesh file says."""
    path = tmp_path / "layer.npy"
    np.save(path, flat_bottom_ellipsoid(24, 0.02))
    out, report = tmp_path / "closed.vtu", tmp_path / "r.json"
    assert main(["mesh", str(path), "-o", str(out), "--no-periodic", "--close-box-layers", "--report", str(report)]) == 0
    assert "layers along the box planes thinner than a sixth of a step closed" in capsys.readouterr().out
    data = json.loads(report.read_text())
    assert data["metadata"]["validation"]["ok"] is True and data["metadata"]["parameters"]["close_box_layers"]
    assert data["quality"]["min_dihedral_deg"] > 10.0 and data["quality"]["q_min"] > 0.3
    assert main(["validate", str(out), "--geometry", str(path), "--no-periodic"]) == 0
    assert "--close-box-layers" in capsys.readouterr().out  # taken from the file
    assert main(["mesh", str(path), "-o", str(tmp_path / "p.vtu"), "--close-box-layers"]) == 2  # periodic
    assert "periodic=False" in capsys.readouterr().err


def test_a_failure_at_a_box_plane_is_retried_with_the_layers_closed():
    from jaxmesh._errors import MeshingError
    from jaxmesh._pipeline import _retry_config

    phi = flat_bottom_ellipsoid(16, 0.02)
    plain = Microstructure.from_levelset(phi, periodic=False)
    at_plane = MeshingError("volume", "recovery stopped", 1, at_box_plane=True)
    config, key, how = _retry_config(plain, MeshConfig(periodic=False), None, at_plane)
    assert config.close_box_layers is True and key == "close_box_layers" and "--close-box-layers" in how
    assert _retry_config(plain, MeshConfig(periodic=False, close_box_layers=False), None, at_plane) is None
    assert _retry_config(plain, MeshConfig(periodic=False), None, MeshingError("volume", "elsewhere", 1)) is None
    analytic = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.2)], BOX, (16, 16, 16),
                                             periodic=False)
    assert _retry_config(analytic, MeshConfig(periodic=False), None, at_plane) is None
    with pytest.raises(ValueError, match="close_box_layers needs periodic=False"):
        MeshConfig(close_box_layers=True)
