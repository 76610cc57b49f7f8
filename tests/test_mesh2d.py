"""The periodic 2D mesher: contour cutting units, then whole meshes checked by the validator,
quality, inclusion areas against analytic values, periodicity, labels, files, bad inputs."""

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

from jaxmesh._contours import assemble_pslg, cut_loop, edge_parameters, resample_polyline
from jaxmesh._mesh2d import Mesh2DConfig, mesh_2d, mesh_file_2d
from jaxmesh._quality import cell_quality, min_angles, signed_volumes
from jaxmesh._validate import validate
from jaxmesh.geometry._microstructure import Microstructure
from jaxmesh.geometry._shapes import ellipsoid_sdf, ellipsoid_volume, sphere_sdf

BOX = (1.0, 1.0)


# ----------------------------------------------------------------------------- contour units
def _circle_loop(center, radius, n=400):
    t = 2 * np.pi * (np.arange(n) + 0.5) / n
    return np.asarray(center) + radius * np.stack([np.cos(t), np.sin(t)], 1)


def _circle_line_refine(center, radius):
    """Exact crossing of the circle with the line x_axis = const nearest to the guess."""

    def refine(points, axis):
        out = points.copy()
        for k, (p, a) in enumerate(zip(points, axis)):
            b = 1 - a
            half = np.sqrt(radius**2 - (p[a] - center[a]) ** 2)
            roots = center[b] + np.array([-half, half])
            out[k, b] = roots[np.argmin(np.abs(roots - p[b]))]
        return out

    return refine


