"""Inclusion surfaces: refinement / flips / cuts keep a closed oriented surface; one sphere meshed at
h = r/6 (volume, level set, quality); two spheres one grid step apart stay two and do not intersect."""

import warnings
from collections import Counter

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from jaxmesh._errors import MeshingError
from jaxmesh._intersect import intersecting_pairs
from jaxmesh._quality import cell_quality, min_angles
from jaxmesh._surface import (SurfaceConfig, as_size_fn, enclosed_volume, evaluate_size, extract, flip_plane_chords,
                              folded, mesh_inclusion, project, refuse_nodes_off_the_level_set, release_touching,
                              remove_fold_nodes, revert_around_defects, unfold)
from jaxmesh._surface_ops import (collapse_edges, cut_plane, flip_edges, half_edges, plane_chords, plane_flags, refine,
                                  straddling, touching_plane_nodes)
from jaxmesh.geometry._microstructure import Microstructure
from jaxmesh.geometry._shapes import sphere_sdf


def _closed(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    return set(cnt.tolist()) == {2} and len(np.unique(directed, axis=0)) == len(directed)  # oriented


@pytest.fixture(scope="module")
def sphere():
    phi = sphere_sdf(np.array([0.5, 0.5, 0.5]), 0.2)
    p, t = extract(phi, [0.3] * 3, [0.7] * 3, 0.05, (1.0, 1.0, 1.0))
    p, _, _ = project(phi, p, np.zeros(p.shape, bool))
    return phi, p, t


def test_marching_cubes_surface_closed_outward_on_level_set(sphere):
    phi, p, t = sphere
    assert _closed(t)
    assert enclosed_volume(p, t) == pytest.approx(4 / 3 * np.pi * 0.2**3, rel=0.05)
    assert np.abs(np.linalg.norm(p - 0.5, axis=1) - 0.2).max() < 1e-12


@pytest.mark.parametrize("rows", [1, 64, 65, 1500, 16384 + 300])
def test_pointwise_kernels_in_row_buckets_equal_a_direct_call(rows):
    """project and evaluate_size pad their rows to a few buckets (chunks of the largest): every row
    gets what an unpadded call gives it, and locked coordinates stay bit-identical."""
    phi = sphere_sdf(np.array([0.5, 0.5, 0.5]), 0.2)
    rng = np.random.default_rng(rows)
    points = 0.5 + 0.3 * rng.standard_normal((rows, 3))
    locked = rng.random((rows, 3)) < 0.2
    q, values, grads = project(phi, points, locked, 4)
    assert q.shape == (rows, 3) and values.shape == (rows,) and grads.shape == (rows, 3)
    assert np.array_equal(q[locked], points[locked])
    direct = np.array([project(phi, points[i:i + 1], locked[i:i + 1], 4)[0][0] for i in range(0, rows, 997)])
    np.testing.assert_allclose(q[::997], direct, rtol=0, atol=1e-14)
    size = evaluate_size(lambda x: 0.01 + jnp.sum(x * x, axis=-1), points)
    np.testing.assert_allclose(size, 0.01 + np.sum(points**2, axis=1), rtol=1e-14)


def test_refine_conforming(sphere):
    _, p, t = sphere
    edges, _ = half_edges(t, len(p))
    split = np.random.default_rng(0).random(len(edges)) < 0.3
    q, t2, parents = refine(p, t, split)
    assert _closed(t2) and len(q) == len(p) + split.sum()
    assert enclosed_volume(q, t2) == pytest.approx(enclosed_volume(p, t), rel=1e-12)  # midpoints: same solid
    q, t4, _ = refine(p, t, np.ones(len(edges), bool))
    assert len(t4) == 4 * len(t)


def test_flips_raise_quality_and_keep_surface(sphere):
    _, p, t = sphere
    t2, n = flip_edges(p, t)
    assert n > 0 and _closed(t2)
    assert cell_quality(p, t2).min() >= cell_quality(p, t).min() - 1e-12
    assert np.sort(cell_quality(p, t2))[:20].mean() > np.sort(cell_quality(p, t))[:20].mean()


def test_normals_of_flat_float32_triangles_are_zero_without_a_warning():
    """The truss relaxation hands flip_edges float32 points; a flat candidate triangle gave 0 / 0 there
    (1e-300 is 0 in float32) and a RuntimeWarning on the terminal."""
    from jaxmesh._surface_ops import _normals

    p = np.array([[[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(_normals(p), [[0, 0, 0], [0, 0, 1]])


def test_a_flip_never_lays_a_triangle_flat_on_a_box_plane():
    # nodes 0, 1, 2 on x = 0 (a trace), node 3 just beyond it: the skinny pair (0, 3, 1), (3, 0, 2)
    # gains quality by flipping to (0, 2, 1), (2, 3, 1), and (0, 2, 1) would lie flat on the plane
    p = np.array([[0, -1, 0], [0, 0, 0.3], [0, 0, -0.3], [-0.05, 1, 0], [0.6, -1, 0.5], [0.6, -1, -0.5],
                  [0.6, 1, 0.5], [0.6, 1, -0.5], [1, 0, 0]], float)
    t = ConvexHull(p).simplices
    inward = np.einsum("ij,ij->i", np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), p[t[:, 0]] - p.mean(0)) < 0
    t[inward] = t[inward][:, [0, 2, 1]]
    on_plane = np.zeros((len(p), 3), bool)
    on_plane[:3, 0] = True

    def flat(tris):
        return int(np.all(p[tris][:, :, 0] == 0.0, axis=1).sum())

    assert flat(t) == 0 and flat(flip_edges(p, t)[0]) == 1  # the unguarded flip does it
    guarded, _ = flip_edges(p, t, on_plane=on_plane)
    assert flat(guarded) == 0 and _closed(guarded)


def _boundary_edges(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    return {tuple(x) for x in uniq[cnt == 1].tolist()}


def test_a_chord_on_the_box_plane_beside_a_trace_is_flipped_away():
    # the patch of the plain-box excursion set `jaxmesh generate --kind grf --volume-fraction 0.2
    # --correlation-length 0.12 --grid 40 --seed 61`, inclusion 3 (a lens 0.01 deep that x = 0 cuts):
    # trace nodes 7, 1, 4 on x = 0, the chord 4-7 skipping 1, and node 3 (degree 3) tenting over the
    # sliver between them; its triangle (4, 7, 3) faces into the inclusion
    p = np.array([[0, 0.8530018, 0.3606393], [0, 0.8570499, 0.3639332], [0, 0.860558, 0.3670755],
                  [0.0009393, 0.8565276, 0.3647928], [0, 0.8589479, 0.3656079], [0.0025089, 0.8517663, 0.3634075],
                  [0.0034303, 0.8527895, 0.3655787], [0, 0.8558164, 0.3628828], [0.003431, 0.8544071, 0.3668479],
                  [0.0033829, 0.8560165, 0.3681829], [0.0023652, 0.8579092, 0.3682497]])
    t = np.array([[1, 3, 7], [4, 3, 1], [10, 4, 2], [7, 5, 0], [5, 7, 6], [7, 8, 6], [4, 7, 3], [7, 4, 8], [4, 9, 8],
                  [9, 4, 10]])
    gradient = np.array([1.16, 0.72, -0.83])  # the level set's there, to a few percent

    def phi(x):
        return x @ gradient

    on_plane = plane_flags(p, (1.0, 1.0, 1.0))
    assert np.flatnonzero(folded(p, t, phi)).tolist() == [6]
    u, v, *_ = plane_chords(p, t, on_plane)
    assert sorted(np.r_[u, v].tolist()) == [4, 7]
    # a trace edge (its other triangle beyond the plane) is no chord
    beyond = np.vstack([p, [-0.002, 0.8575, 0.364]])
    across = t.copy()
    across[7] = [7, 4, 11]
    assert not len(plane_chords(beyond, across, plane_flags(beyond, (1.0, 1.0, 1.0)))[0])
    flipped = flip_plane_chords(p, t, on_plane, phi)
    assert not folded(p, flipped, phi).any()
    assert not len(plane_chords(p, flipped, on_plane)[0])
    assert _boundary_edges(flipped) == _boundary_edges(t)  # the patch's rim, traces included, stays
    directed = np.concatenate([flipped[:, [0, 1]], flipped[:, [1, 2]], flipped[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # still consistently oriented
    # a flip whose triangles would fold is not made
    assert np.array_equal(flip_plane_chords(p, t, on_plane, lambda x: -phi(x)), t)


def _rim(points, tris):
    """The border edges of a patch as pairs of coordinates (node ids change when nodes go)."""
    return {tuple(sorted(map(tuple, points[list(e)].tolist()))) for e in _boundary_edges(tris)}


# two patches of inclusion 1 of the sweep's plain-box `numpy_spheres_s3` (`python benchmarks/sweep_shapes.py
# OUT --no-periodic --only numpy_spheres_s3`), a lens at most 0.0023 deep that x = 0 cuts; each crossed itself
# (the surfaces stage stopped there at every sampling). Lengths in thousandths; the level set's gradient there.
_TENT_OVER_A_CHORD = (  # trace 3, 6, 7 on x = 0, chord 3-7; node 4 (degree 3) beyond it, its triangle (4, 7, 3) folded
    [[0, 4.3991, 120.2108], [0.0929, 4.2513, 120.5476], [0.1272, 4.2324, 120.8503], [0, 4.647, 121.0454],
     [0.0575, 4.5296, 121.2134], [0.1036, 4.5167, 121.6648], [0, 4.7029, 121.2184], [0, 4.7678, 121.4123],
     [0, 4.8569, 121.6656], [0.244, 3.9758, 121.2277], [0.1843, 4.2405, 121.6141]],
    [[0, 3, 1], [3, 2, 1], [4, 7, 3], [3, 6, 4], [4, 6, 7], [7, 8, 5], [3, 9, 2], [7, 5, 3], [5, 10, 3], [10, 9, 3]],
    [0.984, 0.33, -0.097])
_NODE_THROUGH_ITS_RING = (  # node 5 (degree 3) pushed through its ring 3, 4, 6: its three triangles folded
    [[0, 15.4557, 132.1034], [0, 15.8021, 133.0852], [0.118, 15.1225, 132.2255], [0, 15.6475, 132.5993],
     [0.0477, 15.5664, 132.7899], [0.0398, 15.5964, 132.8068], [0.0697, 15.5747, 133.0316],
     [0.1159, 15.579, 133.5872], [0.2426, 14.8791, 132.7139], [0.207, 15.0986, 132.9647],
     [0.1578, 15.3325, 133.1713], [0.1793, 15.3307, 133.4187]],
    [[0, 3, 2], [3, 4, 5], [4, 6, 5], [10, 9, 6], [4, 1, 6], [4, 3, 1], [1, 7, 6], [7, 11, 6], [6, 9, 3], [5, 6, 3],
     [2, 3, 8], [3, 9, 8], [11, 10, 6]],
    [1.234, 0.4, -0.132])


@pytest.mark.parametrize("patch, folds", [(_TENT_OVER_A_CHORD, [2]), (_NODE_THROUGH_ITS_RING, [1, 2, 9])],
                         ids=["tent over a chord", "node through its ring"])
def test_a_node_folded_beside_a_shallow_cut_is_removed(patch, folds):
    p, t, gradient = np.array(patch[0]) * 1e-3, np.array(patch[1]), np.array(patch[2])
    centre = p.mean(axis=0)

    def phi(x):
        return (x - centre) @ gradient

    on_plane = plane_flags(p, (1.0, 1.0, 1.0))
    assert np.flatnonzero(folded(p, t, phi)).tolist() == folds
    assert len(intersecting_pairs(p, t))
    assert folded(p, flip_plane_chords(p, t, on_plane, phi), phi).any()  # the chord flip does not clear it
    q, s, q_on_plane = remove_fold_nodes(p, t, on_plane, phi, (1.0, 1.0, 1.0))
    assert len(q) == len(p) - 1 and len(s) == len(t) - 2  # one node and two triangles go
    assert not folded(q, s, phi).any() and not len(intersecting_pairs(q, s))
    assert _rim(q, s) == _rim(p, t)  # the patch's border, traces included, stays
    assert np.array_equal(q_on_plane, plane_flags(q, (1.0, 1.0, 1.0)))
    directed = np.concatenate([s[:, [0, 1]], s[:, [1, 2]], s[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # still consistently oriented
    assert all(len(x) == 3 for x in map(set, s.tolist()))
    same = remove_fold_nodes(q, s, q_on_plane, phi, (1.0, 1.0, 1.0))  # nothing folded: nothing changes
    assert np.array_equal(same[0], q) and np.array_equal(same[1], s)


def test_unfold_removes_a_fold_and_keeps_nodes_on_the_level_set(sphere):
    phi, p, t = sphere
    edges, _ = half_edges(t, len(p))
    i, j = edges[0]
    q = p.copy()
    q[i] = project(phi, (2 * p[j] - p[i])[None], np.zeros((1, 3), bool))[0][0]  # node i jumps over node j
    assert folded(q, t, phi).any()
    on_plane = np.zeros(q.shape, bool)
    on_plane[j] = True  # a node on a plane is never moved
    r = unfold(q, t, on_plane, phi, 8)
    assert not folded(r, t, phi).any()
    assert np.abs(np.linalg.norm(r - 0.5, axis=1) - 0.2).max() < 1e-10
    assert np.array_equal(r[j], q[j])
    assert np.array_equal(unfold(p, t, on_plane, phi, 8), p)  # nothing folded: nothing moves


def test_revert_around_defects_keeps_the_relaxation_away_from_a_fold_it_made(sphere):
    phi, p, t = sphere
    rng = np.random.default_rng(3)
    moved = project(phi, p + 0.002 * rng.standard_normal(p.shape), np.zeros(p.shape, bool))[0]  # a "relaxation"
    edges, _ = half_edges(t, len(p))
    i, j = edges[0]
    moved[i] = project(phi, (2 * p[j] - p[i])[None], np.zeros((1, 3), bool))[0][0]  # it folds at node i
    assert folded(moved, t, phi).any() and not folded(p, t, phi).any()
    none_pinned = np.zeros(len(p), bool)
    r = revert_around_defects(p, moved, t, phi, 0.0, none_pinned)
    assert r is not None and not folded(r, t, phi).any()
    back = np.all(r == p, axis=1)
    assert back[i] and back[j] and back.sum() < 0.2 * len(p)  # only around the fold
    assert np.array_equal(r[~back], moved[~back])
    # a fold that the nodes before the relaxation already make does not fail it
    assert np.array_equal(revert_around_defects(moved, moved, t, phi, 0.0, none_pinned), moved)
    # defects that going back cannot clear: None (the caller keeps the unrelaxed surface)
    assert revert_around_defects(p, moved, t, phi, 61.0, none_pinned) is None
    # nor where going back would move a pinned (box-plane) node
    pinned = none_pinned.copy()
    pinned[j] = True
    assert revert_around_defects(p, moved, t, phi, 0.0, pinned) is None


def test_cut_plane_splits_without_straddling(sphere):
    phi, p, t = sphere
    box = (0.55, 1.0, 1.0)  # the plane x = 0.55 cuts the sphere
    q, t2, flags, new = cut_plane(p, t, np.zeros(p.shape, bool), 0, 0.55)
    assert len(new) > 0 and (q[new, 0] == 0.55).all() and flags[new, 0].all()
    assert _closed(t2) and not straddling(q, t2, box).any()
    assert enclosed_volume(q, t2) == pytest.approx(enclosed_volume(p, t), rel=1e-12)


def test_a_node_touching_a_plane_without_a_crossing_is_moved_off_it(sphere):
    # the cut's trace nodes have neighbours on both sides; a node laid on the plane x = 0.7 at the
    # sphere's pole has all its neighbours below it: its wrapped copy would have no translate
    phi, p, t = sphere
    q, t2, flags, _ = cut_plane(p, t, np.zeros(p.shape, bool), 0, 0.55)
    assert flags[:, 0].sum() > 10 and not touching_plane_nodes(q, t2, flags, (0.55, 1.0, 1.0)).any()
    q, t2, flags = p.copy(), t, np.zeros(p.shape, bool)
    pole = int(np.argmax(q[:, 0]))
    q[pole] = (0.7, 0.5, 0.5)
    flags[pole, 0] = True
    touch = touching_plane_nodes(q, t2, flags, (0.7, 1.0, 1.0))
    assert np.flatnonzero(touch.any(axis=1)).tolist() == [pole] and touch[pole].tolist() == [True, False, False]
    r, flags2 = release_touching(q, t2, flags, phi, (0.7, 1.0, 1.0), 8)
    assert not flags2[pole].any() and r[pole, 0] < 0.7  # the surface is tangent there: just off it
    assert abs(np.linalg.norm(r[pole] - 0.5) - 0.2) < 1e-10
    rest = np.arange(len(q)) != pole
    assert np.array_equal(r[rest], q[rest]) and np.array_equal(flags2[rest], flags[rest])


def test_collapse_removes_short_edges_and_keeps_traces(sphere):
    phi, p, t = sphere
    q, t2, flags, _ = cut_plane(p, t, np.zeros(p.shape, bool), 0, 0.55)
    edges, _ = half_edges(t2, len(q))
    length = np.linalg.norm(q[edges[:, 0]] - q[edges[:, 1]], axis=1)
    short = length < 0.4 * np.median(length)
    assert short.sum() > 10  # marching cubes and the cut leave many
    q3, t3, flags3, done = collapse_edges(q, t2, flags, short)
    assert done > 0 and len(q3) == len(q) - done and len(t3) == len(t2) - 2 * done
    assert _closed(t3) and np.array_equal(np.unique(t3), np.arange(len(q3)))
    assert len(q3) - len(half_edges(t3, len(q3))[0]) + len(t3) == 2  # still a sphere
    # trace vertices are kept or merged into trace vertices: the plane x = 0.55 keeps its cut
    assert (q3[flags3[:, 0], 0] == 0.55).all() and flags3[:, 0].sum() > 0
    assert not straddling(q3, t3, (0.55, 1.0, 1.0)).any()
    assert enclosed_volume(q3, t3) == pytest.approx(enclosed_volume(q, t2), rel=0.02)


def test_collapse_keeps_a_small_cap_beyond_a_plane(sphere):
    # the plane x = 0.69 leaves a cap of a few triangles beyond it; collapsing its apex into a trace
    # vertex would lay a triangle flat on the plane and drop the trace's translate on the other face
    phi, p, t = sphere
    q, t2, flags, _ = cut_plane(p, t, np.zeros(p.shape, bool), 0, 0.69)
    for _ in range(6):
        q, t2, flags, _ = collapse_edges(q, t2, flags, np.ones(len(half_edges(t2, len(q))[0]), bool))
    assert _closed(t2)
    on_x = flags[t2, 0].all(axis=1) & (q[t2][:, :, 0] == 0.69).all(axis=1)
    assert not on_x.any() and (q[:, 0] > 0.69).any()


def test_sphere_at_r_over_6():
    r = 0.2
    ms = Microstructure.from_functions([sphere_sdf(np.array([0.5, 0.5, 0.5]), r)], (1.0, 1.0, 1.0), (32, 32, 32))
    h = r / 6
    out = mesh_inclusion(ms.inclusions[0], as_size_fn(h, ms.box), ms.box, SurfaceConfig())
    p, t = out["points"], out["triangles"]
    assert _closed(t)
    assert enclosed_volume(p, t) == pytest.approx(4 / 3 * np.pi * r**3, rel=0.01)
    assert np.abs(ms.inclusion_phi(1, p)).max() < 1e-6 * h
    assert cell_quality(p, t).mean() >= 0.85 and min_angles(p, t).min() >= 20.0
    edges, _ = half_edges(t, len(p))
    length = np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1)
    assert 0.7 * h < np.median(length) < 1.5 * h
    assert len(intersecting_pairs(p, t)) == 0


@pytest.mark.parametrize("axes", [(0.127, 0.08, 0.08), (0.15, 0.1, 0.06)])
def test_rotated_ellipsoid_at_smallest_axis_over_6(axes):
    from jaxmesh.geometry._shapes import ellipsoid_sdf

    axes = np.array(axes)
    rotation = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    ms = Microstructure.from_functions([ellipsoid_sdf(np.array([0.5, 0.5, 0.5]), axes, rotation)], (1.0, 1.0, 1.0),
                                       (32, 32, 32))  # fmt: skip
    out = mesh_inclusion(ms.inclusions[0], as_size_fn(axes.min() / 6, ms.box), ms.box, SurfaceConfig())
    p, t = out["points"], out["triangles"]
    assert _closed(t)
    assert enclosed_volume(p, t) == pytest.approx(4 / 3 * np.pi * axes.prod(), rel=0.01)
    assert cell_quality(p, t).mean() >= 0.85 and min_angles(p, t).min() >= 20.0


def test_a_piece_the_box_cuts_to_a_sliver_along_an_edge_gets_a_closed_marching_cubes_surface():
    """A sphere centred beyond the box edge y = z = 0 reaches 0.15 grid steps into a plain box: there
    its piece is a row of three samples along the edge, and beyond the box the field's continuation
    widens along x, past the window its bounds give (at bb47511: "the marching-cubes surface is not
    closed", as for a generated excursion set read as a plain box)."""
    n = 32
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    phi = np.linalg.norm(X - np.array([0.5, -0.1, -0.1]), axis=-1) - (np.hypot(0.1, 0.1) + 0.15 / n)
    ms = Microstructure.from_levelset(np.minimum(phi, np.linalg.norm(X - 0.55, axis=-1) - 0.2), periodic=False)
    sliver = ms.inclusions[1]
    assert (np.asarray(sliver.upper) - sliver.lower)[1:].max() < 0.25 / n
    out = mesh_inclusion(sliver, as_size_fn(0.005, ms.box, False), ms.box, periodic=False)
    p = out["points"]
    assert len(out["triangles"]) and p.min() >= 0.0 and p[:, 1:].max() < 0.25 / n
    assert np.abs(ms.inclusion_phi(2, p[(p[:, 1] > 0) & (p[:, 2] > 0)])).max() < 1e-6 * 0.005


def test_two_spheres_one_grid_step_apart():
    r, step = 0.15, 1.0 / 32
    c = [np.array([0.3, 0.5, 0.5]), np.array([0.3 + 2 * r + step, 0.5, 0.5])]
    ms = Microstructure.from_functions([sphere_sdf(x, r) for x in c], (1.0, 1.0, 1.0), (32, 32, 32))
    assert len(ms.inclusions) == 2
    h = as_size_fn(r / 4, ms.box)
    outs = [mesh_inclusion(inc, h, ms.box) for inc in ms.inclusions]
    for o in outs:
        assert _closed(o["triangles"])
    p = np.vstack([outs[0]["points"], outs[1]["points"]])
    t = np.vstack([outs[0]["triangles"], outs[1]["triangles"] + len(outs[0]["points"])])
    assert len(intersecting_pairs(p, t)) == 0


def test_config_validation():
    with pytest.raises(ValueError, match="snap_fraction"):
        SurfaceConfig(snap_fraction=0.7)
    with pytest.raises(ValueError, match="face_min_angle"):
        SurfaceConfig(face_min_angle=45.0)
    with pytest.raises(ValueError, match="trace_grading"):
        SurfaceConfig(trace_grading=0.0)
    with pytest.raises(ValueError, match="h: expected"):
        as_size_fn(-1.0, (1.0, 1.0, 1.0))


def _tube(counts, radius=0.2, box=(1.0, 1.0, 1.0), seed=0):
    """An open tube along x from x = 0 to x = L: rings of counts[k] nodes (each turned at random),
    consecutive rings zipped by angle; the end rings are the traces on the two box planes."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0.0, box[0], len(counts))
    rings, points = [], []
    for x, m in zip(xs, counts):
        angle = np.sort(rng.uniform(0, 2 * np.pi / m) + 2 * np.pi * np.arange(m) / m)
        rings.append((len(points) + np.arange(m), angle))
        points += [[x, 0.5 + radius * np.cos(t), 0.5 + radius * np.sin(t)] for t in angle]
    tris = []
    for (ia, ta), (ib, tb) in zip(rings[:-1], rings[1:]):
        i = j = 0
        while i < len(ia) or j < len(ib):
            a0, b0 = ia[i % len(ia)], ib[j % len(ib)]
            if j >= len(ib) or (i < len(ia) and ta[(i + 1) % len(ia)] + 2 * np.pi * ((i + 1) // len(ia))
                                < tb[(j + 1) % len(ib)] + 2 * np.pi * ((j + 1) // len(ib))):
                tris.append([a0, ia[(i + 1) % len(ia)], b0])
                i += 1
            else:
                tris.append([a0, ib[(j + 1) % len(ib)], b0])
                j += 1
    on_plane = np.zeros((len(points), 3), bool)
    on_plane[rings[0][0], 0] = on_plane[rings[-1][0], 0] = True
    return np.array(points), np.array(tris, np.int64), on_plane


def _oriented_manifold(tris):
    directed = {(int(a), int(b)) for t in tris for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert len(directed) == 3 * len(tris)  # no directed edge twice: one orientation, no fold-over
    return directed


def test_match_opposite_traces_pairs_and_splits_until_the_traces_are_translates():
    from jaxmesh._surface_ops import boundary_edges, match_opposite_traces

    for counts, seed in (([12, 13, 14, 15], 0), ([16, 12, 12, 11], 1), ([9, 9, 9], 2)):
        points, tris, on_plane = _tube(counts, seed=seed)
        _oriented_manifold(tris)
        p, t, flags = match_opposite_traces(points, tris, on_plane, (1.0, 1.0, 1.0), (0,))
        _oriented_manifold(t)
        edges = boundary_edges(t, len(p))[0]
        ends = [{tuple(sorted(map(tuple, p[e][:, 1:].tolist()))) for e in edges if (p[e, 0] == x).all()}
                for x in (0.0, 1.0)]
        assert ends[0] == ends[1] and len(ends[0]) >= max(counts[0], counts[-1])
        assert flags[np.unique(edges), 0].all()
        # every trace node stays on the circle; no triangle degenerates
        r = np.hypot(p[np.unique(edges), 1] - 0.5, p[np.unique(edges), 2] - 0.5)
        np.testing.assert_allclose(r, 0.2, atol=1e-12)
        area = np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1)
        assert area.min() > 1e-4


def test_match_opposite_traces_refuses_a_surface_that_ends_on_one_plane_only():
    from jaxmesh._surface_ops import TraceMismatch, match_opposite_traces

    points, tris, on_plane = _tube([10, 10, 10])
    on_plane[points[:, 0] == 1.0, 0] = False  # as if the far end were not on the box plane
    with pytest.raises(TraceMismatch, match="only"):
        match_opposite_traces(points, tris, on_plane, (1.0, 1.0, 1.0), (0,))


def test_match_opposite_traces_straightens_a_trace_that_turns_back_on_itself():
    """A trace node pushed just past its next neighbour (a fold of the surface along the plane, as a
    cut of a nearly tangent surface leaves) is collapsed before the traces are paired."""
    from jaxmesh._surface_ops import boundary_edges, match_opposite_traces

    points, tris, on_plane = _tube([12, 10, 12], seed=3)
    start = np.flatnonzero(points[:, 0] == 0.0)
    order = boundary_edges(tris, len(points))[0]
    nxt = {int(i): int(j) for i, j in order if i in start and j in start}
    v = int(start[4])
    w = nxt[v]
    turn = lambda q: np.arctan2(points[q, 2] - 0.5, points[q, 1] - 0.5)  # noqa: E731
    past = turn(w) + 0.05 * (turn(w) - turn(v))  # v a twentieth of a segment beyond w
    points[v, 1:] = 0.5 + 0.2 * np.array([np.cos(past), np.sin(past)])
    p, t, _ = match_opposite_traces(points, tris, on_plane, (1.0, 1.0, 1.0), (0,))
    _oriented_manifold(t)
    assert v not in t  # collapsed into w
    edges = boundary_edges(t, len(p))[0]
    ends = [{tuple(sorted(map(tuple, p[e][:, 1:].tolist()))) for e in edges if (p[e, 0] == x).all()}
            for x in (0.0, 1.0)]
    assert ends[0] == ends[1]


def test_a_node_off_the_level_set_is_reported_where_it_is():
    """The error names the node's place: an unwrapped node beyond the periodic box at its image in
    [0, L), a node on a far box plane x = L at x = L (it read 0, the opposite plane, before)."""
    sphere = sphere_sdf(np.array([0.5, 0.5, 0.5]), 0.2)
    for node, place in (([1.0, 0.5, 1.0], r"\(1\.0, 0\.5, 1\.0\)"), ([1.25, 0.5, -0.25], r"\(0\.25, 0\.5, 0\.75\)")):
        with pytest.raises(MeshingError, match=place):
            refuse_nodes_off_the_level_set(np.array([node]), sphere, (1.0, 1.0, 1.0), 1, 0.01)
    refuse_nodes_off_the_level_set(np.array([[0.7, 0.5, 0.5]]), sphere, (1.0, 1.0, 1.0), 1, 0.01)  # on it
