"""Validator: clean structured meshes pass; every planted defect is caught by its own check."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from jaxmesh._errors import MeshingError
from jaxmesh._mesh import Mesh, facet_table, make_periodic_pairs, structured_mesh
from jaxmesh._periodic import minimum_image
from jaxmesh._validate import CHECKS, validate


class BoxInclusions:
    """Fake microstructure: periodic axis-aligned boxes, exact signed distance (negative inside).

    Box faces on grid lines make the structured meshes conforming: interface vertices have phi = 0.
    """

    def __init__(self, box, centres, halves):
        self.box = tuple(box)
        self.periodic = True
        self.centres = np.asarray(centres, float)
        self.halves = np.asarray(halves, float)
        self.inclusions = [SimpleNamespace(id=k + 1) for k in range(len(centres))]

    def _sdf(self, points):
        out = []
        for c, h in zip(self.centres, self.halves):
            q = np.abs(minimum_image(np.asarray(points, float) - c, np.asarray(self.box))) - h
            out.append(np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0))
        return np.stack(out, axis=-1)

    def phi(self, points):
        return self._sdf(points).min(axis=-1)

    def label(self, points):
        s = self._sdf(points)
        return np.where(s.min(-1) < 0, np.argmin(s, -1) + 1, 0)


class Disc(BoxInclusions):
    """One periodic disc/sphere of radius r at the box centre (not conforming to a grid)."""

    def __init__(self, box, r):
        super().__init__(box, [np.full(len(box), 0.5)], [r])

    def _sdf(self, points):
        d = minimum_image(np.asarray(points, float) - self.centres[0], np.asarray(self.box))
        return (np.linalg.norm(d, axis=-1) - self.halves[0])[:, None]


def _ms(dim):
    """Inclusion 1 in the middle, inclusion 2 around the corner (split over 2^d box corners)."""
    return BoxInclusions((1.0,) * dim, [[0.5] * dim, [0.0] * dim], [0.25, 0.125])


def _labelled(dim, ms=None):
    ms = ms or _ms(dim)
    m = structured_mesh((8,) * dim)
    m.inclusion_id[:] = ms.label(m.points[m.cells].mean(axis=1))
    return m, ms


def _remesh(m, points=None, cells=None, ids=None, **kw):
    """A new Mesh from modified arrays, keeping the original periodic pairs unless overridden."""
    kw.setdefault("periodic_pairs", m.periodic_pairs)
    kw.setdefault("periodic", m.periodic)
    return Mesh(m.points.copy() if points is None else points, m.cells.copy() if cells is None else cells,
                m.inclusion_id.copy() if ids is None else ids, m.box, **kw)


def _failed(rep):
    return set(rep.failed)


def _node(m, coord):
    return int(np.argmin(np.linalg.norm(m.points - np.asarray(coord), axis=1)))


def _inclusion_interior_cell(m, k=1):
    """A cell of inclusion k whose vertices are all strictly inside (no vertex on the interface)."""
    c = m.points[m.cells].mean(axis=1)
    cand = np.flatnonzero(m.inclusion_id == k)
    return int(cand[np.argmin(np.linalg.norm(c[cand] - 0.5, axis=1))])


@pytest.mark.parametrize("dim", [2, 3])
def test_clean_mesh_passes_every_check(dim):
    m, ms = _labelled(dim)
    rep = validate(m, ms)
    assert rep.ok, rep.summary()
    assert list(rep.checks) == list(CHECKS)
    assert not any(c.skipped for c in rep.checks.values())
    # The corner inclusion lies in 2^d pieces of the box, glued into one through the periodic faces.
    assert rep.checks["connectivity"].counts["inclusions"] == 2
    assert rep.checks["interface"].counts["interface_facets"] > 0
    assert rep.checks["interface"].counts["max_abs_phi"] < 1e-12
    json.dumps(rep.to_dict())
    rep.raise_if_invalid()  # no exception


@pytest.mark.parametrize("dim", [2, 3])
def test_flipped_cell_caught_by_orientation_only(dim):
    m, ms = _labelled(dim)
    cells = m.cells.copy()
    cells[5, :2] = cells[5, 1::-1]
    rep = validate(_remesh(m, cells=cells), ms)
    assert _failed(rep) == {"orientation"}
    assert rep.checks["orientation"].counts["inverted"] == 1
    assert rep.checks["orientation"].counts["worst_cell"] == 5


@pytest.mark.parametrize("dim", [2, 3])
def test_cells_of_a_slab_thinner_than_a_millionth_of_their_edges_are_flat(dim):
    """|V| <= 1e-6 l_max^d is flat (a sliver there has dihedral angles near 1e-3 deg): a slab 1e-8
    thick fails the orientation check in every cell and nothing else; one 1e-3 thick passes."""
    slab = structured_mesh((2,) * dim, box=(1.0,) * (dim - 1) + (1e-8,))
    thin = validate(slab)
    assert _failed(thin) == {"orientation"}
    counts = thin.checks["orientation"].counts
    assert counts["inverted"] == 0 and counts["flat"] == slab.n_cells
    assert validate(structured_mesh((2,) * dim, box=(1.0,) * (dim - 1) + (1e-3,))).ok


def test_tangled_mesh_caught_by_orientation_and_volume():
    m, ms = _labelled(2)
    pts = m.points.copy()
    k = _node(m, [0.5, 0.5])
    pts[k] += [0.3, 0.0]  # across its neighbours: cells fold over, sum of signed areas unchanged
    rep = validate(_remesh(m, points=pts), ms)
    assert {"orientation", "volume"} <= _failed(rep)
    assert rep.checks["orientation"].counts["inverted"] > 0


@pytest.mark.parametrize("dim", [2, 3])
def test_deleted_cell_caught_by_volume_and_boundary(dim):
    m, ms = _labelled(dim)
    c = _inclusion_interior_cell(m)
    keep = np.arange(m.n_cells) != c
    rep = validate(_remesh(m, cells=m.cells[keep], ids=m.inclusion_id[keep]), ms)
    assert {"volume", "boundary"} <= _failed(rep)
    assert "orientation" not in _failed(rep) and "manifold" not in _failed(rep)
    assert rep.checks["boundary"].counts["off_box"] == dim + 1


@pytest.mark.parametrize("dim", [2, 3])
def test_duplicated_cell_caught_by_manifold(dim):
    m, ms = _labelled(dim)
    c = _inclusion_interior_cell(m)
    rep = validate(_remesh(m, cells=np.vstack([m.cells, m.cells[c]]), ids=np.append(m.inclusion_id, 1)), ms)
    assert "manifold" in _failed(rep) and "volume" in _failed(rep)
    assert rep.checks["manifold"].counts["non_manifold"] == dim + 1
    assert rep.checks["manifold"].counts["max_cells_per_facet"] == 3
    assert "orientation" not in _failed(rep)


@pytest.mark.parametrize("dim", [2, 3])
def test_node_in_no_cell_caught_by_manifold(dim):
    m, ms = _labelled(dim)
    pts = np.vstack([m.points, m.points[_node(m, [0.375] * dim)]])  # a duplicate that no cell uses
    rep = validate(_remesh(m, points=pts), ms)
    assert _failed(rep) == {"manifold"}
    assert rep.checks["manifold"].counts["unused_nodes"] == 1
    assert rep.checks["manifold"].counts["non_manifold"] == 0


@pytest.mark.parametrize("dim", [2, 3])
def test_boundary_node_moved_off_plane(dim):
    m, ms = _labelled(dim)
    pts = m.points.copy()
    k = _node(m, [0.0] + [0.375] * (dim - 1))  # on x = 0, not on an edge, away from inclusions
    pts[k, 0] = 0.01
    rep = validate(_remesh(m, points=pts), ms)
    assert {"periodic", "boundary"} <= _failed(rep)
    assert "orientation" not in _failed(rep) and "manifold" not in _failed(rep)
    assert rep.checks["periodic"].counts["x_unmatched_nodes"] == 1
    assert rep.checks["periodic"].counts["y_unmatched_facets"] == 0


@pytest.mark.parametrize("dim", [2, 3])
def test_boundary_node_moved_within_plane_caught_by_periodic_only(dim):
    m, ms = _labelled(dim)
    pts = m.points.copy()
    k = _node(m, [0.0] + [0.375] * (dim - 1))
    pts[k, 1] += 0.01  # still on x = 0, so every boundary facet is on the box
    rep = validate(_remesh(m, points=pts), ms)
    assert _failed(rep) == {"periodic"}
    assert rep.checks["periodic"].counts["x_unmatched_facets"] > 0
    assert rep.checks["periodic"].counts["x_pair_disagreements"] > 0


def test_wrong_periodic_pairs_caught():
    m, ms = _labelled(3)
    pairs = {a: p.copy() for a, p in m.periodic_pairs.items()}
    pairs[1][[3, 4], 1] = pairs[1][[4, 3], 1]
    rep = validate(_remesh(m, periodic_pairs=pairs), ms)
    assert _failed(rep) == {"periodic"}
    assert rep.checks["periodic"].counts["y_pair_disagreements"] == 4
    del pairs[2]
    rep = validate(_remesh(m, periodic_pairs=pairs), ms)
    assert rep.checks["periodic"].counts["z_pair_disagreements"] == -1 and not rep.ok


@pytest.mark.parametrize("dim", [2, 3])
def test_relabelled_deep_cell_caught_by_labels(dim):
    m, ms = _labelled(dim)
    ids = m.inclusion_id.copy()
    ids[_inclusion_interior_cell(m)] = 0
    rep = validate(_remesh(m, ids=ids), ms)
    assert "labels" in _failed(rep)
    assert rep.checks["labels"].counts["bad"] == 1
    # The hole's facets are new interfaces, off the level set.
    assert "interface" in _failed(rep)
    assert {"orientation", "volume", "manifold", "boundary", "periodic"}.isdisjoint(_failed(rep))


def test_relabelled_cell_across_interface_caught_by_interface():
    m, ms = _labelled(2)
    c = m.points[m.cells].mean(axis=1)
    # A matrix cell touching inclusion 1 from outside: its centroid is within tolerance of phi = 0.
    outside = np.flatnonzero((m.inclusion_id == 0) & (np.abs(ms.phi(c)) < 0.05) & (np.abs(c[:, 0] - 0.5) < 0.3))
    ids = m.inclusion_id.copy()
    ids[outside[0]] = 1
    rep = validate(_remesh(m, ids=ids), ms)
    assert _failed(rep) == {"interface"}
    assert rep.checks["labels"].counts["tolerated_near_interface"] == 1
    assert rep.checks["interface"].counts["off_level_set"] >= 1


@pytest.mark.parametrize("dim", [2, 3])
def test_inclusion_broken_into_two_ids(dim):
    m, ms = _labelled(dim)
    ids = m.inclusion_id.copy()
    c = m.points[m.cells].mean(axis=1)
    ids[(ids == 1) & (c[:, 0] > 0.5)] = 3
    rep = validate(_remesh(m, ids=ids), ms)
    assert {"connectivity", "labels"} <= _failed(rep)
    assert rep.checks["connectivity"].counts["unknown"] == 1
    assert rep.checks["labels"].counts["unknown_ids"] == 1
    assert "interface" in _failed(rep)  # the cut between 1 and 3 is not on the level set


@pytest.mark.parametrize("dim", [2, 3])
def test_two_inclusions_merged_under_one_id(dim):
    m, ms = _labelled(dim)
    ids = m.inclusion_id.copy()
    ids[ids == 2] = 1
    rep = validate(_remesh(m, ids=ids), ms)
    assert {"connectivity", "labels"} <= _failed(rep)
    assert rep.checks["connectivity"].counts["disconnected"] == 1
    assert rep.checks["connectivity"].counts["missing"] == 1
    assert {"orientation", "volume", "manifold", "boundary", "periodic", "interface"}.isdisjoint(_failed(rep))
    # Without the field, a merge is still visible as one id in two face-connected pieces.
    rep = validate(_remesh(m, ids=ids))
    assert _failed(rep) == {"connectivity"}


@pytest.mark.parametrize("dim", [2, 3])
def test_interface_vertex_moved_off_level_set(dim):
    m, ms = _labelled(dim)
    pts = m.points.copy()
    k = _node(m, [0.25] + [0.5] * (dim - 1))  # on the face x = 0.25 of inclusion 1
    pts[k, 0] += 0.01
    rep = validate(_remesh(m, points=pts), ms)
    assert _failed(rep) == {"interface"}
    assert rep.checks["interface"].counts["off_level_set"] == 1
    assert rep.checks["interface"].counts["max_abs_phi"] == pytest.approx(0.01, rel=1e-9)
    # A looser tolerance accepts it.
    assert validate(_remesh(m, points=pts), ms, interface_tol=0.02).ok


def test_disc_labelled_by_centroid_labels_pass_interface_fails():
    """Labels near a curved interface are tolerated; a staircase mesh is not conforming."""
    ms = Disc((1.0, 1.0), 0.3)
    m, _ = _labelled(2, ms)
    rep = validate(m, ms)
    assert _failed(rep) == {"interface"}
    assert rep.checks["labels"].passed


def test_non_periodic_mesh_skips_periodic_and_does_not_glue():
    m, ms = _labelled(2)
    rep = validate(_remesh(m, periodic=False, periodic_pairs=None), ms)
    assert rep.checks["periodic"].skipped and rep.checks["periodic"].passed
    # Without the torus the corner inclusion is four pieces, each on the box: that is what the box does.
    assert "connectivity" not in _failed(rep)
    # A piece away from the box is still a split inclusion.
    corner = int(np.bincount(m.inclusion_id[m.inclusion_id > 0]).argmax())
    centroids = m.points[m.cells].mean(axis=1)
    off_box = ((m.points[m.cells] > 0) & (m.points[m.cells] < 1)).all(axis=(1, 2))
    inner = np.flatnonzero((m.inclusion_id == 0) & off_box & (np.abs(centroids - 0.5) < 0.4).all(axis=1))
    ids = m.inclusion_id.copy()
    ids[inner[0]] = corner
    rep = validate(_remesh(m, ids=ids, periodic=False, periodic_pairs=None))
    assert "connectivity" in _failed(rep)


def test_skips_without_microstructure_and_report_api():
    m, _ = _labelled(3)
    rep = validate(m)
    assert rep.ok
    assert rep.checks["interface"].skipped and rep.checks["labels"].skipped
    text = rep.summary()
    assert "[SKIP] interface" in text and "[PASS] orientation" in text
    cells = m.cells.copy()
    cells[0, :2] = cells[0, 1::-1]
    bad = validate(_remesh(m, cells=cells))
    assert "[FAIL] orientation" in bad.summary()
    with pytest.raises(MeshingError, match="orientation") as err:
        bad.raise_if_invalid()
    assert err.value.stage == "validate"
    d = bad.to_dict()
    assert d["ok"] is False and d["checks"]["orientation"]["counts"]["inverted"] == 1
    json.dumps(d)


def test_bad_inputs_raise_value_error():
    m, ms = _labelled(2)
    with pytest.raises(ValueError, match="jaxmesh.Mesh"):
        validate(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="box"):
        validate(m, BoxInclusions((2.0, 1.0), [[0.5, 0.5]], [0.25]))
    with pytest.raises(ValueError, match="interface_tol"):
        validate(m, ms, interface_tol=-1.0)


def test_make_periodic_pairs_structured_and_errors():
    m = structured_mesh((4, 3, 2), box=(2.0, 1.5, 1.0))
    pairs = make_periodic_pairs(m.points, m.box)
    assert [len(pairs[a]) for a in range(3)] == [4 * 3, 5 * 3, 5 * 4]
    for a, p in pairs.items():
        shift = np.zeros(3)
        shift[a] = m.box[a]
        np.testing.assert_allclose(m.points[p[:, 1]], m.points[p[:, 0]] + shift, atol=1e-12)
        assert np.all(np.diff(p[:, 0]) > 0)
    pts = m.points.copy()
    pts[_node(m, [2.0, 0.75, 0.5]), 1] += 0.1
    with pytest.raises(ValueError, match="no translated partner"):
        make_periodic_pairs(pts, m.box)
    with pytest.raises(ValueError, match="periodic=False"):
        Mesh(pts, m.cells, m.inclusion_id, m.box)
    assert Mesh(pts, m.cells, m.inclusion_id, m.box, periodic=False).periodic_pairs == {}


def test_facet_table_packed_and_structured_keys_agree():
    m = structured_mesh((3, 3, 3))
    a = facet_table(m.cells, m.n_points, structured=False)
    b = facet_table(m.cells, m.n_points, structured=True)
    np.testing.assert_array_equal(a.facets, b.facets)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.cell_facet, b.cell_facet)
    # Euler-type count for the box: boundary facets = 6 faces * 9 squares * 2 triangles.
    assert np.sum(a.counts == 1) == 108 and set(np.unique(a.counts)) == {1, 2}
    two, owners = a.pairs()
    assert np.all(owners[:, 0] != owners[:, 1]) and len(two) == np.sum(a.counts == 2)
