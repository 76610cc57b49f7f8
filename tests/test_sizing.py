"""Size function h(x) (paper 4.2): analytic references, brute force, invariants, gradients."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmesh._periodic import minimum_image
from jaxmesh._sizing import (
    SizeField,
    SizeParams,
    box_gaps,
    cellwise_element_count,
    edge_gap_sources,
    interface_edges,
    interface_sources,
    limit_gradient,
    predicted_element_count,
    self_gaps,
    size_function,
    size_sources,
    source_sizes,
)
from jaxmesh._surface import as_size_fn
from jaxmesh.geometry._differential import max_abs_curvature
from jaxmesh.geometry._grid import bspline_coefficients, interpolate_cubic, interpolate_linear
from jaxmesh.geometry._microstructure import Microstructure
from jaxmesh.geometry._shapes import sphere_sdf

G = 0.3


def brute_force(h0, src, box, shape, g, h_max, periodic=True):
    """Reference eq. 20: min over ALL sources (O(grid x sources)); also |x - x_s*| (argmin s*)."""
    axes = [np.arange(n) * (L / n) for n, L in zip(shape, box)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(shape))
    delta = x[:, None, :] - np.asarray(src)[None]
    if periodic:
        delta = minimum_image(delta, np.asarray(box))
    dist = np.linalg.norm(delta, axis=-1)
    cones = np.asarray(h0)[None] + g * dist
    best = np.argmin(cones, axis=1)
    h = np.minimum(cones[np.arange(len(x)), best], h_max)
    return h.reshape(shape), dist[np.arange(len(x)), best].reshape(shape)


def check_tolerance(h, ref, dist, spacing):
    """Documented error of the default stencil (radius 2, seeds within 2 cells): one-sided,
    <= 0.3 g spacing (detour at the seed ring) + 4 % of g |x - x_s| (stencil anisotropy)."""
    err = h - ref
    assert err.min() > -1e-12  # never below the exact min: every path is >= the straight segment
    assert np.all(err <= G * (0.3 * spacing + 0.04 * dist) + 1e-12)
    assert err.mean() <= 0.2 * G * spacing


@pytest.fixture(scope="module")
def two_spheres():
    """Two spheres R = 0.15 on the x axis with a gap d = 0.1 (32^3 grid)."""
    fns = [sphere_sdf(jnp.array([0.3, 0.5, 0.5]), 0.15), sphere_sdf(jnp.array([0.7, 0.5, 0.5]), 0.15)]
    ms = Microstructure.from_functions(fns, (1.0, 1.0, 1.0), (32, 32, 32))
    return ms, size_sources(ms)


@pytest.mark.parametrize(
    "shape, box, periodic",
    [((20, 20, 20), (1.0, 1.0, 1.0), True), ((20, 20, 20), (1.0, 1.0, 1.0), False),
     ((32, 16), (2.0, 1.0), True), ((32, 16), (2.0, 1.0), False)],
)
def test_limit_gradient_matches_brute_force(shape, box, periodic):
    rng = np.random.default_rng(1)
    d = len(shape)
    src = rng.random((60, d)) * np.asarray(box)
    h0 = 0.02 + 0.06 * rng.random(60)
    h = np.asarray(limit_gradient(h0, src, box, shape, G, 0.4, periodic=periodic))
    ref, dist = brute_force(h0, src, box, shape, G, 0.4, periodic)
    check_tolerance(h, ref, dist, box[0] / shape[0])


def test_limit_gradient_dense_sources_tolerance(two_spheres):
    ms, src = two_spheres
    h0 = jnp.full(src.points.shape[0], 0.02)
    h = np.asarray(limit_gradient(h0, src.points, ms.box, ms.grid_shape, G, 1.0))
    ref, dist = brute_force(h0, src.points, ms.box, ms.grid_shape, G, 1.0)
    check_tolerance(h, ref, dist, ms.spacing[0])


def test_limit_gradient_no_sources_and_cap():
    h = limit_gradient(jnp.zeros(0), jnp.zeros((0, 2)), (1.0, 1.0), (16, 16), G, 0.2)
    np.testing.assert_allclose(h, 0.2)
    # one source: the cone, capped at h_max
    h = np.asarray(limit_gradient([0.01], [[0.5, 0.5]], (1.0, 1.0), (16, 16), G, 0.1))
    assert h.max() == pytest.approx(0.1) and h[8, 8] == pytest.approx(0.01)
    assert h[8, 12] == pytest.approx(0.01 + G * 0.25)


def test_capacity_bucket_reuses_compilation():
    from jaxmesh import _sizing

    rng = np.random.default_rng(0)
    limit_gradient(np.full(5, 0.05), rng.random((5, 2)), (1.0, 1.0), (16, 16), G, 0.2)
    before = _sizing._limit_gradient._cache_size()
    limit_gradient(np.full(7, 0.05), rng.random((7, 2)), (1.0, 1.0), (16, 16), 0.25, 0.3)
    assert _sizing._limit_gradient._cache_size() == before


def test_interface_sources_on_circle_periodic():
    n, R = 32, 0.3
    x = np.arange(n) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    # circle centred on a box corner: it crosses all four faces, sources must wrap into [0, 1)
    dx, dy = minimum_image(X - 0.0, 1.0), minimum_image(Y - 0.0, 1.0)
    phi = np.hypot(dx, dy) - R
    labels = np.where(phi < 0, 7, 0)
    pts, ids = interface_sources(phi, (1.0, 1.0), labels=labels)
    pts = np.asarray(pts)
    assert np.all((pts >= 0) & (pts < 1))
    r = np.linalg.norm(minimum_image(pts, np.ones(2)), axis=1)
    np.testing.assert_allclose(r, R, atol=(1 / n) ** 2 / (2 * R))  # linear-interpolation sag
    assert np.all(ids == 7)
    # one source per sign change along each axis (periodic)
    inside = phi < 0
    changes = sum(int(np.sum(inside != np.roll(inside, -1, a))) for a in range(2))
    assert pts.shape[0] == changes
    # a slab whose face x = 0.99 lies on the wrap-around edge (x = 31/32 -> 1 == 0)
    slab = np.abs(minimum_image(X - 0.79, 1.0)) - 0.2
    p_per = np.asarray(interface_sources(slab, (1.0, 1.0))[0])
    p_non = np.asarray(interface_sources(slab, (1.0, 1.0), periodic=False)[0])
    np.testing.assert_allclose(np.sort(np.unique(np.round(p_per[:, 0], 12))), [0.59, 0.99], atol=1e-12)
    # not periodic, the last cell ends at x = L, where phi is the border samples' linear continuation:
    # the face at 0.99 is found there too, not on an edge to x = 0
    np.testing.assert_allclose(np.unique(np.round(p_non[:, 0], 12)), [0.59, 0.99], atol=1e-12)
    slab_low = np.abs(minimum_image(X - 0.6, 1.0)) - 0.2  # faces 0.4 and 0.8, no crossing in the last cell
    p_low = np.asarray(interface_sources(slab_low, (1.0, 1.0), periodic=False)[0])
    np.testing.assert_allclose(np.unique(np.round(p_low[:, 0], 12)), [0.4, 0.8], atol=1e-12)


def test_sphere_curvature_size(two_spheres):
    """Sphere radius R: h_curv = alpha R on its surface."""
    fn = sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.25)
    ms = Microstructure.from_functions([fn], (1.0, 1.0, 1.0), (24, 24, 24))
    alpha = 0.5
    field = size_function(ms, SizeParams(iis=0.3, nb_el=1.0, curv_alpha=alpha, grad=G))
    h0 = np.asarray(field.source_h0)
    np.testing.assert_allclose(h0, alpha * 0.25, rtol=1e-2)  # sources off the sphere by the sag
    u = np.random.default_rng(0).normal(size=(200, 3))
    on_surface = 0.5 + 0.25 * u / np.linalg.norm(u, axis=1, keepdims=True)
    h = np.asarray(field(on_surface))
    assert np.all(h >= alpha * 0.25 * 0.99) and np.all(h <= alpha * 0.25 + G * ms.spacing[0])


def test_curvature_capped_at_half_a_grid_step_radius():
    """Two overlapping balls sampled on the grid: the crease where they meet is a kink of the field
    whose spline curvature exceeds what the grid resolves; size_sources caps |kappa| at 2 / step
    (radius half a step), so h_curv >= alpha step / 2 there, and leaves the rest as it is."""
    n = 24
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    ball = lambda c, r: np.linalg.norm(X - np.asarray(c), axis=-1) - r  # noqa: E731
    ms = Microstructure.from_levelset(np.minimum(ball((0.38, 0.5, 0.5), 0.18), ball((0.62, 0.5, 0.5), 0.18)))
    src = size_sources(ms)
    raw = np.abs(np.asarray(max_abs_curvature(ms.inclusions[0].phi_fn, jnp.asarray(src.points))))
    step = 1 / n
    assert raw.max() > 2.5 / step  # the cap bites
    assert np.asarray(src.kappa).max() == pytest.approx(2 / step)
    below = raw < 2 / step
    assert below.mean() > 0.9
    np.testing.assert_allclose(np.asarray(src.kappa)[below], raw[below])
    h0 = np.asarray(size_function(ms, SizeParams(iis=0.2, nb_el=1.0, curv_alpha=0.5), sources=src).source_h0)
    assert h0.min() == pytest.approx(0.5 * step / 2)


def _voxel_sphere_distance(n: int, radius: float, quantise: bool = False) -> np.ndarray:
    """A sphere's field as users make it from a voxel image: the signed Euclidean distance transform of
    its voxels (quantise: the exact distance rounded to whole grid steps instead)."""
    from scipy import ndimage

    x = np.arange(n) / n
    r = np.linalg.norm(np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - 0.5, axis=-1)
    if quantise:
        return (np.round((r - radius) * n) + 0.5) / n
    inside = r < radius
    return (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)) / n


@pytest.mark.parametrize("quantise", [False, True], ids=["distance_transform", "quantised"])
def test_curvature_of_a_field_sampled_from_voxels_is_averaged(quantise):
    """The cubic interpolant of a voxel sphere's distance transform (or of a quantised distance) ripples
    at the grid scale: pointwise, half of its interface curves with radii under two steps and the size
    function asked for ~14 times the elements of the smooth sphere (measured at 48^3). Averaged over
    1.5 steps the ripples cancel; a smooth sphere is left pointwise, and forced averaging keeps its
    curvature (constant mean and Gaussian curvatures average to themselves)."""
    n, radius = 32, 0.3
    ms = Microstructure.from_levelset(_voxel_sphere_distance(n, radius, quantise))
    pointwise, auto = size_sources(ms, curvature_average=0.0), size_sources(ms)
    assert pointwise.curvature_averaged == () and auto.curvature_averaged == (1,)
    assert np.median(np.asarray(pointwise.kappa)) > 0.5 * n  # radii under two steps
    assert np.median(np.asarray(auto.kappa)) < 4.0 / radius
    params = SizeParams(iis=0.1)
    counts = [float(size_function(ms, params, sources=src).element_count()) for src in (pointwise, auto)]
    assert counts[1] < counts[0] / 4

    x = np.arange(n) / n
    smooth = Microstructure.from_levelset(
        np.linalg.norm(np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - 0.5, axis=-1) - radius)
    given = size_sources(smooth)
    assert given.curvature_averaged == ()
    np.testing.assert_array_equal(np.asarray(given.kappa), np.asarray(size_sources(smooth, 0.0).kappa))
    np.testing.assert_allclose(np.asarray(size_sources(smooth, 1.5).kappa), 1 / radius, rtol=0.02)


def test_curvature_average_in_2d_and_bad_values():
    """2D: the signed contour curvature is averaged (a circle keeps 1/R); a bad averaging radius is a
    ValueError from size_sources and from MeshConfig."""
    from jaxmesh import MeshConfig

    n, radius = 64, 0.3
    x = np.arange(n) / n
    r = np.linalg.norm(np.stack(np.meshgrid(x, x, indexing="ij"), axis=-1) - 0.5, axis=-1)
    circle = Microstructure.from_levelset(r - radius)
    np.testing.assert_allclose(np.asarray(size_sources(circle, 2.0).kappa), 1 / radius, rtol=0.02)
    for bad in (-1.0, 20.0, True, "1.5"):
        with pytest.raises(ValueError, match="curvature_average: expected None or grid steps"):
            size_sources(circle, bad)
        with pytest.raises(ValueError, match="MeshConfig.curv_average: expected None or grid steps"):
            MeshConfig(curv_average=bad)


def test_cellwise_element_count_follows_h_inside_the_cells():
    """Smooth h: the node sum (predicted_element_count). One node far finer than its neighbours (a
    gap below the grid step): the node sum counts that h over a whole cell, orders of magnitude too
    many; the cellwise count follows the multilinear h (checked against 16^3 samples per cell)."""
    from scipy import ndimage

    n, box = 12, (1.0, 1.0, 1.0)
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    smooth = 0.05 + 0.01 * np.sin(2 * np.pi * X[..., 0])
    assert cellwise_element_count(smooth, box) == pytest.approx(float(predicted_element_count(smooth, box)), rel=1e-9)
    d = X - 0.5
    h = 0.001 + 0.3 * np.linalg.norm(d - np.round(d), axis=-1)
    fine = (np.arange(16 * n) + 0.5) / 16  # cell midpoints of a 16x finer grid, in node units
    coords = np.stack(np.meshgrid(fine, fine, fine, indexing="ij")).reshape(3, -1)
    brute = 6 * np.sqrt(2) * np.mean(ndimage.map_coordinates(h, coords, order=1, mode="grid-wrap") ** -3.0)
    node_sum = float(predicted_element_count(h, box))
    assert node_sum > 30 * brute
    assert cellwise_element_count(h, box) == pytest.approx(brute, rel=0.3)


def test_gap_narrowness_size(two_spheres):
    """Two spheres at gap d: h_nar = d / nb_el in the gap, the cone g d / 2 above it mid-gap."""
    ms, src = two_spheres
    d, nb_el = 0.1, 3.0
    field = size_function(ms, SizeParams(iis=0.1, nb_el=nb_el, curv_alpha=0.5, grad=G), sources=src)
    h0 = np.asarray(field.source_h0)
    pts = np.asarray(field.source_points)
    pole = np.argmin(np.linalg.norm(pts - [0.45, 0.5, 0.5], axis=1))
    assert h0[pole] == pytest.approx(d / nb_el, rel=1e-3)
    assert h0.min() == pytest.approx(d / nb_el, rel=1e-3)
    assert float(field(jnp.array([[0.5, 0.5, 0.5]]))[0]) == pytest.approx(d / nb_el + G * d / 2, rel=1e-3)
    # away from the gap the curvature term (alpha R = 0.075) rules
    far = np.argmin(np.linalg.norm(pts - [0.15, 0.5, 0.5], axis=1))
    assert h0[far] == pytest.approx(0.5 * 0.15, rel=2e-2)


def test_a_torus_hole_is_a_narrow_gap_of_its_own_inclusion(two_spheres):
    """DN2 sees other inclusions only; the matrix across a torus hole (2 (R - r) = 0.16, ten grid
    steps) is a gap of the torus itself, so nb_el elements span it there too."""
    R, r, c = 0.2, 0.12, 0.5

    def torus(p):
        ring = jnp.sqrt((p[:, 0] - c) ** 2 + (p[:, 1] - c) ** 2) - R
        return jnp.sqrt(ring**2 + (p[:, 2] - c) ** 2) - r

    ms = Microstructure.from_functions([torus], (1.0, 1.0, 1.0), (64, 64, 64))
    src = size_sources(ms)
    pts = np.asarray(src.points)
    axis_dist, height = np.linalg.norm(pts[:, :2] - c, axis=1), np.abs(pts[:, 2] - c)
    inner = (axis_dist < R - r + 0.01) & (height < 0.02)
    outer = (axis_dist > R + r - 0.01) & (height < 0.02)
    assert inner.sum() > 20 and outer.sum() > 20
    gap = np.asarray(src.dn2)
    np.testing.assert_allclose(gap[inner], 2 * (R - r), atol=1.5 / 64)
    assert (gap[outer] > 0.5).all()  # outwards: no other inclusion, no part of its own
    field = size_function(ms, SizeParams(iis=0.1, nb_el=2.0, curv_alpha=5.0, grad=G), sources=src)  # no curvature
    np.testing.assert_allclose(np.asarray(field.source_h0)[inner], (R - r), atol=1.0 / 64)
    # convex inclusions have no gap of their own
    ms2, src2 = two_spheres
    p2 = np.asarray(src2.points)
    centres = np.array([[0.3, 0.5, 0.5], [0.7, 0.5, 0.5]])[src2.ids - 1]  # the fixture's spheres
    normals = (p2 - centres) / np.linalg.norm(p2 - centres, axis=1, keepdims=True)
    assert np.isinf(self_gaps(p2, src2.ids, normals, np.asarray(ms2.dn1), np.asarray(ms2.nearest_id),
                              ms2.box)).all()


def test_gradient_limited_everywhere_incl_periodic_faces(two_spheres):
    ms, src = two_spheres
    h = np.asarray(size_function(ms, SizeParams(iis=0.1, grad=G), sources=src).values)
    step = ms.spacing[0]
    for axis in range(3):  # np.roll pairs node n-1 with node 0: the periodic faces are included
        slope = np.abs(np.roll(h, -1, axis=axis) - h) / step
        assert slope.max() <= G * (1 + 1e-9)  # shortest paths are g-Lipschitz along the stencil
    for shift in ((-1, -1, -1), (-1, 2, 0), (1, -2, 1)):  # diagonals and a knight move
        diag = np.abs(np.roll(h, shift, axis=(0, 1, 2)) - h) / (step * np.linalg.norm(shift))
        assert diag.max() <= G * (1 + 1e-9)


def test_size_field_interpolation_and_count():
    h = jnp.full((16, 16, 16), 0.05)
    field = SizeField(h, (1.0, 2.0, 1.0))
    assert field.element_count() == pytest.approx(6 * math.sqrt(2) * 2.0 / 0.05**3)
    rng = np.random.default_rng(0)
    vals = jnp.asarray(rng.random((16, 8)) + 0.1)
    f2 = SizeField(vals, (2.0, 1.0))
    pts = jnp.asarray(rng.random((50, 2)) * 3 - 0.5)  # outside the box too: periodic
    np.testing.assert_allclose(f2.h_fn()(pts), interpolate_linear(vals, (2.0, 1.0), pts), atol=1e-14)
    np.testing.assert_allclose(f2(jnp.array([[0.125 * 3, 0.0]])), vals[3, 0], atol=1e-14)
    assert predicted_element_count(vals, (2.0, 1.0)) == pytest.approx(
        4 / math.sqrt(3) * 2.0 * float(jnp.mean(vals**-2))
    )


def _fd(f, x, eps):
    return (f(x + eps) - f(x - eps)) / (2 * eps)


@pytest.fixture(scope="module")
def circles_2d():
    """A 2D RVE where every parameter is active: a big circle (iis), a small one (curvature),
    a close pair (narrowness), matrix far away (h_max)."""
    fns = [sphere_sdf(jnp.array(c), r) for c, r in
           (([0.3, 0.3], 0.2), ([0.75, 0.75], 0.05), ([0.75, 0.25], 0.08), ([0.75, 0.46], 0.08))]
    ms = Microstructure.from_functions(fns, (1.0, 1.0), (48, 48))
    return ms, size_sources(ms)


@pytest.mark.parametrize("name", ["iis", "nb_el", "curv_alpha", "grad", "h_max"])
def test_parameter_gradients_match_finite_differences(circles_2d, name):
    ms, src = circles_2d
    base = dict(iis=0.06, nb_el=2.0, curv_alpha=0.5, grad=0.3, h_max=0.12)

    def count(v):
        p = SizeParams(**{**base, name: v})
        return size_function(ms, p, sources=src).element_count()

    x = base[name]
    grad = float(jax.grad(count)(jnp.asarray(x)))
    fd = float(_fd(count, x, 1e-6 * x))
    assert abs(grad) > 1.0  # the parameter is active
    assert grad == pytest.approx(fd, rel=2e-4)


def test_gradient_wrt_level_set_values():
    """Through the source positions (t = phi_a / (phi_a - phi_b)) and the curvature of the
    level set's own interpolant, for a fixed sign pattern."""
    n, box = 32, (1.0, 1.0)
    x = np.arange(n) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    phi0 = jnp.asarray(np.hypot(X - 0.4871, (Y - 0.5213) * 1.3) - 0.2)  # no symmetric ties
    edges = interface_edges(phi0)
    dn2 = jnp.full(edges.a.size, 0.5)

    def count(values):
        pts, ids = interface_sources(values, box, edges=edges)
        kappa = max_abs_curvature(lambda p: interpolate_cubic(bspline_coefficients(values), box, p), pts)
        h0 = source_sizes(pts, ids, dn2, kappa, 0.08, 3.0, 0.5)
        return predicted_element_count(limit_gradient(h0, pts, box, (n, n), G, 0.2), box)

    # a smooth direction: the count is piecewise smooth (paths switch at ties), and a rough one
    # (white noise, whose curvature changes wildly from source to source) puts kinks everywhere
    direction = jnp.asarray(np.cos(2 * np.pi * X) + 0.5 * np.sin(2 * np.pi * (Y + 0.1)) + 0.3)
    grad = jax.grad(count)(phi0)
    directional = float(jnp.sum(grad * direction))
    fd = float(_fd(lambda t: count(phi0 + t * direction), 0.0, 1e-7))
    assert abs(directional) > 10.0
    assert directional == pytest.approx(fd, rel=1e-5)
    assert np.all(np.isfinite(np.asarray(grad)))


