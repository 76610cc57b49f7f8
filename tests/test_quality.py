"""Quality measures: analytic references (regular / Kuhn / corner simplices), invariances, report."""

import json

import numpy as np
import pytest

from jaxmesh._mesh import structured_mesh
from jaxmesh._quality import (FLAT_ANGLE_DEG, FLAT_REL_VOLUME, cell_quality, dihedral_angles, flat_cells, min_angles,
                              quality_report, signed_volumes)

REGULAR_TET = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
CORNER_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
KUHN_TET = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]])
EQUILATERAL = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, np.sqrt(3) / 2]])
ONE_TET = np.array([[0, 1, 2, 3]])
ONE_TRI = np.array([[0, 1, 2]])


def _random_similarity(rng, pts):
    """Rotate, scale and translate points (quality and angles are invariant)."""
    d = pts.shape[1]
    rot, _ = np.linalg.qr(rng.normal(size=(d, d)))
    if np.linalg.det(rot) < 0:
        rot[:, 0] *= -1
    return 3.7 * pts @ rot.T + rng.normal(size=d)


def _circumradius_lstsq(p):
    """Independent reference: solve 2 (p_i - p_0) . c = |p_i|^2 - |p_0|^2 for the circumcentre."""
    a = 2 * (p[1:] - p[0])
    b = np.sum(p[1:] ** 2, 1) - np.sum(p[0] ** 2)
    c = np.linalg.solve(a, b)
    return np.linalg.norm(p[0] - c)


def test_regular_tet_quality_one_and_invariant():
    rng = np.random.default_rng(0)
    assert cell_quality(REGULAR_TET, ONE_TET)[0] == pytest.approx(1.0, abs=1e-14)
    for _ in range(5):
        assert cell_quality(_random_similarity(rng, REGULAR_TET), ONE_TET)[0] == pytest.approx(1.0, abs=1e-12)


def test_equilateral_triangle_quality_one_2d_and_3d():
    assert cell_quality(EQUILATERAL, ONE_TRI)[0] == pytest.approx(1.0, abs=1e-14)
    lifted = np.column_stack([EQUILATERAL, np.zeros(3)]) @ np.linalg.qr(np.arange(9.0).reshape(3, 3) + np.eye(3))[0]
    assert cell_quality(lifted, ONE_TRI)[0] == pytest.approx(1.0, abs=1e-12)


def test_known_qualities_kuhn_tet_and_right_triangle():
    # Kuhn tet: R = sqrt(3)/2 (cube diagonal), V = 1/6, faces 1/2, 1/2, sqrt2/2, sqrt2/2.
    assert cell_quality(KUHN_TET, ONE_TET)[0] == pytest.approx(np.sqrt(3) / (1 + np.sqrt(2)), rel=1e-13)
    right = np.array([[0.0, 0], [1, 0], [0, 1]])
    assert cell_quality(right, ONE_TRI)[0] == pytest.approx(2 * (np.sqrt(2) - 1), rel=1e-13)


def test_quality_matches_independent_radius_ratio():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(40, 4, 3))
    q = cell_quality(pts.reshape(-1, 3), np.arange(160).reshape(40, 4))
    for k in range(40):
        p = pts[k]
        vol = abs(np.linalg.det(p[1:] - p[0])) / 6
        areas = sum(0.5 * np.linalg.norm(np.cross(p[f[1]] - p[f[0]], p[f[2]] - p[f[0]]))
                    for f in ([1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]))
        assert q[k] == pytest.approx(3 * (3 * vol / areas) / _circumradius_lstsq(p), rel=1e-9)
    tri = rng.normal(size=(30, 3, 2))
    qt = cell_quality(tri.reshape(-1, 2), np.arange(90).reshape(30, 3))
    for k in range(30):
        p = tri[k]
        area = 0.5 * abs(np.linalg.det(p[1:] - p[0]))
        perim = sum(np.linalg.norm(p[i] - p[(i + 1) % 3]) for i in range(3))
        assert qt[k] == pytest.approx(2 * (2 * area / perim) / _circumradius_lstsq(p), rel=1e-9)


