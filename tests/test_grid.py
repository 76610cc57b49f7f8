"""Level-set grids: periodic linear / cubic B-spline interpolation, validation, derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from jaxmesh.geometry._grid import (
    LevelSetGrid,
    bspline_coefficients,
    grid_phi_fn,
    interpolate,
    interpolate_cubic,
    interpolate_linear,
    make_levelset_grid,
)

# (shape, box) with equal spacing on every axis, including non-cubic boxes
CASES = [
    ((32, 16), (2.0, 1.0)),
    ((8, 12, 16), (0.5, 0.75, 1.0)),
]


def _random_case(shape, box, m=500, seed=0):
    rng = np.random.default_rng(seed)
    values = rng.standard_normal(shape)
    # points well outside the box too: they must wrap
    points = rng.uniform(-1.5, 2.5, (m, len(shape))) * np.asarray(box)
    return values, points


def _grid_coords(points, shape, box):
    """Index coordinates for scipy: x / h along each axis, (d, m)."""
    return (points / (np.asarray(box) / np.asarray(shape))).T


# ---------------------------------------------------------------- analytic references


def _trig(points, box):
    x = 2 * np.pi * np.asarray(points) / np.asarray(box)
    return np.sin(x[..., 0]) * np.cos(x[..., 1]) + 0.3 * np.cos(2 * x[..., 0] + x[..., 1])


@pytest.mark.parametrize("order, rate", [("linear", 4.0), ("cubic", 16.0)])
def test_convergence_on_smooth_periodic_field(order, rate):
    """Interpolation error of a smooth periodic field drops like h^2 (linear) / h^4 (cubic)."""
    box = (2.0, 1.0)
    pts = np.random.default_rng(1).uniform(0, 1, (2000, 2)) * np.asarray(box)
    errors = []
    for n in (16, 32, 64):
        grid = make_levelset_grid(_trig(make_levelset_grid(np.zeros((2 * n, n)), box).coordinates(), box), box)
        errors.append(np.abs(np.asarray(interpolate(grid, pts, order)) - _trig(pts, box)).max())
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all(ratios > 0.75 * rate), (errors, ratios)
    assert errors[-1] < (2e-2 if order == "linear" else 2e-5)


def test_linear_is_exact_on_bilinear_patch():
    """Inside one cell, multilinear interpolation of a bilinear function is exact."""
    box = (1.0, 1.0)
    grid_xy = make_levelset_grid(np.zeros((8, 8)), box).coordinates()
    f = lambda p: 1.0 + 2.0 * p[..., 0] - 3.0 * p[..., 1] + 5.0 * p[..., 0] * p[..., 1]  # noqa: E731
    grid = make_levelset_grid(f(grid_xy), box)
    pts = np.random.default_rng(2).uniform(0.125, 0.875, (300, 2))  # away from the wrap seam
    assert np.allclose(interpolate(grid, pts, "linear"), f(pts), atol=1e-13)


# ---------------------------------------------------------------- scipy cross-checks


@pytest.mark.parametrize("shape, box", CASES)
def test_linear_matches_scipy_grid_wrap(shape, box):
    values, points = _random_case(shape, box)
    ref = map_coordinates(values, _grid_coords(points, shape, box), order=1, mode="grid-wrap")
    got = np.asarray(interpolate_linear(values, box, points))
    assert got.shape == (len(points),)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape, box", CASES)
def test_cubic_matches_scipy_grid_wrap(shape, box):
    values, points = _random_case(shape, box, seed=3)
    ref = map_coordinates(values, _grid_coords(points, shape, box), order=3, mode="grid-wrap")
    grid = make_levelset_grid(values, box)
    np.testing.assert_allclose(interpolate(grid, points, "cubic"), ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(grid_phi_fn(grid)(points), ref, rtol=0, atol=1e-10)
    coeffs = bspline_coefficients(values)
    np.testing.assert_allclose(interpolate_cubic(coeffs, box, points), ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("shape, box", CASES)
def test_prefilter_solves_periodic_kernel(shape, box):
    values, _ = _random_case(shape, box)
    c = np.asarray(bspline_coefficients(values))
    for a in range(values.ndim):  # applying [1, 4, 1] / 6 along every axis gives the samples back
        c = (np.roll(c, 1, axis=a) + 4.0 * c + np.roll(c, -1, axis=a)) / 6.0
    np.testing.assert_allclose(c, values, atol=1e-12)


# ---------------------------------------------------------------- invariants


@pytest.mark.parametrize("shape, box", CASES)
@pytest.mark.parametrize("order", ["linear", "cubic"])
def test_reproduces_samples_at_nodes(shape, box, order):
    values, _ = _random_case(shape, box)
    grid = make_levelset_grid(values, box)
    nodes = grid.coordinates().reshape(-1, grid.dim)
    np.testing.assert_allclose(interpolate(grid, nodes, order), values.reshape(-1), atol=1e-12)


@pytest.mark.parametrize("shape, box", CASES)
@pytest.mark.parametrize("order", ["linear", "cubic"])
def test_periodicity(shape, box, order):
    values, points = _random_case(shape, box, m=200)
    phi_fn = grid_phi_fn(make_levelset_grid(values, box), order)
    base = np.asarray(phi_fn(points))
    for a in range(len(shape)):
        for k in (-2, -1, 1, 3):
            shifted = points.copy()
            shifted[:, a] += k * box[a]
            np.testing.assert_allclose(phi_fn(shifted), base, atol=1e-12)


def test_grid_properties_and_defaults():
    grid = make_levelset_grid(np.zeros((16, 8, 4), dtype=np.int64), box=(4.0, 2.0, 1.0))
    assert grid.dim == 3 and grid.shape == (16, 8, 4) and grid.spacing == (0.25, 0.25, 0.25)
    assert grid.values.dtype == jnp.float64  # tests run with x64
    xyz = grid.coordinates()
    assert xyz.shape == (16, 8, 4, 3)
    np.testing.assert_allclose(xyz[3, 2, 1], [0.75, 0.5, 0.25])
    np.testing.assert_allclose(xyz[-1, -1, -1], [3.75, 1.75, 0.75])  # no duplicated last node
    unit = make_levelset_grid(np.zeros((6, 6)))
    assert unit.box == (1.0, 1.0)
    assert make_levelset_grid(np.zeros((6, 6)), dtype=jnp.float32).values.dtype == jnp.float32


def test_float32_grid_interpolates():
    values, points = _random_case((16, 16), (1.0, 1.0))
    grid = make_levelset_grid(values, dtype=jnp.float32)
    got = interpolate(grid, points.astype(np.float32), "cubic")
    assert got.dtype == jnp.float32
    ref = map_coordinates(values, _grid_coords(points, (16, 16), (1.0, 1.0)), order=3, mode="grid-wrap")
    np.testing.assert_allclose(got, ref, atol=1e-4)


# ---------------------------------------------------------------- jit, vmap, gradients


def test_jit_and_vectorised_over_many_points():
    shape, box = (16, 24, 8), (1.0, 1.5, 0.5)
    values, _ = _random_case(shape, box)
    points = np.random.default_rng(5).uniform(-1, 2, (10_000, 3))
    phi_fn = grid_phi_fn(make_levelset_grid(values, box))
    got = jax.jit(phi_fn)(points)
    assert got.shape == (10_000,)
    ref = map_coordinates(values, _grid_coords(points, shape, box), order=3, mode="grid-wrap")
    np.testing.assert_allclose(got, ref, atol=1e-10)
    # leading batch axes are kept
    assert phi_fn(points.reshape(100, 100, 3)).shape == (100, 100)


def test_phi_fn_is_a_pytree_argument_without_retrace():
    shape, box = (16, 16), (1.0, 1.0)
    points = np.random.default_rng(6).uniform(0, 1, (50, 2))

    @eqx.debug.assert_max_traces(max_traces=1)
    def evaluate(phi_fn, p):
        return phi_fn(p)

    evaluate = jax.jit(evaluate)
    for seed in range(3):  # new grids of one shape reuse the compiled function
        values, _ = _random_case(shape, box, seed=seed)
        phi_fn = grid_phi_fn(make_levelset_grid(values, box))
        np.testing.assert_allclose(evaluate(phi_fn, points), phi_fn(points), atol=1e-13)


@pytest.mark.parametrize("order", ["linear", "cubic"])
def test_grad_wrt_values_matches_finite_differences(order):
    shape, box = (8, 6, 10), (0.8, 0.6, 1.0)
    values, points = _random_case(shape, box, m=20)
    weights = np.random.default_rng(7).standard_normal(len(points))

    @jax.jit
    def loss(vals):
        grid = LevelSetGrid(values=vals, box=box)
        return jnp.sum(weights * interpolate(grid, points, order) ** 2)

    g = np.asarray(jax.grad(loss)(jnp.asarray(values)))
    eps = 1e-6
    rng = np.random.default_rng(8)
    for flat in rng.choice(values.size, 12, replace=False):
        idx = np.unravel_index(flat, shape)
        e = np.zeros(shape)
        e[idx] = eps
        fd = (loss(values + e) - loss(values - e)) / (2 * eps)
        np.testing.assert_allclose(g[idx], fd, rtol=1e-6, atol=1e-8)


def test_grad_through_make_levelset_grid_and_module():
    """make_levelset_grid accepts a tracer; the grid module itself is differentiable."""
    values, points = _random_case((8, 8), (1.0, 1.0), m=10)
    f = lambda v: jnp.sum(interpolate(make_levelset_grid(v), points, "cubic"))  # noqa: E731
    g1 = jax.grad(f)(jnp.asarray(values))
    grid = make_levelset_grid(values)
    g2 = jax.grad(lambda gr: jnp.sum(interpolate(gr, points, "cubic")))(grid).values
    np.testing.assert_allclose(g1, g2, atol=1e-14)
    assert np.all(np.isfinite(g1)) and abs(float(jnp.sum(g1)) - len(points)) < 1e-10  # partition of unity


def test_cubic_point_derivatives_match_finite_differences():
    shape, box = (12, 8, 16), (0.75, 0.5, 1.0)
    values, points = _random_case(shape, box, m=30, seed=9)
    # include points exactly on nodes and on cell faces, where the stencil switches
    nodes = make_levelset_grid(values, box).coordinates().reshape(-1, 3)[::97]
    points = np.concatenate([points, nodes, nodes + [0.5 * 0.0625, 0.0, 0.0]])
    phi_fn = grid_phi_fn(make_levelset_grid(values, box))
    scalar = lambda x: phi_fn(x[None])[0]  # noqa: E731
    grad_fn = jax.jit(jax.vmap(jax.grad(scalar)))
    grads = np.asarray(grad_fn(points))
    hess = np.asarray(jax.jit(jax.vmap(jax.hessian(scalar)))(points))
    assert np.all(np.isfinite(grads)) and np.all(np.isfinite(hess))
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), atol=1e-9)
    # the spline's third derivative jumps at node planes, so the Hessian's central differences
    # carry an O(eps * jump) error there: a small step and a 1e-4 relative tolerance
    eps = 1e-6
    for a in range(3):
        e = np.zeros(3)
        e[a] = eps
        fd = (np.asarray(phi_fn(points + e)) - np.asarray(phi_fn(points - e))) / (2 * eps)
        np.testing.assert_allclose(grads[:, a], fd, rtol=1e-6, atol=1e-5)
        fd_h = (np.asarray(grad_fn(points + e)) - np.asarray(grad_fn(points - e))) / (2 * eps)
        np.testing.assert_allclose(hess[:, :, a], fd_h, rtol=1e-4, atol=1e-3)


def test_linear_point_gradient_is_piecewise_constant_slope():
    values, points = _random_case((16, 16), (1.0, 1.0), m=40, seed=10)
    phi_fn = grid_phi_fn(make_levelset_grid(values), "linear")
    grads = np.asarray(jax.vmap(jax.grad(lambda x: phi_fn(x[None])[0]))(points))
    eps = 1e-7
    for a in range(2):
        e = np.zeros(2)
        e[a] = eps
        fd = (np.asarray(phi_fn(points + e)) - np.asarray(phi_fn(points - e))) / (2 * eps)
        np.testing.assert_allclose(grads[:, a], fd, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "values, box, words",
    [
        (np.full((8, 8), np.nan), None, "finite"),
        (np.array([[0.0, np.inf, 0, 0]] * 4), None, "finite"),
        (np.zeros(16), None, "2D or 3D"),
        (np.zeros((4, 4, 4, 4)), None, "2D or 3D"),
        (np.zeros((0, 8)), None, "non-empty"),
        (np.zeros((8, 3)), (1.0, 0.375), "at least 4"),
        (np.zeros((8, 8)), (1.0, 1.0, 1.0), "box of length 2"),
        (np.zeros((8, 8)), (1.0, -1.0), "positive finite"),
        (np.zeros((8, 8)), (1.0, np.nan), "positive finite"),
        (np.zeros((16, 8)), (1.0, 1.0), "non-cubic spacing mismatch"),
        (np.array([["a"] * 4] * 4), None, "real numeric"),
        (np.zeros((4, 4), dtype=complex), None, "real numeric"),
        ([[1.0, 2.0], [3.0]], None, "numeric array"),
    ],
)
def test_bad_input_raises_value_error(values, box, words):
    with pytest.raises(ValueError, match="expected") as info:
        make_levelset_grid(values, box)
    assert words in str(info.value)
    assert "Hint" in str(info.value) or "hint" in str(info.value)


def test_spacing_mismatch_hint_names_matching_box():
    with pytest.raises(ValueError, match=r"box=\(1\.0, 0\.5\)"):
        make_levelset_grid(np.zeros((32, 16)), (1.0, 1.0))


def test_bad_points_and_order():
    grid = make_levelset_grid(np.zeros((8, 8)))
    with pytest.raises(ValueError, match=r"expected points of shape \(m, 2\)"):
        interpolate(grid, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="expected order"):
        interpolate(grid, np.zeros((5, 2)), order="quintic")
    with pytest.raises(ValueError, match="expected order"):
        grid_phi_fn(grid, order="nearest")
    with pytest.raises(ValueError, match="expected box with 2"):
        interpolate_linear(np.zeros((8, 8)), (1.0,), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="rank 2 or 3"):
        LevelSetGrid(values=jnp.zeros(8), box=(1.0,))
