"""Unit tests of the constrained 2D triangulation: segment recovery (splitting, flips), flood fill,
labels, quality flips. NumPy only, tiny inputs."""

import numpy as np
import pytest

from jaxmesh._contours import BOX_SEGMENT, INTERFACE, PSLG, assemble_pslg, rebuild_box_segments, split_segments
from jaxmesh._errors import MeshingError
from jaxmesh._quality import cell_quality, signed_volumes
from jaxmesh._triangulate2d import (
    component_labels,
    conforming_delaunay,
    constrained_delaunay,
    delaunay_triangles,
    distance_to_segments,
    edge_keys,
    flood_fill,
    improve_by_flips,
    interface_sides,
    interior_edges,
    missing_segments,
    recover_segments_by_flips,
    refine_bad_triangles,
    smooth_free_nodes,
    triangle_angles,
)


def _hull_area(points):
    from scipy.spatial import ConvexHull

    return ConvexHull(points).volume


def _check_triangulation(points, tri, area):
    """Valid: all CCW and non-flat, manifold, covering exactly the expected area."""
    v = signed_volumes(points, tri)
    assert np.all(v > 0)
    assert np.isclose(v.sum(), area, rtol=1e-12)
    interior_edges(tri, len(points))  # raises on a non-manifold edge


def _has_edge(tri, n, a, b):
    return not missing_segments(tri, np.array([[a, b]]), n)[0]


def _circle_pslg(radius=0.3, n_nodes=12, center=(0.5, 0.5)):
    """A periodic unit box (coarse box edges) with one closed interface polygon on a circle."""
    pslg = assemble_pslg([], [], (1.0, 1.0), lambda p: np.full(len(p), 0.25))
    t = 2 * np.pi * np.arange(n_nodes) / n_nodes
    ring = np.asarray(center) + radius * np.stack([np.cos(t), np.sin(t)], 1)
    n0 = pslg.n_points
    ids = n0 + np.arange(n_nodes)
    seg = np.stack([ids, np.roll(ids, -1)], 1)
    return PSLG(
        points=np.vstack([pslg.points, ring]),
        segments=np.vstack([pslg.segments, seg]),
        segment_inclusion=np.concatenate([pslg.segment_inclusion, np.ones(n_nodes, np.int64)]),
        segment_partner=np.concatenate([pslg.segment_partner, -np.ones(n_nodes, np.int64)]),
        node_kind=np.concatenate([pslg.node_kind, np.full(n_nodes, INTERFACE, np.int8)]),
        node_axis=np.concatenate([pslg.node_axis, -np.ones(n_nodes, np.int8)]),
        node_inclusion=np.concatenate([pslg.node_inclusion, np.ones(n_nodes, np.int64)]),
        periodic_pairs=pslg.periodic_pairs,
        box=(1.0, 1.0),
    )


def _radial_projection(center=(0.5, 0.5), radius=0.3):
    def project(points, ids):
        d = points - np.asarray(center)
        return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)

    return project


def test_flip_recovery_forces_long_segments():
    rng = np.random.default_rng(0)
    pts = np.vstack([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], rng.uniform(0.02, 0.98, (300, 2))])
    pts = np.vstack([pts, [[0.1, 0.13], [0.9, 0.81], [0.15, 0.85], [0.8, 0.2]]])
    a, b, c, d = len(pts) - 4, len(pts) - 3, len(pts) - 2, len(pts) - 1
    segments = np.array([[a, b], [c, d]])
    tri = delaunay_triangles(pts)
    assert missing_segments(tri, segments, len(pts)).all()  # long diagonals are never Delaunay here
    # two crossing segments cannot both be present: recover one
    out = recover_segments_by_flips(pts, tri, segments[:1])
    assert _has_edge(out, len(pts), a, b)
    assert len(out) == len(tri)
    _check_triangulation(pts, out, 1.0)


def test_constrained_delaunay_keeps_polygon_and_raises_on_node_on_segment():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 2 * np.pi, 9)[:-1]
    star = 0.5 + np.stack([np.cos(t), np.sin(t)], 1) * np.where(np.arange(8) % 2, 0.1, 0.4)[:, None]
    pts = np.vstack([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], star, rng.uniform(0.01, 0.99, (200, 2))])
    ids = 4 + np.arange(8)
    seg = np.stack([ids, np.roll(ids, -1)], 1)
    tri = constrained_delaunay(pts, seg)
    assert not missing_segments(tri, seg, len(pts)).any()
    _check_triangulation(pts, tri, 1.0)
    # a node exactly on a segment cannot be flipped around
    pts2 = np.vstack([pts[:4], [[0.2, 0.5], [0.8, 0.5], [0.5, 0.5], [0.5, 0.8], [0.5, 0.2]]])
    with pytest.raises(MeshingError, match="lies on the constrained segment") as err:
        recover_segments_by_flips(pts2, delaunay_triangles(pts2), np.array([[4, 5]]))
    assert err.value.segment == (4, 5)  # so that the face mesher can say whose trace it is