def test_flat_and_sliver_cells():
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    assert cell_quality(flat, ONE_TET)[0] == 0.0
    sliver = flat + np.array([0, 0, 0, 1e-4])[:, None] * np.array([0, 0, 1])
    assert 0 < cell_quality(sliver, ONE_TET)[0] < 1e-3
    ang = dihedral_angles(sliver, ONE_TET)[0]
    assert ang.min() < 0.1 and ang.max() > 179.9  # the sliver signature
    collinear = np.array([[0.0, 0], [1, 0], [2, 0]])
    assert cell_quality(collinear, ONE_TRI)[0] == 0.0
    assert min_angles(collinear, ONE_TRI)[0] == pytest.approx(0.0, abs=1e-12)


def test_flat_cells_by_volume_or_by_angle():
    """A cap triangle 1e-5 high on a unit base has V / l_max^2 = 5e-6, above the volume bound, but
    angles of 0.001 deg: flat by the angle bound. A needle tet (a 1e-4 base under a unit apex) has
    fair dihedral angles but V / l_max^3 ~ 1e-9: flat by the volume bound. A regular cell is neither."""
    cap = np.array([[0.0, 0], [1, 0], [0.5, 1e-5]])
    flat, rel, angles = flat_cells(cap, ONE_TRI)
    assert flat[0] and rel[0] == pytest.approx(5e-6) and angles[0] < FLAT_ANGLE_DEG and rel[0] > FLAT_REL_VOLUME
    needle = np.array([[0.0, 0, 0], [1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1]])
    flat, rel, angles = flat_cells(needle, ONE_TET)
    assert flat[0] and rel[0] < FLAT_REL_VOLUME and angles[0] > 1.0
    regular = np.array([[0.0, 0], [1, 0], [0.5, 0.5 * np.sqrt(3)]])
    flat, rel, angles = flat_cells(regular, ONE_TRI)
    assert not flat[0] and angles[0] == pytest.approx(60.0)


def test_signed_volumes_sign_and_value():
    assert signed_volumes(CORNER_TET, ONE_TET)[0] == pytest.approx(1 / 6)
    assert signed_volumes(CORNER_TET, np.array([[1, 0, 2, 3]]))[0] == pytest.approx(-1 / 6)
    assert signed_volumes(EQUILATERAL, ONE_TRI)[0] == pytest.approx(np.sqrt(3) / 4)
    assert signed_volumes(EQUILATERAL, np.array([[0, 2, 1]]))[0] == pytest.approx(-np.sqrt(3) / 4)
    for div, box in [((5, 3), (2.0, 0.5)), ((3, 2, 4), (1.0, 2.0, 0.5))]:
        m = structured_mesh(div, box)
        v = signed_volumes(m.points, m.cells)
        assert np.all(v > 0) and v.sum() == pytest.approx(np.prod(box), rel=1e-13)


def test_dihedral_angles_regular_and_corner_tet():
    reg = dihedral_angles(REGULAR_TET, ONE_TET)[0]
    np.testing.assert_allclose(reg, np.degrees(np.arccos(1 / 3)), atol=1e-10)
    assert reg[0] == pytest.approx(70.5288, abs=1e-4)
    corner = dihedral_angles(CORNER_TET, ONE_TET)[0]
    # Edges at the origin (0,1), (0,2), (0,3) meet at right angles; the others at arccos(1/sqrt 3).
    np.testing.assert_allclose(corner[:3], 90.0, atol=1e-10)
    np.testing.assert_allclose(corner[3:], np.degrees(np.arccos(1 / np.sqrt(3))), atol=1e-10)


def test_min_angles():
    assert min_angles(EQUILATERAL, ONE_TRI)[0] == pytest.approx(60.0)
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert min_angles(tri, ONE_TRI)[0] == pytest.approx(45.0)
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(60, 2))
    tris = np.arange(60).reshape(20, 3)
    angles = min_angles(pts, tris)
    assert np.all(angles > 0) and np.all(angles <= 60.0 + 1e-12)


