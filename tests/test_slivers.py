"""Quality optimisation of tet meshes (NumPy only): signed quality, colour classes, smoothing, flips."""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from jaxmesh._quality import cell_quality, signed_volumes
from jaxmesh._slivers import (
    _cavity,
    _circumcentres_p,
    _edges,
    _neighbours,
    _polygon_triangulations,
    colour_classes,
    improve_topology,
    insert_steiner,
    smooth_vertices,
    tet_quality,
)
from jaxmesh._volume_recover import triangle_keys


def _positive(points, cells):
    cells = np.array(cells, dtype=np.int64)
    neg = signed_volumes(points, cells) < 0
    cells[neg, :2] = cells[neg, 1::-1]
    return cells


def _jittered_cube(n=5, amp=0.3, seed=0):
    """Delaunay of a jittered grid in the unit cube; the hull nodes are the fixed ones."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.linspace(0, 1, n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    hull = np.any((g == 0) | (g == 1), axis=1)
    g[~hull] += amp / (n - 1) * rng.uniform(-1, 1, (int((~hull).sum()), 3))
    g[hull] += 0.02 / (n - 1) * rng.uniform(-1, 1, (int(hull.sum()), 3))  # no flat tets on the hull
    cells = _positive(g, Delaunay(g).simplices)
    assert cell_quality(g, cells).min() > 0
    return g, cells, ~hull


def test_tet_quality_is_signed_radius_ratio():
    p, c, _ = _jittered_cube()
    np.testing.assert_allclose(tet_quality(p[c]), cell_quality(p, c), atol=1e-12)
    np.testing.assert_allclose(tet_quality(p[c[:, [1, 0, 2, 3]]]), -cell_quality(p, c), atol=1e-12)
    reg = np.array([[[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]], float)
    assert abs(abs(tet_quality(reg)[0]) - 1.0) < 1e-12


def test_polygon_triangulations_are_catalan():
    for n, count in ((3, 1), (4, 2), (5, 5), (6, 14), (7, 42)):
        t = _polygon_triangulations(n)
        assert t.shape == (count, n - 2, 3)
        # each triangulation covers the polygon's area once: n - 2 distinct triangles using all vertices
        assert all(len({tuple(sorted(x)) for x in tri}) == n - 2 and set(tri.ravel()) == set(range(n)) for tri in t)


def test_colour_classes_are_independent_and_cover():
    p, c, free = _jittered_cube()
    e = _edges(c)
    classes = colour_classes(e, free)
    got = np.concatenate(classes)
    assert np.array_equal(np.sort(got), np.flatnonzero(free))
    for cls in classes:
        inside = np.zeros(len(p), bool)
        inside[cls] = True
        assert not np.any(inside[e[:, 0]] & inside[e[:, 1]])


def test_smooth_vertices_raises_worst_quality_and_keeps_fixed_nodes():
    p, c, free = _jittered_cube(amp=0.6, seed=3)
    q0 = cell_quality(p, c)
    p2, moves = smooth_vertices(p, c, free, sweeps=4)
    q = tet_quality(p2[c])
    movable = free[c].any(axis=1)  # tets of hull nodes only cannot change
    assert moves > 0 and q[movable].min() > q0[movable].min() and q.min() > 0
    assert q.mean() > q0.mean()
    np.testing.assert_array_equal(p2[~free], p[~free])


def _edge_ring(n_ring=4, half=2.0):
    """Tets around the edge p q = (0, 0, +-half) and a unit ring of n_ring points in the plane z = 0:
    with a long edge (half 2) the tets around it are needles and the ring's triangulation is better."""
    ang = 2 * np.pi * np.arange(n_ring) / n_ring
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(n_ring)], 1)
    pts = np.concatenate([[[0, 0, half], [0, 0, -half]], ring])
    cells = [[0, 1, 2 + i, 2 + (i + 1) % n_ring] for i in range(n_ring)]
    return pts, _positive(pts, cells)


def test_edge_removal_replaces_the_ring_and_keeps_the_volume():
    for n_ring in (3, 4, 5, 6, 7):
        pts, cells = _edge_ring(n_ring)
        tets, n = improve_topology(pts, cells, np.zeros(0, np.int64), threshold=0.9, passes=1)
        assert n == 1 and len(tets) == 2 * n_ring - 4  # one edge removal, n tets -> 2 n - 4
        assert tet_quality(pts[tets]).min() > tet_quality(pts[cells]).min()
        assert np.all(signed_volumes(pts, tets) > 0)
        assert abs(signed_volumes(pts, tets).sum() - signed_volumes(pts, cells).sum()) < 1e-12
        assert not ((tets == 0).any(axis=1) & (tets == 1).any(axis=1)).any()  # the edge is gone


