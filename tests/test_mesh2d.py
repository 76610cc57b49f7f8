"""The 2D mesher: contour cutting units, then whole meshes checked by the validator, quality,
inclusion areas against analytic values, periodicity, labels, files, bad inputs; then the same for
non-periodic boxes (inclusions clipped by the box, never wrapped)."""

from dataclasses import replace

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

from jaxmesh._contours import (
    BOX_EDGE,
    BOX_SEGMENT,
    FIXED,
    assemble_box_pslg,
    assemble_pslg,
    box_window_axes,
    clip_loop,
    cut_loop,
    edge_parameters,
    extract_box_loops,
    rebuild_box_segments,
    resample_polyline,
    split_segments,
)
from jaxmesh._errors import MeshingError
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


@pytest.mark.parametrize("seed", [0, 1])
def test_refinement_splits_a_segment_its_apex_encroaches(seed):
    # four discs from a level-set grid, default size function: the truss left an interior node just
    # inside a disc's chord, a flat triangle whose circumcentre lies across the segment; inserting it
    # there changed nothing, and every round added the same node again (unused duplicates)
    n = 96
    x = np.arange(n) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    discs = [((0.2, 0.3), 0.12), ((0.7, 0.75), 0.15), ((0.55, 0.2), 0.1), ((0.05, 0.9), 0.08)]
    phi = np.min([np.hypot((X - cx + 0.5) % 1 - 0.5, (Y - cy + 0.5) % 1 - 0.5) - r for (cx, cy), r in discs], axis=0)
    ms = Microstructure.from_levelset(phi)
    mesh = mesh_2d(ms, seed=seed)
    assert len(np.unique(mesh.cells)) == mesh.n_points
    _check_mesh(mesh, ms, 0.04)
    assert mesh.metadata["counts"]["refinement"]["left"] == 0


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
    ms3 = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.3)], (1.0, 1.0, 1.0), (16, 16, 16))
    with pytest.raises(ValueError, match="expected a 2D microstructure"):
        mesh_2d(ms3, h=0.05)


def _periodic_distance(u):
    return np.minimum(u % 1.0, 1.0 - u % 1.0)


@pytest.mark.parametrize("case", ["wavy band", "diagonal band", "band and circle", "matrix negative"])
def test_percolating_inclusions_mesh_periodic_and_conforming(case):
    """Inclusions that reach their own periodic image (a band, a channel, a field negative in the
    matrix) are closed off beyond the box, cut by it, and their crossings of opposite edges paired."""
    n = 64
    x, y = np.meshgrid(np.arange(n) / n, np.arange(n) / n, indexing="ij")
    phi, area = {
        "wavy band": (_periodic_distance(y - 0.5 - 0.05 * np.sin(2 * np.pi * x)) - 0.15, 0.3),
        "diagonal band": (_periodic_distance(y - x) / np.sqrt(2) - 0.1, 0.2 * np.sqrt(2)),
        "band and circle": (np.minimum(np.abs(y - 0.4) - 0.12,
                                       np.hypot(_periodic_distance(x), _periodic_distance(y - 0.8)) - 0.1), None),
        "matrix negative": (0.3 - np.hypot(x - 0.5, y - 0.5), 1 - np.pi * 0.09),
    }[case]
    ms = Microstructure.from_levelset(phi)
    mesh = mesh_2d(ms, h=0.04)
    _check_mesh(mesh, ms, 0.04, min_angle=20.0, mean_q=0.85)
    spans = [np.ptp(np.asarray([inc.lower, inc.upper]), axis=0) for inc in ms.inclusions]
    assert max(s.max() for s in spans) > 0.999  # it does percolate
    if area is not None:
        inside = signed_volumes(mesh.points, mesh.cells)[mesh.inclusion_id > 0].sum()
        assert inside == pytest.approx(area, rel=0.01)


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


# ----------------------------------------------------------------------------- non-periodic box
def _box_loops(center, radius, step=0.01):
    """Zero contours of a circle on its window clipped to the unit box (as mesh_2d samples it)."""
    c = np.asarray(center)
    axes = box_window_axes(c - radius, c + radius, step, 3 * step, BOX)
    xy = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    return axes, extract_box_loops(np.linalg.norm(xy - c, axis=-1) - radius, axes, BOX, 1)