def test_split_mirrors_box_segments_and_projects_interfaces():
    pslg = _circle_pslg()
    box_seg = np.nonzero(pslg.segment_inclusion == BOX_SEGMENT)[0]
    # pick a segment on a slave edge (x = 1): its master on x = 0 must be split identically
    slave = next(s for s in box_seg if np.all(pslg.points[pslg.segments[s], 0] == 1.0))
    master = pslg.segment_partner[slave]
    assert pslg.segment_partner[master] == slave
    iface = np.nonzero(pslg.segment_inclusion == 1)[0][:2]
    out = split_segments(pslg, np.array([slave, *iface]), _radial_projection())
    assert out.n_points == pslg.n_points + 4  # 2 interface midpoints + 1 box midpoint mirrored
    new = out.points[pslg.n_points:]
    r = np.linalg.norm(new[out.node_kind[pslg.n_points:] == INTERFACE] - 0.5, axis=1)
    assert np.allclose(r, 0.3, atol=1e-14)
    # the mirrored pair: exact translates, registered as a periodic pair on axis 0
    pair = out.periodic_pairs[0][-1]
    assert out.points[pair[1], 0] == 1.0 and out.points[pair[0], 0] == 0.0
    assert out.points[pair[1], 1] == out.points[pair[0], 1]
    # partners stay symmetric and translated node-by-node
    for s in np.nonzero(out.segment_inclusion == BOX_SEGMENT)[0]:
        p = out.segment_partner[s]
        assert out.segment_partner[p] == s
        d = out.points[out.segments[p]] - out.points[out.segments[s]]
        assert np.allclose(np.abs(d), np.abs(d[0]), atol=0) and np.count_nonzero(d[0]) == 1
    # every old node keeps its id and coordinates
    assert np.array_equal(out.points[: pslg.n_points], pslg.points)


@pytest.mark.parametrize("remove", [False, True])
def test_conforming_delaunay_recovers_every_segment(remove):
    pslg = _circle_pslg(n_nodes=10)
    # a dense lattice hugging the coarse polygon: many segments are missing at first
    g = np.stack(np.meshgrid(np.linspace(0.03, 0.97, 30), np.linspace(0.03, 0.97, 30), indexing="ij"), -1)
    interior = g.reshape(-1, 2) + 1e-4 * np.random.default_rng(2).standard_normal((900, 2))
    tri0 = delaunay_triangles(np.vstack([pslg.points, interior]))
    assert missing_segments(tri0, pslg.segments, pslg.n_points + len(interior)).any()
    out, inner, tri, stats = conforming_delaunay(pslg, interior, _radial_projection(), remove_encroaching=remove)
    pts = np.vstack([out.points, inner])
    assert not missing_segments(tri, out.segments, len(pts)).any()
    _check_triangulation(pts, tri, 1.0)
    if remove:
        assert stats["removed"] > 0 and len(inner) < len(interior)
    else:
        assert stats["split"] > 0 and len(inner) == len(interior)
        # split interface nodes lie on the circle
        iface = out.node_kind == INTERFACE
        assert np.allclose(np.linalg.norm(out.points[iface] - 0.5, axis=1), 0.3, atol=1e-14)
    assert stats["flip_recovered"] == 0