def test_improve_topology_flips_unless_a_face_is_protected():
    pts, cells = _edge_ring(4)
    out, n = improve_topology(pts, cells, np.zeros(0, np.int64), threshold=0.9)
    assert n >= 1 and tet_quality(pts[out]).min() > tet_quality(pts[cells]).min()
    assert abs(signed_volumes(pts, out).sum() - signed_volumes(pts, cells).sum()) < 1e-12
    prot = np.unique(triangle_keys(np.array([[0, 1, 2]]), len(pts)))  # a face around the edge
    out, n = improve_topology(pts, cells, prot, threshold=0.9)
    assert n == 0 and np.array_equal(out, cells)


def test_improve_topology_on_a_delaunay_mesh_never_lowers_the_worst_tet():
    p, c, _ = _jittered_cube(amp=0.6, seed=1)
    q0 = tet_quality(p[c])
    out, n = improve_topology(p, c, np.zeros(0, np.int64), threshold=0.5)
    q = tet_quality(p[out])
    assert q.min() >= q0.min() and q.min() > 0
    assert abs(signed_volumes(p, out).sum() - signed_volumes(p, c).sum()) < 1e-12


def _random_delaunay(k=60, seed=0):
    """Delaunay of the 27 nodes of a 3^3 grid on the unit cube and k random inner points: has slivers."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.linspace(0, 1, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = np.concatenate([g, rng.uniform(0.1, 0.9, (k, 3))])
    return pts, _positive(pts, Delaunay(pts).simplices)


def test_insert_steiner_splits_slivers_and_respects_protected_faces():
    pts, cells = _random_delaunay()
    q0 = cell_quality(pts, cells)
    bad = np.flatnonzero(q0 < 0.1)
    assert len(bad)
    p2, c2, added = insert_steiner(pts, cells, np.zeros(0, np.int64), bad)
    assert len(added) and np.array_equal(added, np.arange(len(pts), len(p2)))
    np.testing.assert_array_equal(p2[: len(pts)], pts)
    assert signed_volumes(p2, c2).min() > 0 and abs(signed_volumes(p2, c2).sum() - 1.0) < 1e-12
    assert (cell_quality(p2, c2) < 0.1).sum() < len(bad)
    # with every face of the bad tets protected no cavity may open them: nothing changes
    faces = cells[bad][:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3)
    p3, c3, added3 = insert_steiner(pts, cells, np.unique(triangle_keys(faces, len(pts))), bad)
    assert not len(added3) and np.array_equal(c3, cells) and len(p3) == len(pts)


def test_a_steiner_cavity_is_the_connected_set_of_tets_whose_circumsphere_holds_the_point():
    pts, cells = _random_delaunay(k=60, seed=4)
    n = len(pts)
    rng = np.random.default_rng(1)
    protected = np.unique(triangle_keys(cells[rng.choice(len(cells), 15, replace=False)][:, [1, 2, 3]], n))
    across = _neighbours(cells, protected, n)
    centres = _circumcentres_p(pts[cells])
    radius2 = np.sum((pts[cells[:, 0]] - centres) ** 2, axis=1)
    face_keys = triangle_keys(cells[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), n).reshape(-1, 4)
    member = np.zeros(len(cells), bool)
    for seed in range(0, len(cells), 7):
        x = centres[across[seed][across[seed] >= 0][0]] if (across[seed] >= 0).any() else pts[cells[seed]].mean(0)
        holds = np.sum((x - centres) ** 2, axis=1) < radius2 * (1 - 1e-12)
        # the reference: a flood fill over shared faces that are not protected
        reach, todo = {seed}, [seed]
        while todo:
            t = todo.pop()
            for key in face_keys[t]:
                if np.isin(key, protected):
                    continue
                for nb in np.flatnonzero((face_keys == key).any(axis=1)):
                    if nb not in reach and holds[nb]:
                        reach.add(int(nb))
                        todo.append(int(nb))
        dead = np.zeros(len(cells), bool)
        assert sorted(_cavity(across, centres, radius2, dead, seed, x, member).tolist()) == sorted(reach)
        assert not member.any()  # the scratch flags are left clear
        if len(reach) > 1:
            dead[max(reach - {seed})] = True
            assert _cavity(across, centres, radius2, dead, seed, x, member) is None and not member.any()
