"""Lawson flips of surface triangulations before the volume step."""

import numpy as np
from scipy.spatial import Delaunay

from jaxmesh._face_flips import delaunay_box_faces, lawson_flips


def test_planar_quad_flips_to_the_delaunay_diagonal():
    # a thin rhombus: diagonal 0-2 (long) is not Delaunay, 1-3 is
    pts = np.array([[0.0, 0.0, 0.0], [1.0, -0.2, 0.0], [2.0, 0.0, 0.0], [1.0, 0.2, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    out, flips = lawson_flips(pts, tris, np.zeros(2, int))
    assert flips == 1
    assert {tuple(sorted(t)) for t in out} == {(0, 1, 3), (1, 2, 3)}
    normals = np.cross(pts[out[:, 1]] - pts[out[:, 0]], pts[out[:, 2]] - pts[out[:, 0]])
    assert np.all(normals[:, 2] > 0)  # orientation kept


def test_region_boundary_is_never_flipped():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, -0.2, 0.0], [2.0, 0.0, 0.0], [1.0, 0.2, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    out, flips = lawson_flips(pts, tris, np.array([0, 1]))
    assert flips == 0 and np.array_equal(out, tris)


def test_box_faces_stay_periodic_translates():
    """Flip a spoiled master face; the opposite face must be its exact translate afterwards."""
    from jaxmesh._mesh import structured_mesh
    from jaxmesh._surface_mesh import BOX_FACE, OUTSIDE, SurfaceMesh

    mesh = structured_mesh((4, 4, 4))
    tris = np.concatenate(list(mesh.boundary_facets().values()))
    pts = mesh.points.copy()
    pairs = mesh.periodic_pairs
    rng = np.random.default_rng(0)
    for axis in range(3):
        other = [a for a in range(3) if a != axis]
        inner = (pts[:, axis] == 0) & np.all((pts[:, other] > 0) & (pts[:, other] < 1), axis=1)
        for i in np.nonzero(inner)[0]:  # jitter face-interior nodes in the plane, the same on the partner
            j = pairs[axis][pairs[axis][:, 0] == i, 1][0]
            shift = rng.uniform(-0.09, 0.09, 2)
            pts[i, other] += shift
            pts[j, other] += shift
    surface = SurfaceMesh(pts, tris, np.tile([0, OUTSIDE], (len(tris), 1)), np.full(len(tris), BOX_FACE),
                          np.zeros(len(pts), int), mesh.box, pairs)
    out, flips = delaunay_box_faces(surface)
    assert flips > 0
    for axis in range(3):
        lower = out.triangles[np.all(out.points[out.triangles][:, :, axis] == 0.0, axis=1)]
        upper = out.triangles[np.all(out.points[out.triangles][:, :, axis] == 1.0, axis=1)]
        to_upper = dict(pairs[axis].tolist())
        assert {tuple(sorted(to_upper[v] for v in t)) for t in lower} == {tuple(sorted(t)) for t in upper}
    # every face triangle is now a face of the Delaunay tetrahedralisation of the nodes
    from jaxmesh._volume_recover import missing_triangles

    assert not missing_triangles(out.triangles, Delaunay(out.points).simplices, len(out.points)).any()


def test_an_interface_flip_never_lays_a_triangle_flat_on_a_box_plane():
    """Where an interface grazes x = 0, the Delaunay diagonal of a pair can join three trace nodes.

    Found on a Gaussian excursion set (seed 42): the flipped triangle lay on the box face, which
    held the same triangle, and the labels of the volume step conflicted there.
    """
    from jaxmesh._face_flips import delaunay_interfaces
    from jaxmesh._surface_mesh import INTERFACE, SurfaceMesh

    # edge a-b (b just off the plane) between c and d on the plane: not Delaunay, its flip is c-d
    pts = np.array([[0.0, 0.3, 0.5], [4e-4, 0.7, 0.5], [0.0, 0.5, 0.6], [0.0, 0.5, 0.4]])
    tris = np.array([[0, 1, 2], [1, 0, 3]])
    free, flips = lawson_flips(pts, tris, np.zeros(2, int))
    assert flips == 1  # without the box planes, the flip happens
    assert (pts[free][:, :, 0] == 0.0).all(axis=1).any()
    surface = SurfaceMesh(pts, tris, np.tile([1, 0], (2, 1)), np.full(2, INTERFACE), np.ones(4, int), (1.0, 1.0, 1.0))
    out, flips = delaunay_interfaces(surface)
    assert flips == 0 and np.array_equal(out.triangles, tris)
    # a pair off the planes still flips
    shifted = SurfaceMesh(pts + [0.1, 0.0, 0.0], tris, surface.sides, surface.kind, surface.node_inclusion, surface.box)
    assert delaunay_interfaces(shifted)[1] == 1