def test_flood_fill_and_labels():
    pslg = _circle_pslg(n_nodes=24)
    rng = np.random.default_rng(3)
    interior = rng.uniform(0.02, 0.98, (400, 2))
    r = np.linalg.norm(interior - 0.5, axis=1)
    interior = interior[np.abs(r - 0.3) > 0.03]
    out, inner, tri, _ = conforming_delaunay(pslg, interior, _radial_projection())
    pts = np.vstack([out.points, inner])
    n_comp, comp = flood_fill(tri, out.segments, len(pts))
    assert n_comp == 2
    cent = pts[tri].mean(axis=1)
    inside = np.linalg.norm(cent - 0.5, axis=1) < 0.3
    # every component is exactly one side of the circle
    for c in range(n_comp):
        assert len(np.unique(inside[comp == c])) == 1
    # majority labels survive wrong votes on a minority of triangles
    votes = inside.astype(np.int64) * 7
    noisy = votes.copy()
    flip = rng.uniform(size=len(votes)) < 0.2
    noisy[flip] = 7 - noisy[flip]
    lab, dissent = component_labels(comp, noisy)
    assert np.array_equal(lab[comp], votes)
    assert 0.1 < dissent.max() < 0.3  # ~20% wrong non-zero votes in the matrix component
    # weights decide: light wrong votes barely count
    w = np.where(flip, 1e-3, 1.0)
    lab, dissent = component_labels(comp, noisy, w)
    assert np.array_equal(lab[comp], votes) and dissent.max() < 1e-2
    # a component without votes is matrix
    assert component_labels(np.array([0]), np.array([5]), n_components=2)[0].tolist() == [5, 0]
    # interface sides: every triangle along the circle, voted from its own side
    t, inc = interface_sides(tri, out.segments, out.segment_inclusion, len(pts))
    assert np.all(inc == 1) and len(t) == 2 * np.count_nonzero(out.segment_inclusion == 1)
    assert set(comp[t].tolist()) == {0, 1}
    # without constraints everything is one component
    assert flood_fill(tri, np.zeros((0, 2), np.int64), len(pts))[0] == 1


def test_improve_by_flips_raises_min_quality_and_keeps_constraints():
    rng = np.random.default_rng(4)
    pts = np.vstack([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], rng.uniform(0.05, 0.95, (150, 2))])
    tri = delaunay_triangles(pts)
    # spoil the Delaunay triangulation by flipping every flippable edge once
    c, d, u, v, t1, t2, _ = interior_edges(tri, len(pts))
    bad = tri.copy()
    used = np.zeros(len(tri), dtype=bool)
    for k in range(len(c)):
        if used[t1[k]] or used[t2[k]]:
            continue
        n1, n2 = np.array([c[k], v[k], u[k]]), np.array([v[k], d[k], u[k]])
        if signed_volumes(pts, np.stack([n1, n2])).min() <= 0:
            continue
        bad[t1[k]], bad[t2[k]] = n1, n2
        used[t1[k]] = used[t2[k]] = True
    q_bad = cell_quality(pts, bad)
    # constrain one of the spoiled (non-Delaunay) edges: it must survive
    keep = np.array([[v[0], u[0]]]) if used[t1[0]] else np.zeros((0, 2), np.int64)
    out, n_flips = improve_by_flips(pts, bad, keep)
    q = cell_quality(pts, out)
    assert n_flips > 0
    assert q.min() > q_bad.min()
    _check_triangulation(pts, out, 1.0)
    assert not missing_segments(out, keep, len(pts)).any()
    # never worse than where it started (Delaunay maximises the min angle, not min q)
    out0, _ = improve_by_flips(pts, tri, np.zeros((0, 2), np.int64))
    assert cell_quality(pts, out0).min() >= cell_quality(pts, tri).min()


def test_smooth_free_nodes_raises_angles_and_keeps_fixed_nodes_and_segments():
    rng = np.random.default_rng(5)
    side = np.linspace(0.0, 1.0, 11)
    fixed = np.unique(np.vstack([np.c_[side, 0 * side], np.c_[side, 0 * side + 1], np.c_[0 * side, side],
                                 np.c_[0 * side + 1, side], np.c_[0.5 + 0 * side[1:-1], side[1:-1]]]), axis=0)
    pts = np.vstack([fixed, rng.uniform(0.02, 0.98, (400, 2))])
    wall = np.flatnonzero(np.isclose(pts[: len(fixed), 0], 0.5))
    wall = wall[np.argsort(pts[wall, 1])]
    segments = np.stack([wall[:-1], wall[1:]], axis=1)  # the line x = 0.5, from y = 0.1 to 0.9
    tri = constrained_delaunay(pts, segments)
    mid = np.flatnonzero((pts[:, 1] > 0.2) & (pts[:, 1] < 0.8))
    mid = mid[mid >= len(fixed)]  # free nodes beside the wall, away from its ends
    out = smooth_free_nodes(pts, tri, len(fixed))
    assert np.array_equal(out[: len(fixed)], pts[: len(fixed)])
    _check_triangulation(out, tri, 1.0)  # nothing inverted, area kept
    before, after = triangle_angles(pts, tri).min(axis=1), triangle_angles(out, tri).min(axis=1)
    assert after.min() >= before.min() and after.mean() > before.mean() + 5.0
    assert np.array_equal(np.sign(out[mid, 0] - 0.5), np.sign(pts[mid, 0] - 0.5))  # none crossed the wall
    assert not np.array_equal(out, pts)