def test_cut_loop_circle_at_corner():
    c, r = np.array([0.0, 0.0]), 0.3
    arcs, crossings = cut_loop(_circle_loop(c, r), BOX, _circle_line_refine(c, r), 1)
    assert len(arcs) == 4 and len(crossings) == 4
    # one crossing per line image, at the analytic coordinates, on both master lines
    assert sorted((x.axis, round(x.t, 12)) for x in crossings) == [(0, 0.3), (0, 0.7), (1, 0.3), (1, 0.7)]
    for arc in arcs:
        assert not arc.closed
        pts = arc.points
        assert np.all((pts >= 0) & (pts <= 1))
        # the four corner pieces: every interior point is at distance r from its own corner image
        corner = np.round(pts[len(pts) // 2])
        assert np.allclose(np.linalg.norm(pts[1:-1] - corner, axis=1), r, atol=1e-4)
        for end, p in ((arc.start, pts[0]), (arc.end, pts[-1])):
            x = crossings[end[0]]
            assert p[x.axis] == end[1] * BOX[x.axis] and p[1 - x.axis] == x.t


def test_cut_loop_inside_and_edge():
    c, r = np.array([0.5, 0.5]), 0.2
    arcs, crossings = cut_loop(_circle_loop(c, r), BOX, _circle_line_refine(c, r), 1)
    assert len(arcs) == 1 and arcs[0].closed and not crossings
    # a circle across x = 1 (unwrapped centre beyond the box): 2 arcs, 2 crossings on x = 0 / x = 1
    c = np.array([1.1, 0.5])
    arcs, crossings = cut_loop(_circle_loop(c, r), BOX, _circle_line_refine(c, r), 1)
    assert len(arcs) == 2 and {x.axis for x in crossings} == {0}
    assert sorted(round(x.t, 12) for x in crossings) == pytest.approx([0.5 - np.sqrt(0.03), 0.5 + np.sqrt(0.03)])
    sides = sorted((a.start[1], a.end[1]) for a in arcs)
    assert sides == [(0, 0), (1, 1)]  # the small cap ends on x = 0, the big part on x = 1


def test_resample_and_edge_parameters():
    loop = _circle_loop((0.5, 0.5), 0.25, 2000)
    nodes = resample_polyline(loop, True, lambda p: np.full(len(p), 0.05), 6)
    d = np.linalg.norm(np.diff(np.vstack([nodes, nodes[:1]]), axis=0), axis=1)
    assert len(nodes) == round(2 * np.pi * 0.25 / 0.05) and np.ptp(d) < 1e-3 * d.mean()
    # graded h: spacing follows h (h-weighted arclength is equidistributed)
    line = np.stack([np.linspace(0, 1, 1001), np.zeros(1001)], 1)
    graded = resample_polyline(line, False, lambda p: 0.02 + 0.08 * p[:, 0], 1)
    s = np.diff(graded[:, 0])
    mid = 0.5 * (graded[1:, 0] + graded[:-1, 0])
    assert np.allclose(s / (0.02 + 0.08 * mid), s[0] / (0.02 + 0.08 * mid[0]), rtol=0.05)
    assert graded[0, 0] == 0.0 and graded[-1, 0] == 1.0
    t = edge_parameters(np.array([0.0, 0.33, 1.0]), lambda t: np.stack([np.zeros_like(t), t], 1),
                        lambda p: np.full(len(p), 0.1))
    assert 0.33 in t and t[0] == 0.0 and t[-1] == 1.0
    assert np.all(np.diff(t) > 0.07) and np.all(np.diff(t) < 0.13)


def test_assemble_pslg_box_is_periodic():
    pslg = assemble_pslg([], [], (2.0, 1.0), lambda p: np.full(len(p), 0.1))
    for a, pairs in pslg.periodic_pairs.items():
        shift = np.zeros(2)
        shift[a] = (2.0, 1.0)[a]
        assert np.array_equal(pslg.points[pairs[:, 1]], pslg.points[pairs[:, 0]] + shift)
        assert np.all(pslg.points[pairs[:, 0], a] == 0.0)
    assert len(pslg.periodic_pairs[0]) == 11 and len(pslg.periodic_pairs[1]) == 21


# ----------------------------------------------------------------------------- whole meshes
def _crossing_angles(mesh):
    """Angle (degrees) between the interface and the box line at every interface/box crossing node,
    from the interface edge leaving the node (a chord: within ~h * curvature of the tangent)."""
    c = mesh.cells
    e = np.concatenate([c[:, [0, 1]], c[:, [1, 2]], c[:, [2, 0]]])
    lab = np.tile(mesh.inclusion_id, 3)
    key = np.minimum(e[:, 0], e[:, 1]) * mesh.n_points + np.maximum(e[:, 0], e[:, 1])
    order = np.argsort(key, kind="stable")
    k, le = key[order], lab[order]
    pair = np.nonzero((k[1:] == k[:-1]) & (le[1:] != le[:-1]))[0]
    iface = e[order][pair]  # interface edges (between two labels)
    box = np.asarray(mesh.box)
    nodes, angles = [], []
    for a, b in iface:
        for u, v in ((a, b), (b, a)):
            p = mesh.points[u]
            axis = np.nonzero((p == 0.0) | (p == box))[0]
            if axis.size:
                t = mesh.points[v] - p
                angles.append(np.degrees(np.arcsin(min(1.0, abs(t[axis[0]]) / np.linalg.norm(t)))))
                nodes.append(u)
    return np.asarray(nodes, dtype=np.int64), np.asarray(angles)


def _check_mesh(mesh, ms, h, *, min_angle=20.0, mean_q=0.9, area_rtol=None):
    report = validate(mesh, ms)
    assert report.ok, report.summary()
    q = cell_quality(mesh.points, mesh.cells)
    ang = min_angles(mesh.points, mesh.cells)
    assert q.mean() >= mean_q
    # the interface meets a box line at angle theta: a triangle there cannot beat theta
    nodes, theta = _crossing_angles(mesh)
    sharp = nodes[theta < 2 * min_angle]
    near = np.zeros(mesh.n_cells, dtype=bool)
    if sharp.size:
        cent = mesh.points[mesh.cells].mean(axis=1)
        d = np.min(np.linalg.norm(cent[:, None] - mesh.points[sharp][None], axis=2), axis=1)
        near = d < 3 * h
        assert ang.min() >= 0.5 * theta.min()
    assert ang[~near].min() >= min_angle
    # interface vertices on their zero level set, periodic partners exact translates
    for a, pairs in mesh.periodic_pairs.items():
        shift = np.eye(2)[a] * mesh.box[a]
        assert np.array_equal(mesh.points[pairs[:, 1]], mesh.points[pairs[:, 0]] + shift)
    if area_rtol is not None:
        area = signed_volumes(mesh.points, mesh.cells)
        for inc in ms.inclusions:
            assert abs(area[mesh.inclusion_id == inc.id].sum() / inc.volume - 1) < area_rtol
    return report


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("base", [(0.5, 0.5), (0.05, 0.5), (0.97, 0.03)], ids=["centre", "edge", "corner"])
def test_single_circle(base, seed):
    r = 0.2
    # each seed moves the circle a little (other crossings) and changes the mesher's jitter
    center = tuple(np.asarray(base) + np.random.default_rng(seed).uniform(-0.01, 0.01, 2))
    ms = Microstructure.from_functions([sphere_sdf(jnp.asarray(center), r)], BOX, (64, 64), volumes=[np.pi * r * r])
    mesh = mesh_2d(ms, h=r / 8, seed=seed)
    _check_mesh(mesh, ms, r / 8, area_rtol=0.01)
    # interface vertices exactly on the circle
    ids = mesh.inclusion_id
    lo = np.full(mesh.n_points, 9)
    hi = np.zeros(mesh.n_points, dtype=np.int64)
    for k in range(3):
        np.minimum.at(lo, mesh.cells[:, k], ids)
        np.maximum.at(hi, mesh.cells[:, k], ids)
    iface = mesh.points[lo != hi]
    d = iface - np.asarray(center)
    d -= np.round(d)
    assert len(iface) >= 2 * np.pi * r / (r / 8) - 2
    assert np.abs(np.linalg.norm(d, axis=1) - r).max() < 1e-10
    assert mesh.metadata["relaxation"]["stop_reason"] in ("converged", "max_retriangulations", "max_iterations")
    assert set(mesh.metadata["timings"]) >= {"interfaces_and_box", "interior_nodes", "triangulation", "relaxation"}


def _ellipses(seed, grid=128, n=30, fraction=0.4):
    from jaxmesh._generate import random_inclusions

    specs = random_inclusions(BOX, n=n, volume_fraction=fraction, shape="ellipsoid", radius=(0.08, 0.02),
                              min_gap=2.0 / grid, seed=seed)
    fns = [ellipsoid_sdf(jnp.asarray(s.center), jnp.asarray(s.axes), jnp.asarray(s.rotation)) for s in specs]
    return Microstructure.from_functions(fns, BOX, (grid, grid), volumes=[float(ellipsoid_volume(s.axes)) for s in specs])


def test_random_ellipses_coarse():
    ms = _ellipses(0, grid=64)
    assert ms.volume_fraction() == pytest.approx(0.4, abs=0.01)
    mesh = mesh_2d(ms, h=0.015)
    _check_mesh(mesh, ms, 0.015, area_rtol=0.03)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_ellipses_seeds(seed):
    ms = _ellipses(seed)
    mesh = mesh_2d(ms, h=0.01)
    _check_mesh(mesh, ms, 0.01, area_rtol=0.02)


def test_levelset_and_label_inputs():
    n = 48
    x = np.arange(n) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    d = np.stack([X - 0.02, Y - 0.5], -1)
    d -= np.round(d)
    phi = np.linalg.norm(d, axis=-1) - 0.25
    for ms in (Microstructure.from_levelset(phi), Microstructure.from_labels((phi < 0).astype(np.int64))):
        mesh = mesh_2d(ms, h=0.03, config=Mesh2DConfig(relax=False))
        assert validate(mesh, ms).ok
        assert set(np.unique(mesh.inclusion_id)) == {0, 1}


def test_seed_reproducible_and_no_relax():
    ms = Microstructure.from_functions([sphere_sdf(jnp.array([0.3, 0.6]), 0.2)], BOX, (48, 48))
    cfg = Mesh2DConfig(relax=False)
    a, b = mesh_2d(ms, h=0.05, config=cfg, seed=1), mesh_2d(ms, h=0.05, config=cfg, seed=1)
    c = mesh_2d(ms, h=0.05, config=cfg, seed=2)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.cells, b.cells)
    assert not np.array_equal(a.points, c.points)
    assert validate(c, ms).ok


def test_mesh_file_2d(tmp_path):
    n = 48
    x = np.arange(n) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    phi = np.hypot(X - 0.5, Y - 0.5) - 0.3
    src = tmp_path / "rve.npy"
    np.save(src, phi)
    out, png = tmp_path / "rve.vtu", tmp_path / "rve.png"
    mesh = mesh_file_2d(src, out, h=0.05, plot=png)
    assert out.exists() and png.exists() and png.stat().st_size > 0
    back = meshio.read(out)
    assert len(back.points) == mesh.n_points
    assert mesh.metadata["validation"]["checks"]["periodic"]["passed"]


def test_bad_inputs():
    ms = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5]), 0.2)], BOX, (32, 32))
    with pytest.raises(ValueError, match="expected a size h"):
        mesh_2d(ms, h=-0.1)
    with pytest.raises(ValueError, match="expected a size h"):
        mesh_2d(ms, h=0.5)
    with pytest.raises(ValueError, match="expected h None, a float or a SizeField"):
        mesh_2d(ms, h="fine")
    with pytest.raises(ValueError, match="expected either h or size-function"):
        mesh_2d(ms, h=0.05, iis=0.05)
    with pytest.raises(ValueError, match="Mesh2DConfig.removal_fraction"):
        Mesh2DConfig(removal_fraction=2.0)
    with pytest.raises(ValueError, match="expected config a Mesh2DConfig"):
        mesh_2d(ms, h=0.05, config={"relax": False})
    with pytest.raises(ValueError, match="2D"):
        mesh_2d("not a microstructure", h=0.05)
    flat = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5]), 0.2)], BOX, (32, 32), periodic=False)
    with pytest.raises(ValueError, match="expected a periodic microstructure"):
        mesh_2d(flat, h=0.05)
    ms3 = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.3)], (1.0, 1.0, 1.0), (16, 16, 16))
    with pytest.raises(ValueError, match="expected a 2D microstructure"):
        mesh_2d(ms3, h=0.05)


