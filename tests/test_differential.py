"""Differential geometry of level sets: gradients, Hessians, normals, curvatures."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmesh.geometry._differential import (
    Curvatures,
    curvatures,
    curvatures_from_derivatives,
    gradient,
    hessian,
    max_abs_curvature,
    unit_normal,
)
from jaxmesh.geometry._grid import grid_phi_fn, make_levelset_grid


def _sphere_points(m, radius, centre, seed=0):
    d = len(centre)
    v = np.random.default_rng(seed).standard_normal((m, d))
    return np.asarray(centre) + radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def _sphere_sdf(centre, radius):
    c = jnp.asarray(centre)
    return lambda p: jnp.linalg.norm(p - c, axis=-1) - radius


# ---------------------------------------------------------------- analytic references


def test_gradient_and_hessian_of_quadratic_are_exact():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((3, 3))
    a = a + a.T
    b = rng.standard_normal(3)
    phi_fn = lambda p: jnp.einsum("mi,ij,mj->m", p, a, p) + p @ b  # noqa: E731
    points = rng.standard_normal((20, 3))
    np.testing.assert_allclose(gradient(phi_fn, points), points @ (2 * a) + b, atol=1e-13)
    np.testing.assert_allclose(hessian(phi_fn, points), np.broadcast_to(2 * a, (20, 3, 3)), atol=1e-13)


@pytest.mark.parametrize("radius", [0.25, 0.7, 3.0])
def test_exact_sphere_sdf(radius):
    centre = (0.1, -0.2, 0.3)
    phi_fn = _sphere_sdf(centre, radius)
    points = _sphere_points(50, radius, centre)
    c = curvatures(phi_fn, points)
    assert isinstance(c, Curvatures)
    for field in (c.mean, c.k1, c.k2):
        np.testing.assert_allclose(field, 1.0 / radius, rtol=0, atol=1e-10)
    np.testing.assert_allclose(c.gaussian, 1.0 / radius**2, rtol=1e-10)
    np.testing.assert_allclose(max_abs_curvature(phi_fn, points), 1.0 / radius, rtol=1e-10)
    np.testing.assert_allclose(unit_normal(phi_fn, points), (points - centre) / radius, atol=1e-12)
    # off the surface the level set through the point is a sphere of radius |p - c|
    off = _sphere_points(20, 1.7 * radius, centre, seed=1)
    np.testing.assert_allclose(curvatures(phi_fn, off).k2, 1.0 / (1.7 * radius), rtol=1e-10)


def _ellipsoid(a, b, c):
    return lambda p: (p[:, 0] / a) ** 2 + (p[:, 1] / b) ** 2 + (p[:, 2] / c) ** 2 - 1.0


def test_ellipsoid_axis_tips():
    a, b, c = 1.0, 0.6, 0.4
    tips = np.array([[a, 0, 0], [0, b, 0], [0, 0, c], [-a, 0, 0]], dtype=float)
    # principal curvatures at (a,0,0): a/b^2, a/c^2; at (0,b,0): b/a^2, b/c^2; at (0,0,c): c/a^2, c/b^2
    expected = np.array(
        [[a / c**2, a / b**2], [b / c**2, b / a**2], [c / b**2, c / a**2], [a / c**2, a / b**2]]
    )
    curv = curvatures(_ellipsoid(a, b, c), tips)
    np.testing.assert_allclose(curv.k1, expected[:, 0], rtol=1e-8)
    np.testing.assert_allclose(curv.k2, expected[:, 1], rtol=1e-8)
    np.testing.assert_allclose(curv.gaussian, expected[:, 0] * expected[:, 1], rtol=1e-8)
    np.testing.assert_allclose(curv.mean, expected.mean(axis=1), rtol=1e-8)
    np.testing.assert_allclose(max_abs_curvature(_ellipsoid(a, b, c), tips), expected[:, 0], rtol=1e-8)


def test_ellipsoid_general_points_closed_form():
    """Gaussian K = 1/(a b c s)^2 and mean H = (a^2+b^2+c^2-|p|^2)/(2 (abc)^2 s^1.5), s = sum x_i^2/a_i^4."""
    abc = np.array([1.0, 0.6, 0.4])
    points = _sphere_points(40, 1.0, (0.0, 0.0, 0.0), seed=2) * abc  # on the ellipsoid
    s = np.sum(points**2 / abc**4, axis=1)
    prod2 = np.prod(abc) ** 2
    gauss = 1.0 / (prod2 * s**2)
    mean = (np.sum(abc**2) - np.sum(points**2, axis=1)) / (2.0 * prod2 * s**1.5)
    curv = curvatures(_ellipsoid(*abc), points)
    np.testing.assert_allclose(curv.gaussian, gauss, rtol=1e-10)
    np.testing.assert_allclose(curv.mean, mean, rtol=1e-10)
    np.testing.assert_allclose(curv.k1 * curv.k2, gauss, rtol=1e-8)
    assert np.all(curv.k1 >= curv.k2)


def test_saddle_sign_and_values():
    phi_fn = lambda p: p[:, 0] ** 2 - p[:, 1] ** 2 - p[:, 2]  # noqa: E731
    curv = curvatures(phi_fn, np.zeros((1, 3)))
    np.testing.assert_allclose([curv.mean[0], curv.gaussian[0], curv.k1[0], curv.k2[0]], [0, -4, 2, -2], atol=1e-12)
    np.testing.assert_allclose(max_abs_curvature(phi_fn, np.zeros((1, 3))), [2.0], atol=1e-12)


def test_curvature_depends_only_on_the_level_set_and_its_orientation():
    """phi, 3 phi and phi + phi^3 share the zero set: same curvatures there; -phi flips the sign."""
    base = _ellipsoid(1.0, 0.7, 0.5)
    points = _sphere_points(25, 1.0, (0.0, 0.0, 0.0), seed=3) * np.array([1.0, 0.7, 0.5])
    ref = curvatures(base, points)
    for other in (lambda p: 3.0 * base(p), lambda p: base(p) + base(p) ** 3):
        got = curvatures(other, points)
        for r, g in zip(ref, got):
            np.testing.assert_allclose(g, r, rtol=1e-9, atol=1e-12)
    flipped = curvatures(lambda p: -base(p), points)
    np.testing.assert_allclose(flipped.mean, -ref.mean, rtol=1e-10)
    np.testing.assert_allclose(flipped.k1, -ref.k2, rtol=1e-10)
    np.testing.assert_allclose(flipped.gaussian, ref.gaussian, rtol=1e-10)


# ---------------------------------------------------------------- 2D


@pytest.mark.parametrize("kind", ["sdf", "quadratic"])
def test_circle_curvature(kind):
    radius, centre = 0.35, np.array([0.2, -0.1])
    if kind == "sdf":
        phi_fn = _sphere_sdf(centre, radius)
    else:  # |grad phi| = 2 r, not 1: the general formula must still give 1/R
        phi_fn = lambda p: jnp.sum((p - centre) ** 2, axis=-1) - radius**2  # noqa: E731
    points = _sphere_points(30, radius, centre)
    curv = curvatures(phi_fn, points)
    np.testing.assert_allclose(curv.mean, 1.0 / radius, rtol=1e-10)
    np.testing.assert_allclose(curv.k1, 1.0 / radius, rtol=1e-10)
    np.testing.assert_array_equal(curv.gaussian, 0.0)
    np.testing.assert_array_equal(curv.k2, 0.0)
    np.testing.assert_allclose(unit_normal(phi_fn, points), (points - centre) / radius, atol=1e-12)


def test_ellipse_curvature():
    a, b = 0.8, 0.3
    t = np.random.default_rng(4).uniform(0, 2 * np.pi, 40)
    points = np.stack([a * np.cos(t), b * np.sin(t)], axis=1)
    expected = a * b / (a**2 * np.sin(t) ** 2 + b**2 * np.cos(t) ** 2) ** 1.5
    phi_fn = lambda p: (p[:, 0] / a) ** 2 + (p[:, 1] / b) ** 2 - 1.0  # noqa: E731
    np.testing.assert_allclose(curvatures(phi_fn, points).k1, expected, rtol=1e-10)
    tips = np.array([[a, 0.0], [0.0, b]])
    np.testing.assert_allclose(max_abs_curvature(phi_fn, tips), [a / b**2, b / a**2], rtol=1e-10)


# ---------------------------------------------------------------- grids


def test_sampled_sphere_on_48_grid_cubic():
    n, radius, centre = 48, 0.3, np.array([0.5, 0.5, 0.5])
    grid = make_levelset_grid(np.zeros((n, n, n)))
    phi = np.linalg.norm(grid.coordinates() - centre, axis=-1) - radius
    phi_fn = grid_phi_fn(make_levelset_grid(phi))
    points = _sphere_points(200, radius, centre, seed=5)
    normals = np.asarray(unit_normal(phi_fn, points))
    assert np.abs(normals - (points - centre) / radius).max() < 1e-3
    curv = jax.jit(lambda p: curvatures(phi_fn, p))(points)
    for field in (curv.mean, curv.k1, curv.k2):
        assert np.abs(np.asarray(field) * radius - 1.0).max() < 0.03
    assert np.abs(np.asarray(curv.gaussian) * radius**2 - 1.0).max() < 0.05


def test_sampled_circle_crossing_the_periodic_seam():
    """A circle centred on the box corner is cut by all four faces; the wrap keeps it whole."""
    n, radius = 48, 0.3
    grid = make_levelset_grid(np.zeros((n, n)))
    xy = grid.coordinates()
    delta = xy - np.round(xy)  # minimum image to the corner (0, 0)
    phi_fn = grid_phi_fn(make_levelset_grid(np.linalg.norm(delta, axis=-1) - radius))
    points = _sphere_points(100, radius, (0.0, 0.0), seed=6)  # outside [0, 1)^2 for most
    assert np.abs(np.asarray(curvatures(phi_fn, points).k1) * radius - 1.0).max() < 0.03
    normals = np.asarray(unit_normal(phi_fn, points))
    assert np.abs(normals - points / radius).max() < 2e-3


# ---------------------------------------------------------------- robustness and gradients


def test_zero_gradient_is_safe():
    phi_fn = lambda p: jnp.sum(p * p, axis=-1) - 1.0  # noqa: E731  grad = 0 at the origin
    origin = np.zeros((1, 3))
    np.testing.assert_array_equal(unit_normal(phi_fn, origin), 0.0)
    curv = curvatures(phi_fn, origin)
    assert all(np.all(np.isfinite(f)) for f in curv)
    for fn in (lambda p: unit_normal(phi_fn, p).sum(), lambda p: max_abs_curvature(phi_fn, p).sum()):
        g = jax.grad(fn)(jnp.asarray(origin))
        assert np.all(np.isfinite(g))


def test_curvature_gradient_matches_finite_differences():
    phi_fn = _ellipsoid(1.0, 0.6, 0.4)
    points = _sphere_points(8, 1.0, (0.0, 0.0, 0.0), seed=7) * np.array([1.0, 0.6, 0.4]) * 1.1
    f = jax.jit(lambda p: jnp.sum(max_abs_curvature(phi_fn, p) + curvatures(phi_fn, p).gaussian))
    g = np.asarray(jax.grad(f)(jnp.asarray(points)))
    eps = 1e-6
    for i in range(len(points)):
        for a in range(3):
            e = np.zeros_like(points)
            e[i, a] = eps
            fd = (f(points + e) - f(points - e)) / (2 * eps)
            np.testing.assert_allclose(g[i, a], fd, rtol=1e-6, atol=1e-6)


def test_curvature_gradient_wrt_grid_values_is_finite_and_matches_fd():
    n = 16
    grid = make_levelset_grid(np.zeros((n, n)))
    phi0 = np.linalg.norm(grid.coordinates() - 0.5, axis=-1) - 0.3
    points = _sphere_points(10, 0.3, (0.5, 0.5), seed=8)

    @jax.jit
    def loss(values):
        return jnp.sum(curvatures(grid_phi_fn(make_levelset_grid(values)), points).k1)

    g = np.asarray(jax.grad(loss)(jnp.asarray(phi0)))
    assert np.all(np.isfinite(g))
    eps = 1e-6
    for idx in [(8, 3), (3, 8), (13, 8), (8, 8)]:
        e = np.zeros_like(phi0)
        e[idx] = eps
        fd = (loss(phi0 + e) - loss(phi0 - e)) / (2 * eps)
        np.testing.assert_allclose(g[idx], fd, rtol=1e-5, atol=1e-6)


def test_bad_points_raise():
    phi_fn = _sphere_sdf((0.0, 0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="expected points of shape"):
        curvatures(phi_fn, np.zeros(3))
    with pytest.raises(ValueError, match="expected points of shape"):
        curvatures(lambda p: p[:, 0], np.zeros((4, 4)))
    with pytest.raises(ValueError, match="expected points of shape"):
        gradient(phi_fn, np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="expected grad"):
        curvatures_from_derivatives(jnp.zeros((2, 3)), jnp.zeros((2, 2, 2)))