def test_edge_keys_and_errors():
    assert edge_keys(np.array([3]), np.array([1]), 10)[0] == edge_keys(np.array([1]), np.array([3]), 10)[0] == 13
    with pytest.raises(ValueError, match="expected"):
        delaunay_triangles(np.zeros((2, 2)))
    tri = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [0, 1, 4]])  # edge (0, 1) in three triangles
    with pytest.raises(MeshingError, match="more than two"):
        interior_edges(tri, 5)


def test_distance_to_segments_matches_brute_force():
    rng = np.random.default_rng(5)
    nodes = rng.uniform(0, 1, (20, 2))
    segs = np.stack([np.arange(0, 20, 2), np.arange(1, 20, 2)], 1)
    q = rng.uniform(0, 1, (300, 2))
    a, b = nodes[segs[:, 0]], nodes[segs[:, 1]]
    t = np.clip(np.einsum("mkd,kd->mk", q[:, None] - a, b - a) / np.sum((b - a) ** 2, 1), 0, 1)
    exact = np.linalg.norm(q[:, None] - (a + t[..., None] * (b - a)), axis=2).min(1)
    approx = distance_to_segments(q, nodes, segs, 0.01)
    assert np.all(approx >= exact - 1e-12) and np.all(approx <= exact + 0.005)


def test_refine_bad_triangles_thin_gap_to_box_edge():
    """A coarse polygon 0.01 above the box edge y = 0: the thin matrix strip gets refined until its
    triangles reach the angle target; box splits are mirrored, periodic pairs stay translates."""
    pslg = _circle_pslg(radius=0.3, n_nodes=24, center=(0.5, 0.31))
    project = _radial_projection(center=(0.5, 0.31))
    out, inner, tri, _ = conforming_delaunay(pslg, np.zeros((0, 2)), project)
    pts = np.vstack([out.points, inner])
    from jaxmesh._triangulate2d import triangle_angles

    assert triangle_angles(pts, tri).min() < 10
    ref, inner2, tri2, stats = refine_bad_triangles(out, inner, tri, project, lambda p: np.full(len(p), 0.1),
                                                    min_angle=20.5, min_edge=0.01)
    pts2 = np.vstack([ref.points, inner2])
    assert stats["split"] > 0 and stats["left"] == 0
    assert triangle_angles(pts2, tri2).min() >= 20.5
    _check_triangulation(pts2, tri2, 1.0)
    assert not missing_segments(tri2, ref.segments, len(pts2)).any()
    for a, pairs in ref.periodic_pairs.items():
        assert np.array_equal(pts2[pairs[:, 1]], pts2[pairs[:, 0]] + np.eye(2)[a])
    # new interface nodes on the circle
    iface = ref.node_kind == INTERFACE
    assert np.allclose(np.linalg.norm(ref.points[iface] - (0.5, 0.31), axis=1), 0.3, atol=1e-14)


def test_rebuild_box_segments_after_sliding():
    pslg = assemble_pslg([], [], (1.0, 1.0), lambda p: np.full(len(p), 0.2))
    pts = pslg.points.copy()
    # swap the order of two master nodes on x = 0 (and their partners), as a sliding node would
    pairs = pslg.periodic_pairs[0]
    inner = pairs[(pts[pairs[:, 0], 1] > 0) & (pts[pairs[:, 0], 1] < 1)]
    (m1, s1), (m2, s2) = inner[0], inner[1]
    for i, j in ((m1, m2), (s1, s2)):
        pts[i, 1], pts[j, 1] = pts[j, 1], pts[i, 1]
    from dataclasses import replace

    out = rebuild_box_segments(replace(pslg, points=pts))
    tri = constrained_delaunay(pts, out.segments)
    _check_triangulation(pts, tri, 1.0)
    assert not missing_segments(tri, out.segments, len(pts)).any()
    seg = out.segments
    for s, p in enumerate(out.segment_partner):
        assert np.allclose(np.abs(pts[seg[p]] - pts[seg[s]]).sum(axis=1).max(), 1.0)