@pytest.mark.parametrize("div", [(6, 6), (3, 3, 3)])
def test_quality_report_json_and_consistent(div):
    m = structured_mesh(div)
    m.inclusion_id[: m.n_cells // 4] = 1
    rep = quality_report(m)
    text = json.dumps(rep)  # must be JSON-serialisable
    assert json.loads(text)["n_cells"] == m.n_cells
    assert sum(rep["hist_counts"]) == m.n_cells
    assert len(rep["hist_edges"]) == len(rep["hist_counts"]) + 1 == 21
    assert rep["cells_per_inclusion"] == {"0": m.n_cells - m.n_cells // 4, "1": m.n_cells // 4}
    assert rep["n_below"] == 0 and rep["frac_below"] == 0.0
    pct = list(rep["q_percentiles"].values())
    assert rep["q_min"] <= pct[0] and pct == sorted(pct) and pct[-1] <= rep["q_max"]
    if len(div) == 3:
        assert rep["q_min"] == pytest.approx(np.sqrt(3) / (1 + np.sqrt(2)))
        assert rep["min_dihedral_deg"] == pytest.approx(45.0) and rep["max_dihedral_deg"] == pytest.approx(90.0)
    else:
        assert rep["min_angle_deg"] == pytest.approx(45.0)


def test_quality_report_counts_bad_cells():
    m = structured_mesh((4, 4))
    # Squash one grid node towards a neighbour: its cells become poor.
    k = 2 * 5 + 2  # node (2, 2)
    m.points[k] = m.points[k] + np.array([0.2, 0.0])
    rep = quality_report(m, bins=10, threshold=0.5)
    q = cell_quality(m.points, m.cells)
    assert rep["n_below"] == int(np.sum(q < 0.5)) > 0
    assert rep["frac_below"] == pytest.approx(np.mean(q < 0.5))
    assert len(rep["hist_counts"]) == 10


def test_quality_report_locates_the_worst_cell():
    """A node pushed towards the plane x = 0 flattens its cells there: the report names the worst one,
    its plane (distance 0: it has a vertex on it) and whether it touches an interface (at x = 2/3 here)."""
    m = structured_mesh((3, 3, 3))
    k = int(np.flatnonzero(np.all(np.isclose(m.points, 1 / 3), axis=1))[0])
    m.points[k, 0] = 0.03
    centroids = m.points[m.cells].mean(axis=1)
    m.inclusion_id[centroids[:, 0] > 2 / 3] = 1
    rep = quality_report(m)
    q = cell_quality(m.points, m.cells)
    worst = rep["worst_cell"]
    assert worst["index"] == int(np.argmin(q)) and worst["q"] == pytest.approx(q.min()) and k in m.cells[worst["index"]]
    assert worst["centroid"] == pytest.approx(centroids[worst["index"]].tolist())
    assert worst["nearest_box_plane"] == {"axis": 0, "at": 0.0, "distance": 0.0}
    assert worst["inclusion_id"] == 0 and worst["on_interface"] is False
    assert rep["n_dihedral_below_10"] == int(np.sum(dihedral_angles(m.points, m.cells).min(axis=1) < 10))
    m.inclusion_id[:] = np.where(centroids[:, 0] < 1 / 3, 1, 0)
    assert quality_report(m)["worst_cell"]["on_interface"] is True


def test_bad_inputs_raise_value_error():
    with pytest.raises(ValueError, match="points"):
        cell_quality(np.zeros((4, 4)), ONE_TET)
    with pytest.raises(ValueError, match="vertex ids"):
        cell_quality(REGULAR_TET, np.array([[0, 1, 2, 7]]))
    with pytest.raises(ValueError, match="integer"):
        signed_volumes(REGULAR_TET, ONE_TET.astype(float))
    with pytest.raises(ValueError, match="tetrahedra"):
        dihedral_angles(REGULAR_TET, ONE_TRI)
    with pytest.raises(ValueError, match="bins"):
        quality_report(structured_mesh((2, 2)), bins=0)