@pytest.mark.parametrize("interior", ["hex", "quadtree"])
def test_size_function_graded(interior):
    if interior == "quadtree":
        pytest.importorskip("jaxmesh._octree")
    from jaxmesh._sizing import SizeParams, size_function

    circles = [((0.3, 0.3), 0.15), ((0.62, 0.35), 0.15), ((0.1, 0.85), 0.12), ((0.7, 0.8), 0.06)]
    ms = Microstructure.from_functions([sphere_sdf(jnp.asarray(c), r) for c, r in circles], BOX, (48, 48),
                                       volumes=[np.pi * r * r for _, r in circles])
    field = size_function(ms, SizeParams(iis=0.04, nb_el=2, curv_alpha=0.3))  # ~21 chords on r = 0.06
    mesh = mesh_2d(ms, field, config=Mesh2DConfig(interior=interior))
    _check_mesh(mesh, ms, float(np.min(field.values)), area_rtol=0.03)
    # the mesh follows the field: edges in the narrow gap are much shorter than far from inclusions
    e = np.concatenate([mesh.cells[:, [0, 1]], mesh.cells[:, [1, 2]], mesh.cells[:, [2, 0]]])
    mid = mesh.points[e].mean(axis=1)
    length = np.linalg.norm(np.diff(mesh.points[e], axis=1)[:, 0], axis=1)
    h_mid = np.asarray(field(jnp.asarray(mid)))
    assert np.median(length / h_mid) == pytest.approx(1.0, abs=0.2)
    # the same through the size-function keywords (h=None)
    assert mesh_2d(ms, iis=0.04, nb_el=2, curv_alpha=0.3, config=Mesh2DConfig(interior=interior)).metadata["h"] == "field"
