"""Analytic SDFs: exact distances (analytic points, brute-force surface sampling), |grad| = 1,
parameter gradients vs central finite differences, 2D variants, volumes, bad inputs."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from jaxmesh.geometry._shapes import ellipsoid_sdf, ellipsoid_volume, sphere_sdf, sphere_volume


def _rotation(seed, dim):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(dim, dim)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _ellipsoid_points(axes, n):
    """Dense surface samples (m, d) and their parametrisation in the principal frame."""
    if len(axes) == 2:
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.stack([axes[0] * np.cos(t), axes[1] * np.sin(t)], 1)
    th, ph = np.meshgrid(np.linspace(0, np.pi, n), np.linspace(0, 2 * np.pi, 2 * n), indexing="ij")
    u = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    return u * axes


def _surface(axes, params):
    if len(axes) == 2:
        return axes * np.array([np.cos(params[0]), np.sin(params[0])])
    th, ph = params
    return axes * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _brute_distance(axes, y):
    """Unsigned distance of local point y to the ellipsoid surface: dense samples, then a local polish."""
    pts = _ellipsoid_points(axes, 2000 if len(axes) == 2 else 300)
    k = np.argmin(np.linalg.norm(pts - y, axis=1))
    if len(axes) == 2:
        x0 = [np.arctan2(pts[k, 1] / axes[1], pts[k, 0] / axes[0])]
    else:
        p = pts[k] / axes
        x0 = [np.arccos(np.clip(p[2], -1, 1)), np.arctan2(p[1], p[0])]
    res = minimize(lambda q: np.sum((_surface(axes, q) - y) ** 2), x0, method="Nelder-Mead",
                   options={"xatol": 1e-12, "fatol": 1e-20, "maxiter": 4000})
    return math.sqrt(min(res.fun, np.min(np.sum((pts - y) ** 2, 1))))


# ----------------------------------------------------------------------------------------- sphere


@pytest.mark.parametrize("dim", [2, 3])
def test_sphere_exact_values_and_unit_gradient(dim):
    c = jnp.full(dim, 0.5)
    phi = sphere_sdf(c, 0.2)
    x = jnp.array([[0.5] * dim, [0.5] * (dim - 1) + [0.9], [0.8] + [0.5] * (dim - 1)])
    np.testing.assert_allclose(phi(x), [-0.2, 0.2, 0.1], atol=1e-15)
    pts = jax.random.uniform(jax.random.PRNGKey(0), (200, dim))
    g = jax.jit(jax.vmap(jax.grad(lambda p: phi(p))))(pts)
    np.testing.assert_allclose(jnp.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    assert np.all(np.isfinite(jax.grad(lambda p: phi(p))(c)))  # safe norm at the centre
    assert phi(jnp.zeros((4, 5, dim))).shape == (4, 5)


def test_sphere_parameter_gradients_match_finite_differences():
    x = jnp.array([[0.9, 0.3, 0.1]])

    def f(p):
        return sphere_sdf(p[:3], p[3])(x)[0]

    p = jnp.array([0.4, 0.5, 0.45, 0.2])
    eps = 1e-6
    fd = [(f(p.at[k].add(eps)) - f(p.at[k].add(-eps))) / (2 * eps) for k in range(4)]
    np.testing.assert_allclose(jax.grad(f)(p), fd, atol=1e-8)


# -------------------------------------------------------------------------------------- ellipsoid


def test_ellipsoid_on_axis_and_centre_analytic():
    a = np.array([0.3, 0.2, 0.1])
    phi = ellipsoid_sdf(np.zeros(3), a)
    # outside on an axis: nearest point is the tip; inside on the shortest axis: the short tip
    x = np.array([[0.5, 0, 0], [0, 0.35, 0], [0, 0, -0.4], [0, 0, 0.04], [0, 0, 0]])
    np.testing.assert_allclose(phi(x), [0.2, 0.15, 0.3, -0.06, -0.1], atol=1e-14)
    # inside on the longest axis (medial segment): closed form x_i = a_i^2 y_i / (a_i^2 - a_min^2)
    y = 0.1
    p0 = a[0] ** 2 * y / (a[0] ** 2 - a[2] ** 2)
    expect = -math.sqrt((y - p0) ** 2 + a[2] ** 2 * (1 - (p0 / a[0]) ** 2))
    np.testing.assert_allclose(phi(np.array([[y, 0, 0]])), [expect], atol=1e-14)
    assert abs(-float(phi(np.array([[y, 0, 0]]))[0]) - _brute_distance(a, np.array([y, 0, 0]))) < 1e-8


@pytest.mark.parametrize("dim", [2, 3])
def test_ellipsoid_matches_brute_force_off_axis(dim):
    rng = np.random.default_rng(dim)
    a = np.array([0.4, 0.15]) if dim == 2 else np.array([0.4, 0.25, 0.1])
    rot, c = _rotation(1, dim), rng.uniform(0, 1, dim)
    phi = ellipsoid_sdf(c, a, rot)
    local = np.concatenate([rng.uniform(-0.6, 0.6, (10, dim)), rng.uniform(-1, 1, (6, dim)) * a * 0.9])
    local[-1] = a * np.eye(dim)[0] * 1e-9 + 1e-3 * a  # near the centre
    got = np.asarray(phi(c + local @ rot.T))
    inside = np.sum((local / a) ** 2, 1) < 1
    ref = np.array([_brute_distance(a, y) for y in local]) * np.where(inside, -1, 1)
    np.testing.assert_allclose(got, ref, atol=2e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_ellipsoid_unit_gradient_away_from_medial_axis(dim):
    a = np.array([0.3, 0.12]) if dim == 2 else np.array([0.3, 0.2, 0.12])
    rot, c = _rotation(3, dim), np.full(dim, 0.5)
    phi = ellipsoid_sdf(c, a, rot)
    rng = np.random.default_rng(0)
    local = rng.uniform(-0.5, 0.5, (400, dim))
    local = local[np.abs(local[:, -1]) > 0.02]  # the medial set lies in the plane y_min = 0
    g = jax.jit(jax.vmap(jax.grad(lambda p: phi(p))))(jnp.asarray(c + local @ rot.T))
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-9)
    # on the surface the gradient is the outward normal
    surf = _ellipsoid_points(a, 24)[::7]
    n = surf / a**2
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    gs = jax.jit(jax.vmap(jax.grad(lambda p: phi(p))))(jnp.asarray(c + surf @ rot.T))
    np.testing.assert_allclose(gs, n @ rot.T, atol=1e-9)
    np.testing.assert_allclose(phi(c + surf @ rot.T), 0.0, atol=1e-14)


def test_ellipsoid_degenerate_cases_finite():
    # equal axes = sphere; spheroid with two equal smallest axes on its long axis (medial segment)
    c = jnp.array([0.1, 0.2, 0.3])
    x = jax.random.uniform(jax.random.PRNGKey(1), (50, 3))
    np.testing.assert_allclose(ellipsoid_sdf(c, jnp.full(3, 0.2))(x), sphere_sdf(c, 0.2)(x), atol=1e-14)
    phi = ellipsoid_sdf(jnp.zeros(3), jnp.array([0.3, 0.1, 0.1]))
    pts = jnp.array([[0.05, 0.0, 0.0], [0.0, 0.0, 0.0], [0.29, 0.0, 0.0], [0.05, 1e-12, 0.0], [0.5, 0.0, 0.0]])
    v = phi(pts)
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(jax.jit(jax.vmap(jax.grad(lambda p: phi(p))))(pts)))
    np.testing.assert_allclose(v[0], v[3], atol=1e-10)  # continuous across the medial segment
    np.testing.assert_allclose(v[4], 0.2, atol=1e-14)


def test_ellipsoid_parameter_gradients_match_finite_differences():
    x = jnp.array([[0.8, 0.6, 0.3], [0.5, 0.52, 0.45]])

    def f(p):  # centre, axes, rotation angle about z
        t = p[6]
        rot = jnp.array([[jnp.cos(t), -jnp.sin(t), 0.0], [jnp.sin(t), jnp.cos(t), 0.0], [0.0, 0.0, 1.0]])
        return jnp.sum(ellipsoid_sdf(p[:3], p[3:6], rot)(x) * jnp.array([1.0, 0.7]))

    p = jnp.array([0.5, 0.5, 0.5, 0.3, 0.2, 0.1, 0.4])
    eps = 1e-6
    fj = jax.jit(f)
    fd = [(fj(p.at[k].add(eps)) - fj(p.at[k].add(-eps))) / (2 * eps) for k in range(7)]
    np.testing.assert_allclose(jax.jit(jax.grad(f))(p), fd, atol=1e-7)
    np.testing.assert_allclose(fj(p), f(p), atol=1e-14)


def test_volumes_analytic():
    assert math.isclose(sphere_volume(1.0, 3), 4 * math.pi / 3)
    assert math.isclose(sphere_volume(0.5, 2), math.pi * 0.25)
    assert math.isclose(ellipsoid_volume(np.array([1.0, 2.0, 3.0])), 8 * math.pi)
    assert math.isclose(ellipsoid_volume([0.2, 0.1]), math.pi * 0.02)
    np.testing.assert_allclose(jax.grad(ellipsoid_volume)(jnp.array([1.0, 2.0, 3.0])),
                               4 * math.pi / 3 * np.array([6.0, 3.0, 2.0]))


@pytest.mark.parametrize(
    "call",
    [
        lambda: sphere_sdf(jnp.zeros(3), -0.1),
        lambda: sphere_sdf(jnp.zeros(4), 0.1),
        lambda: sphere_sdf(jnp.zeros(3), jnp.ones(2)),
        lambda: ellipsoid_sdf(jnp.zeros(3), jnp.array([0.1, -0.2, 0.3])),
        lambda: ellipsoid_sdf(jnp.zeros(3), jnp.array([0.1, 0.2])),
        lambda: ellipsoid_sdf(jnp.zeros(2), jnp.ones(2), 2 * jnp.eye(2)),
        lambda: ellipsoid_sdf(jnp.zeros(3), jnp.ones(3), jnp.eye(2)),
        lambda: sphere_sdf(jnp.zeros(3), 0.1)(jnp.zeros((5, 2))),
        lambda: sphere_volume(1.0, 4),
    ],
)
def test_bad_inputs_raise_value_error(call):
    with pytest.raises(ValueError, match="expected"):
        call()