def test_source_sizes_formula():
    h0 = source_sizes(np.zeros((4, 3)), np.ones(4), jnp.array([0.3, 0.03, 0.3, 1e-6]),
                      jnp.array([0.0, 0.0, 20.0, 0.0]), 0.05, 3.0, 0.6, h_min=0.001)
    np.testing.assert_allclose(h0, [0.05, 0.01, 0.03, 0.001])


def test_box_gaps_facing_only():
    box = (1.0, 1.0, 1.0)
    points = np.array([
        [0.5, 0.5, 0.004],  # bottom of a sphere 0.004 above z = 0: a thin layer
        [0.5, 0.5, 0.996],  # a cap 0.004 deep cut off at z = L (faces z = L through the wrap)
        [0.5, 0.5, 0.004],  # the same point on a surface crossing z = 0 steeply: no layer
        [0.002, 0.5, 0.002],  # a trace passing 0.0028 from the edge x = z = 0, facing it
        [0.3, 0.5, 0.5],  # far from every plane
    ])
    up, diag = np.array([0.0, 0.0, -1.0]), np.array([-1.0, 0.0, -1.0]) / np.sqrt(2.0)
    normals = np.array([up, -up, [1.0, 0.0, 0.0], diag, [0.0, 0.0, 1.0]])
    gap = box_gaps(points, normals, box)
    np.testing.assert_allclose(gap[:2], 0.004)
    assert gap[2] > 0.2 and gap[4] > 0.2  # only the distant planes x = 0, z = 0 ahead of them
    np.testing.assert_allclose(gap[3], 0.002 * np.sqrt(2.0))
    # 25 degrees off the direction to the plane: beyond the default 20
    tilted = np.array([[np.sin(np.radians(25.0)), 0.0, -np.cos(np.radians(25.0))]])
    assert box_gaps(points[:1], tilted, box)[0] > 0.2
    assert box_gaps(points[:1], tilted, box, max_angle=30.0)[0] == pytest.approx(0.004)