def test_clip_loop_corner_side_and_inside():
    c, r = np.array([0.97, 0.03]), 0.2
    axes, loops = _box_loops(c, r)
    assert axes[0][-1] == 1.0 and axes[1][0] == 0.0 and axes[0][0] > 0 and axes[1][-1] < 1
    arcs, crossings = [], []
    for loop in loops:
        a, x = clip_loop(loop, BOX, _circle_line_refine(c, r), 1)
        arcs += a
        crossings += x
    # one arc from x = 1 to y = 0 at the analytic crossings; the part outside the box is gone
    half = np.sqrt(r**2 - 0.03**2)
    assert len(arcs) == 1 and len(crossings) == 2
    assert sorted((x.axis, round(x.t, 12)) for x in crossings) == [(0, round(0.03 + half, 12)),
                                                                  (1, round(0.97 - half, 12))]
    arc = arcs[0]
    assert {arc.start[1], arc.end[1]} == {0, 1}
    assert np.all((arc.points >= 0) & (arc.points <= 1))
    assert np.allclose(np.linalg.norm(arc.points[1:-1] - c, axis=1), r, atol=1e-3)
    for end, p in ((arc.start, arc.points[0]), (arc.end, arc.points[-1])):
        x = crossings[end[0]]
        assert p[x.axis] == end[1] * BOX[x.axis] and p[1 - x.axis] == x.t
    # a circle cut by one side: one arc ending twice on that side; a circle inside: one loop
    arcs, crossings = clip_loop(_box_loops((0.5, 0.05), r)[1][0], BOX, _circle_line_refine((0.5, 0.05), r), 1)
    assert len(arcs) == 1 and [(x.axis, arcs[0].start[1]) for x in crossings] == [(1, 0), (1, 0)]
    assert arcs[0].end[1] == 0 and arcs[0].points[:, 1].max() < 0.26
    arcs, crossings = clip_loop(_box_loops((0.5, 0.5), r)[1][0], BOX, _circle_line_refine((0.5, 0.5), r), 1)
    assert len(arcs) == 1 and arcs[0].closed and not crossings


def test_assemble_box_pslg_sides_are_independent():
    c, r = np.array([0.97, 0.03]), 0.2
    arcs, crossings = clip_loop(_box_loops(c, r)[1][0], BOX, _circle_line_refine(c, r), 1)
    arcs = [replace(a, points=resample_polyline(a.points, False, lambda p: np.full(len(p), 0.05))) for a in arcs]
    pslg = assemble_box_pslg(arcs, crossings, BOX, lambda p: np.full(len(p), 0.1))
    assert not pslg.periodic and pslg.periodic_pairs == {} and np.all(pslg.segment_partner == -1)
    pts, box_seg = pslg.points, pslg.segments[pslg.segment_inclusion == BOX_SEGMENT]
    # each crossing is a node of its own side only: (1, 0.03 + half) but not (0, 0.03 + half)
    fixed = pts[(pslg.node_kind == FIXED) & (pslg.node_axis >= 0)]
    half = np.sqrt(r**2 - 0.03**2)
    assert sorted(map(tuple, np.round(fixed, 12))) == [(round(0.97 - half, 12), 0.0), (1.0, round(0.03 + half, 12))]
    # the box boundary: every box segment on one side, the four sides of total length 4
    on = np.all((pts[box_seg] == 0.0) | (pts[box_seg] == 1.0), axis=1)
    assert np.all(on.any(axis=1))
    assert np.linalg.norm(np.diff(pts[box_seg], axis=1)[:, 0], axis=1).sum() == pytest.approx(4.0, abs=1e-12)
    # the sides are meshed on their own: x = 0 has no crossing, x = 1 one, so the node counts differ
    n_left = np.sum(pts[pslg.node_kind == BOX_EDGE, 0] == 0.0)
    n_right = np.sum(pts[(pslg.node_kind == BOX_EDGE) | (pslg.node_kind == FIXED), 0] == 1.0)
    assert n_left == 9 and n_right >= 10
    # a split of a box segment is not mirrored, and rebuilding from the node order gives the same boundary
    right = np.nonzero((pslg.segment_inclusion == BOX_SEGMENT) & np.all(pts[pslg.segments, 0] == 1.0, axis=1))[0][0]
    split = split_segments(pslg, np.array([right]), lambda p, i: p)
    new = split.points[pslg.n_points:]
    assert len(new) == 1 and new[0, 0] == 1.0 and split.periodic_pairs == {}
    rebuilt = rebuild_box_segments(split)
    assert _box_segment_set(rebuilt) == _box_segment_set(split) and np.all(rebuilt.segment_partner == -1)


