"""Triangle-triangle intersection tests: planted crossings, shared vertices/edges, coplanar overlap."""

import numpy as np
import pytest

from jaxmesh._intersect import candidate_pairs, intersecting_pairs


def _pair(t2_points, shared=()):
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]] + list(t2_points), float)
    t2 = [3, 4, 5][: 3 - len(shared)]
    return p, np.array([[0, 1, 2], list(shared) + t2])


def test_crossing_triangles_detected():
    p, t = _pair([[0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [2.0, 2.0, 0.0]])
    assert intersecting_pairs(p, t).tolist() == [[0, 1]]


def test_separated_triangles_not_detected():
    p, t = _pair([[0.2, 0.2, 0.1], [0.9, 0.2, 0.5], [0.2, 0.9, 0.5]])
    assert len(intersecting_pairs(p, t)) == 0


def test_shared_vertex():
    p, t = _pair([[0.5, 0.5, 1.0], [0.5, -0.5, 1.0]], shared=(0,))  # fan around vertex 0: fine
    assert len(intersecting_pairs(p, t)) == 0
    p, t = _pair([[0.3, 0.3, -1.0], [0.3, 0.3, 1.0]], shared=(1,))  # opposite edge pierces triangle 0
    assert intersecting_pairs(p, t).tolist() == [[0, 1]]


def test_shared_edge_fold_and_hinge():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.0], [0, -1, 0]])
    assert intersecting_pairs(p, np.array([[0, 1, 2], [1, 0, 3]])).tolist() == [[0, 1]]  # folded onto its neighbour
    assert len(intersecting_pairs(p, np.array([[0, 1, 2], [1, 0, 4]]))) == 0  # flat hinge


def test_coplanar_overlap():
    p, t = _pair([[0.2, 0.2, 0.0], [1.2, 0.2, 0.0], [0.2, 1.2, 0.0]])
    assert intersecting_pairs(p, t).tolist() == [[0, 1]]
    p, t = _pair([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [1.0, 2.0, 0.0]])
    assert len(intersecting_pairs(p, t)) == 0


def _icosphere(level=2):
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
         [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
         [8, 6, 7], [9, 8, 1]]  # fmt: skip
    p, f = np.array(v, float), np.array(f)
    for _ in range(level):
        mid = {}
        out = []
        pts = list(p)
        for a, b, c in f:
            m = []
            for u, w in ((a, b), (b, c), (c, a)):
                k = (min(u, w), max(u, w))
                if k not in mid:
                    mid[k] = len(pts)
                    pts.append((pts[u] + pts[w]) / 2)
                m.append(mid[k])
            out += [[a, m[0], m[2]], [m[0], b, m[1]], [m[2], m[1], c], [m[0], m[1], m[2]]]
        p, f = np.array(pts), np.array(out)
    return p / np.linalg.norm(p, axis=1, keepdims=True), f


def test_closed_sphere_has_none_and_planted_defect_found():
    p, f = _icosphere(2)
    assert len(intersecting_pairs(p, f)) == 0
    q = p.copy()
    q[0] *= -1.5  # pull a vertex through the far side: its fan crosses the sphere
    assert len(intersecting_pairs(q, f)) > 0
    two = np.vstack([p, p + [1.5, 0.013, 0.029]])  # two overlapping spheres (generic position)
    assert len(intersecting_pairs(two, np.vstack([f, f + len(p)]))) > 0


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_broad_phase_matches_brute_force(scale):
    rng = np.random.default_rng(0)
    # graded: a cluster of tiny triangles beside large ones (a box face beside a shallow cap)
    p = np.vstack([rng.random((60, 3)), 0.5 + 0.01 * rng.random((60, 3))]) * scale
    t = np.vstack([rng.integers(0, 60, (40, 3)), rng.integers(60, 120, (80, 3))])
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    lo, hi = p[t].min(1), p[t].max(1)
    brute = [(i, j) for i in range(len(t)) for j in range(i + 1, len(t))
             if np.all(lo[i] <= hi[j]) and np.all(lo[j] <= hi[i])]  # fmt: skip
    assert candidate_pairs(p, t).tolist() == [list(x) for x in brute]


def test_bad_input():
    with pytest.raises(ValueError, match="expected points"):
        intersecting_pairs(np.zeros((3, 2)), np.array([[0, 1, 2]]))