def test_box_gaps_a_trace_faces_by_its_normal_within_its_plane():
    """A sliver the box cuts along the edge y = z = 0: its trace on z = 0 runs 0.004 from the edge
    and its normal points halfway between the planes. Within z = 0 it faces the edge; off the plane
    the same normal faces nothing near."""
    diag = np.array([[0.0, 1.0, 1.0]]) / np.sqrt(2.0)
    on_plane = box_gaps(np.array([[0.5, 0.004, 0.0]]), diag, (1.0, 1.0, 1.0))
    assert on_plane[0] == pytest.approx(0.004)
    assert box_gaps(np.array([[0.5, 0.004, 0.02]]), diag, (1.0, 1.0, 1.0))[0] > 0.2
    # a normal almost across its plane has no direction within it (renormalised, 1e-4 of y would face
    # y = 0): the 3D test decides, and faces nothing near
    across = np.array([[0.0, 1e-4, 1.0]]) / np.hypot(1e-4, 1.0)
    assert box_gaps(np.array([[0.5, 0.004, 0.0]]), across, (1.0, 1.0, 1.0))[0] > 0.2


def test_size_refined_where_a_trace_passes_near_a_box_edge():
    # the sphere crosses x = 0 deeply, and its trace there passes 0.003 above the edge x = z = 0
    centre, radius = np.array([0.03, 0.5, 0.09]), 0.09
    gap = np.linalg.norm(centre[[0, 2]]) - radius
    assert 0.0 < gap < 0.005
    ms = Microstructure.from_functions([sphere_sdf(jnp.asarray(centre), radius)], (1.0, 1.0, 1.0), (32, 32, 32))
    src = size_sources(ms)
    field = size_function(ms, SizeParams(), sources=src)
    near_edge = np.asarray(field(jnp.array([[0.0, 0.5, 0.0]])))[0]
    far_side = np.asarray(field(jnp.asarray(centre + [0.0, 0.0, radius])[None]))[0]
    assert near_edge < 0.4 * far_side
    assert (src.box_gap < 0.01).any() and np.all(src.box_gap >= (1 / 32) / 6 - 1e-12)
    assert np.all(src.box_gap <= np.sqrt(3.0))  # finite: jax.grad through box_gap / nb_el stays finite
    without = size_function(ms, SizeParams(), sources=src._replace(box_gap=None))
    assert np.asarray(without(jnp.array([[0.0, 0.5, 0.0]])))[0] > 2.0 * near_edge