def _box_segment_set(pslg):
    return set(map(tuple, np.sort(pslg.segments[pslg.segment_inclusion == BOX_SEGMENT], axis=1).tolist()))


def _clipped_disk_area(center, radius, box=BOX):
    """Area of a disk inside the box [0, Lx] x [0, Ly] (quadrature of its chords along x)."""
    from scipy.integrate import quad

    cx, cy = center

    def chord(x):
        s = np.sqrt(max(radius**2 - (x - cx) ** 2, 0.0))
        return max(0.0, min(box[1], cy + s) - max(0.0, cy - s))

    lo, hi = max(0.0, cx - radius), min(box[0], cx + radius)
    kinks = [x for x in (cx - radius, cx + radius, cx) if lo < x < hi]
    kinks += [cx + sgn * np.sqrt(radius**2 - (cy - y) ** 2) for y in (0.0, box[1]) for sgn in (-1, 1)
              if abs(cy - y) < radius and lo < cx + sgn * np.sqrt(radius**2 - (cy - y) ** 2) < hi]
    return quad(chord, lo, hi, points=sorted(kinks) or None, epsabs=1e-13, limit=200)[0]


def _interface_nodes(mesh):
    ids = mesh.inclusion_id
    lo = np.full(mesh.n_points, 10**6)
    hi = np.zeros(mesh.n_points, dtype=np.int64)
    for k in range(3):
        np.minimum.at(lo, mesh.cells[:, k], ids)
        np.maximum.at(hi, mesh.cells[:, k], ids)
    return lo != hi


def _check_flat(mesh, ms, h, circles, area_rtol, **kw):
    """Non-periodic mesh: valid, quality as the periodic one, each inclusion within its own
    circle (no wrapped copy anywhere) and of the area of that circle clipped by the box."""
    assert mesh.periodic is False and not mesh.periodic_pairs
    _check_mesh(mesh, ms, h, **kw)
    area = signed_volumes(mesh.points, mesh.cells)
    cent = mesh.points[mesh.cells].mean(axis=1)
    for k in range(1, int(mesh.inclusion_id.max()) + 1):
        mine = mesh.inclusion_id == k
        # plain (not minimum-image) distances: a part wrapped to the opposite side is far from every circle
        d = np.array([np.linalg.norm(cent[mine] - c, axis=1).max() - r for c, r in circles])
        j = int(np.argmin(d))
        assert d[j] < 0
        assert area[mine].sum() == pytest.approx(_clipped_disk_area(*circles[j]), rel=area_rtol)
    assert area[mesh.inclusion_id > 0].sum() == pytest.approx(sum(_clipped_disk_area(*c) for c in circles),
                                                              rel=area_rtol)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("base", [(0.5, 0.05), (0.97, 0.03)], ids=["side", "corner"])
def test_flat_circle_clipped_by_box(base, seed):
    r = 0.2
    center = tuple(np.asarray(base) + np.random.default_rng(seed).uniform(-0.01, 0.01, 2))
    ms = Microstructure.from_functions([sphere_sdf(jnp.asarray(center), r)], BOX, (64, 64), periodic=False)
    mesh = mesh_2d(ms, h=r / 8, seed=seed)
    _check_flat(mesh, ms, r / 8, [(center, r)], area_rtol=0.01)
    # interface nodes exactly on the circle (no periodic image) and none near the opposite sides
    iface = mesh.points[_interface_nodes(mesh)]
    assert np.abs(np.linalg.norm(iface - np.asarray(center), axis=1) - r).max() < 1e-10
    assert iface[:, 1].max() < center[1] + r + 1e-12
    if base[0] > 0.5:
        assert iface[:, 0].min() > center[0] - r - 1e-12
    # the cut part is missing: well below the full disk's area
    area = signed_volumes(mesh.points, mesh.cells)[mesh.inclusion_id == 1].sum()
    assert area < 0.95 * np.pi * r * r
    assert mesh.metadata["relaxation"]["stop_reason"] in ("converged", "max_retriangulations", "max_iterations")


