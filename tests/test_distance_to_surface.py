"""distance_to_surface against brute force on a graded surface (triangles of very different sizes)."""

import numpy as np

from jaxmesh._surface_mesh import BOX_FACE, INTERFACE, SurfaceMesh
from jaxmesh._volume_recover import distance_to_surface, point_triangle_distance


def _graded_surface() -> SurfaceMesh:
    """Two big triangles (a coarse face) and a fan of small ones (a fine patch) near them."""
    big = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    k = 12
    ang = np.linspace(0, 2 * np.pi, k, endpoint=False)
    fan = np.concatenate([[[0.5, 0.5, 0.3]], np.stack([0.5 + 0.02 * np.cos(ang), 0.5 + 0.02 * np.sin(ang),
                                                       np.full(k, 0.3)], 1)])
    points = np.concatenate([big, fan])
    tris = np.concatenate([[[0, 1, 2], [1, 3, 2]], [[4, 5 + i, 5 + (i + 1) % k] for i in range(k)]])
    kind = np.array([BOX_FACE] * 2 + [INTERFACE] * k)
    return SurfaceMesh(points, tris, np.zeros((len(tris), 2)), kind, np.zeros(len(points)), (1.0, 1.0, 1.0))


def test_distance_matches_brute_force_below_radius_and_is_inf_beyond():
    s = _graded_surface()
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(0, 1, (300, 3)), [0.5, 0.5, 0.3] + rng.normal(0, 0.02, (200, 3))])
    radius = rng.uniform(0.001, 0.2, len(pts))
    P = s.points[s.triangles]
    pi, ti = np.repeat(np.arange(len(pts)), len(P)), np.tile(np.arange(len(P)), len(pts))
    brute = point_triangle_distance(pts[pi], P[ti, 0], P[ti, 1], P[ti, 2]).reshape(len(pts), len(P)).min(axis=1)
    expected = np.where(brute < radius, brute, np.inf)
    for chunk, batch in ((8192, 1 << 19), (7, 5)):  # one pass, and many chunks / pair batches
        got = distance_to_surface(pts, s, radius, chunk=chunk, pair_batch=batch)
        np.testing.assert_array_equal(got, expected)
    assert np.isfinite(expected).sum() > 100 and np.isinf(expected).sum() > 50  # both regimes are exercised