def test_bad_inputs(two_spheres):
    ms, _ = two_spheres
    for bad in (dict(iis=-0.1), dict(nb_el=0.0), dict(curv_alpha=float("nan")), dict(grad=50.0),
                dict(iis=0.1, h_max=0.05), dict(iis=0.1, h_min=0.2)):
        with pytest.raises(ValueError, match="expected"):
            SizeParams(**bad)
    with pytest.raises(ValueError, match="smallest box length"):
        size_function(ms, SizeParams(iis=2.0))
    with pytest.raises(ValueError, match="1e-4"):
        size_function(ms, SizeParams(iis=1e-6))
    with pytest.raises(ValueError, match="expected sources"):
        limit_gradient(np.ones(3), np.zeros((3, 2)), (1.0, 1.0, 1.0), (8, 8, 8), G, 0.1)
    with pytest.raises(ValueError, match="positive source sizes"):
        limit_gradient(np.zeros(3), np.zeros((3, 3)), (1.0, 1.0, 1.0), (8, 8, 8), G, 0.1)
    with pytest.raises(ValueError, match="2D or 3D"):
        interface_sources(np.zeros(10))
    with pytest.raises(ValueError, match="NaN"):
        interface_sources(np.full((8, 8), np.nan))
    with pytest.raises(ValueError, match="one per source"):
        source_sizes(np.zeros((4, 2)), np.ones(3), np.ones(4), np.ones(4), 0.1, 3.0, 0.5)