_FLAT_CIRCLES = [((0.98, 0.5), 0.2), ((0.4, 0.3), 0.15), ((0.3, 0.97), 0.12), ((0.02, 0.05), 0.15),
                 ((0.6, 0.75), 0.1)]  # cut by x = 1, inside, cut by y = 1, cut by the corner (0, 0), inside


def _flat_field(n=64):
    x = np.arange(n) / n  # node-centred: the last sample at (n - 1) / n, the field clamped beyond
    X, Y = np.meshgrid(x, x, indexing="ij")
    return np.min([np.hypot(X - c[0], Y - c[1]) - r for c, r in _FLAT_CIRCLES], axis=0)


@pytest.mark.parametrize("seed", [0, 1])
def test_flat_levelset_grid(seed):
    ms = Microstructure.from_levelset(_flat_field(), periodic=False)
    assert len(ms.inclusions) == 5
    mesh = mesh_2d(ms, h=0.025, seed=seed)
    _check_flat(mesh, ms, 0.025, _FLAT_CIRCLES, area_rtol=0.02)
    assert mesh.metadata["counts"]["n_crossings"] == 6


def test_flat_labels():
    ms = Microstructure.from_labels(_flat_field() < 0, periodic=False)
    mesh = mesh_2d(ms, h=0.025)
    # the level set of a voxel image is the distance to the voxels: areas within a few percent
    _check_flat(mesh, ms, 0.025, _FLAT_CIRCLES, area_rtol=0.05)
    assert set(np.unique(mesh.inclusion_id)) == set(range(6))


def test_flat_labels_the_box_splits():
    """A periodic label image read as a plain box: label 1 (cut by x = 0) in two parts, label 2 (on a
    corner) in four; each part is meshed as its own inclusion."""
    n = 96
    x = (np.arange(n) + 0.5) / n
    X = np.stack(np.meshgrid(x, x, indexing="ij"), -1)
    lab = np.zeros((n, n), np.int64)
    for k, (c, r) in enumerate([((0.0, 0.5), 0.2), ((0.0, 0.0), 0.22), ((0.55, 0.55), 0.15)], 1):
        d = X - np.asarray(c)
        lab[np.linalg.norm(d - np.round(d), axis=-1) < r] = k  # with its periodic images
    ms = Microstructure.from_labels(lab, periodic=False)
    assert [i.description["label"] for i in ms.inclusions] == [1, 1, 2, 2, 2, 2, 3]
    mesh = mesh_2d(ms, h=0.025)
    report = validate(mesh, ms)
    assert report.ok, report.summary()
    assert not mesh.periodic and set(np.unique(mesh.inclusion_id)) == set(range(8))


@pytest.mark.parametrize("interior", ["hex", "quadtree"])
def test_flat_size_function(interior):
    from jaxmesh._sizing import SizeParams, size_function

    ms = Microstructure.from_levelset(_flat_field(), periodic=False)
    mesh = mesh_2d(ms, iis=0.04, nb_el=2, curv_alpha=0.3, config=Mesh2DConfig(interior=interior))
    assert mesh.metadata["h"] == "field"
    field = size_function(ms, SizeParams(iis=0.04, nb_el=2, curv_alpha=0.3))
    _check_flat(mesh, ms, float(np.min(field.values)), _FLAT_CIRCLES, area_rtol=0.03)


def test_mesh_file_2d_flat(tmp_path):
    src, out = tmp_path / "box.npy", tmp_path / "box.vtu"
    np.save(src, _flat_field(48))
    mesh = mesh_file_2d(src, out, h=0.05, periodic=False)
    assert out.exists() and mesh.periodic is False
    assert mesh.metadata["validation"]["checks"]["periodic"]["skipped"]