def test_edge_gap_sources_find_where_an_inclusion_passes_close_to_a_plain_box_edge():
    """A sphere 0.3 grid steps from the edge x = z = L of a plain box (its distance sampled without
    wrapping): one source on that edge at y = 0.5 with the level set's value there as its gap (at 0.15
    steps the continued field crosses the edge: |phi| there), none on a periodic field or from a sphere
    well clear of the edges; the size function (clamped at the last node, as the mesher takes it on a
    plain box) there comes down to about that gap (it stayed at h_max: no interface source lies in the
    last cell)."""
    n, R = 48, 0.1
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    a = (R + 0.3 / n) / np.sqrt(2)
    centre = np.array([1 - a, 0.5, 1 - a])
    ms = Microstructure.from_levelset(np.linalg.norm(x - centre, axis=-1) - R, periodic=False)
    points, ids, gaps = edge_gap_sources(ms)
    assert len(points) == 1 and ids.tolist() == [1]
    np.testing.assert_allclose(points[0], [1.0, 0.5, 1.0])
    assert 0 < gaps[0] < 0.5 / n and gaps[0] == pytest.approx(float(ms.phi(points)[0]))
    h = float(as_size_fn(size_function(ms), ms.box, periodic=False)(jnp.asarray(points))[0])  # as the mesher sees it
    assert h < 2 * gaps[0] + 0.5 / n
    a = (R + 0.15 / n) / np.sqrt(2)  # continued beyond the last sample, the field crosses the edge by a sliver
    sliver = Microstructure.from_levelset(np.linalg.norm(x - [1 - a, 0.5, 1 - a], axis=-1) - R, periodic=False)
    points, _, gaps = edge_gap_sources(sliver)
    assert len(points) == 1 and -0.5 / n < float(sliver.phi(points)[0]) < 0
    assert gaps[0] == pytest.approx(-float(sliver.phi(points)[0]))
    clear = Microstructure.from_levelset(np.linalg.norm(x - 0.5, axis=-1) - 0.2, periodic=False)
    assert len(edge_gap_sources(clear)[0]) == 0
    d = x - centre
    wrapped = Microstructure.from_levelset(np.linalg.norm(d - np.round(d), axis=-1) - R)
    assert len(edge_gap_sources(wrapped)[0]) == 0
