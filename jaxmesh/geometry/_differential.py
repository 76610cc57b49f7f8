"""Differential geometry of level sets by autodiff: gradients, Hessians, normals, curvatures.

Every function takes any JAX level-set callable ``phi_fn(points (m, d)) -> (m,)`` (a grid
interpolant from :func:`jaxmesh.geometry._grid.grid_phi_fn` or an analytic JAX function) and
differentiates a scalar version of it point by point (vmap of grad). The curvature formulas hold
for a general level set, not only a signed distance (|grad phi| = 1): Goldman, "Curvature
formulas for implicit curves and surfaces", CAGD 22 (2005).

Sign convention: phi is negative inside, so a convex inclusion has POSITIVE curvature (sphere of
radius R: mean = k1 = k2 = 1/R, gaussian = 1/R^2; circle: 1/R).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

PhiFn = Callable[[Array], Array]


def _check_points(points, dims: tuple[int, ...] | None = None) -> Array:
    points = jnp.asarray(points)
    if points.ndim != 2 or (dims is not None and points.shape[-1] not in dims):
        want = "(m, d)" if dims is None else " or ".join(f"(m, {d})" for d in dims)
        raise ValueError(
            f"expected points of shape {want}, got {points.shape}. "
            "Hint: pass a batch of points, e.g. x[None] for a single point."
        )
    if not jnp.issubdtype(points.dtype, jnp.floating):
        points = points.astype(jnp.result_type(float))
    return points


def _scalar(phi_fn: PhiFn) -> Callable[[Array], Array]:
    """phi at one point (d,) -> () from a batched phi_fn (m, d) -> (m,)."""
    return lambda x: jnp.reshape(phi_fn(x[None, :]), ())


def _grad_and_hessian(phi_fn: PhiFn, points: Array) -> tuple[Array, Array]:
    """(m, d) gradients and (m, d, d) Hessians in one forward-over-reverse pass."""
    grad_fn = jax.grad(_scalar(phi_fn))

    def both(x):
        g = grad_fn(x)
        return g, g

    hess, grad = jax.vmap(jax.jacfwd(both, has_aux=True))(points)
    return grad, hess


# Jitted entry points. Eager autodiff of a 4^3 stencil dispatches hundreds of small ops (seconds on
# the first call); filter_jit compiles once per phi_fn (a closure is static, hashed by identity; a
# PyTree phi_fn such as grid_phi_fn's result is traced, so new grids of one shape reuse the cache).
# Inside an outer jit these simply inline.
@eqx.filter_jit
def _gradient_jit(phi_fn: PhiFn, points: Array) -> Array:
    return jax.vmap(jax.grad(_scalar(phi_fn)))(points)


@eqx.filter_jit
def _hessian_jit(phi_fn: PhiFn, points: Array) -> Array:
    return jax.vmap(jax.hessian(_scalar(phi_fn)))(points)


@eqx.filter_jit
def _curvatures_jit(phi_fn: PhiFn, points: Array) -> "Curvatures":
    grad, hess = _grad_and_hessian(phi_fn, points)
    return curvatures_from_derivatives(grad, hess)


def _safe_where_positive(x: Array) -> tuple[Array, Array]:
    """(x > 0 mask, x with non-positive entries replaced by 1): the double-where trick keeps
    gradients finite where a divisor vanishes."""
    ok = x > 0
    return ok, jnp.where(ok, x, 1.0)


def _safe_sqrt(x: Array) -> Array:
    """sqrt(max(x, 0)) with a finite (zero) gradient at x <= 0."""
    ok, x_safe = _safe_where_positive(x)
    return jnp.where(ok, jnp.sqrt(x_safe), 0.0)


def gradient(phi_fn: PhiFn, points: Float[ArrayLike, "m d"]) -> Float[Array, "m d"]:
    """Gradient of phi at each point, by reverse-mode autodiff.

    Args:
        phi_fn: level-set callable (m, d) -> (m,).
        points: (m, d) points, d = 2 or 3.

    Returns:
        (m, d) gradients.

    Example:
        >>> gradient(lambda p: jnp.linalg.norm(p, axis=-1) - 1.0, jnp.array([[2.0, 0.0]]))  # [[1, 0]]
    """
    points = _check_points(points)
    return _gradient_jit(phi_fn, points)


def hessian(phi_fn: PhiFn, points: Float[ArrayLike, "m d"]) -> Float[Array, "m d d"]:
    """Hessian of phi at each point (forward over reverse autodiff).

    Args:
        phi_fn: level-set callable (m, d) -> (m,).
        points: (m, d) points.

    Returns:
        (m, d, d) symmetric Hessians.
    """
    points = _check_points(points)
    return _hessian_jit(phi_fn, points)


def _normalize(g: Array) -> tuple[Array, Array, Array]:
    """(unit vectors, |g|, mask |g| > 0); zero vector where |g| = 0, finite gradients everywhere."""
    sq = jnp.sum(g * g, axis=-1)
    ok, sq_safe = _safe_where_positive(sq)
    norm = jnp.sqrt(sq_safe)
    unit = jnp.where(ok[..., None], g / norm[..., None], 0.0)
    return unit, jnp.where(ok, norm, 0.0), ok


def unit_normal(phi_fn: PhiFn, points: Float[ArrayLike, "m d"]) -> Float[Array, "m d"]:
    """Outward unit normal grad phi / |grad phi| (points from inside, phi < 0, to outside).

    Safe: where grad phi = 0 the normal is the zero vector, and derivatives stay finite.

    Args:
        phi_fn: level-set callable (m, d) -> (m,).
        points: (m, d) points.

    Returns:
        (m, d) unit normals (or zeros at critical points of phi).
    """
    return _normalize(gradient(phi_fn, points))[0]


class Curvatures(NamedTuple):
    """Curvatures of the level set through each point, each (m,).

    3D: mean = (k1 + k2) / 2, gaussian = k1 k2, k1 >= k2 principal curvatures.
    2D: mean = k1 = curvature of the contour, gaussian = k2 = 0.
    """

    mean: Array
    gaussian: Array
    k1: Array
    k2: Array


def _adjugate_quadratic(hess: Array, g: Array) -> Array:
    """g^T adj(H) g for (m, 3, 3) H: adj(H) has columns r1 x r2, r2 x r0, r0 x r1 (rows r_i)."""
    r0, r1, r2 = hess[:, 0], hess[:, 1], hess[:, 2]
    adj_cols = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-1)
    return jnp.einsum("mi,mij,mj->m", g, adj_cols, g)


def curvatures_from_derivatives(
    grad: Float[Array, "m d"], hess: Float[Array, "m d d"]
) -> Curvatures:
    """Level-set curvatures from the gradient g and Hessian H of phi (Goldman 2005).

    3D: mean = (|g|^2 tr H - g^T H g) / (2 |g|^3), gaussian = g^T adj(H) g / |g|^4,
    k1,2 = mean +- sqrt(max(mean^2 - gaussian, 0)), the root evaluated in the cancellation-free
    form |P H P / |g| - mean P|_F / sqrt(2) (P = I - n n^T), equal in exact arithmetic.
    2D: curvature = (|g|^2 tr H - g^T H g) / |g|^3.
    Where g = 0 the curvature is undefined; zeros are returned there (finite gradients).

    Args:
        grad: (m, d) gradients of phi.
        hess: (m, d, d) Hessians of phi.

    Returns:
        :class:`Curvatures`, each field (m,).
    """
    d = grad.shape[-1]
    if d not in (2, 3) or hess.shape[-2:] != (d, d):
        raise ValueError(
            f"expected grad (m, 2|3) and hess (m, d, d), got {grad.shape} and {hess.shape}. "
            "Hint: curvatures are defined for 2D contours and 3D surfaces."
        )
    g2 = jnp.sum(grad * grad, axis=-1)
    ok, g2_safe = _safe_where_positive(g2)
    gnorm = jnp.sqrt(g2_safe)
    trace = jnp.trace(hess, axis1=-2, axis2=-1)
    ghg = jnp.einsum("mi,mij,mj->m", grad, hess, grad)
    numerator = g2 * trace - ghg
    if d == 2:
        kappa = jnp.where(ok, numerator / (g2_safe * gnorm), 0.0)
        zero = jnp.zeros_like(kappa)
        return Curvatures(mean=kappa, gaussian=zero, k1=kappa, k2=zero)
    mean = jnp.where(ok, numerator / (2.0 * g2_safe * gnorm), 0.0)
    gaussian = jnp.where(ok, _adjugate_quadratic(hess, grad) / (g2_safe * g2_safe), 0.0)
    # sqrt(mean^2 - gaussian) loses half the digits near umbilics (sphere: ~1e-8 error). The same
    # (k1 - k2) / 2 is |D|_F / sqrt(2) for the traceless tangential shape operator
    # D = P H P / |g| - mean P, P = I - n n^T: a sum of squares, exact to rounding.
    n = grad / gnorm[:, None]
    proj = jnp.eye(3, dtype=hess.dtype) - n[:, :, None] * n[:, None, :]
    shape_op = jnp.einsum("mij,mjk,mkl->mil", proj, hess, proj) / gnorm[:, None, None]
    dev = shape_op - mean[:, None, None] * proj
    root = jnp.where(ok, _safe_sqrt(0.5 * jnp.sum(dev * dev, axis=(-2, -1))), 0.0)
    return Curvatures(mean=mean, gaussian=gaussian, k1=mean + root, k2=mean - root)


def curvatures(phi_fn: PhiFn, points: Float[ArrayLike, "m d"]) -> Curvatures:
    """Mean, Gaussian and principal curvatures of the level set of phi through each point.

    Works for any level-set function (|grad phi| need not be 1); paper eq. 14-16 generalised.
    Positive for a convex inclusion with phi negative inside.

    Args:
        phi_fn: level-set callable (m, d) -> (m,).
        points: (m, d) points, d = 2 or 3.

    Returns:
        :class:`Curvatures` (mean, gaussian, k1, k2), each (m,). In 2D mean = k1 = contour
        curvature, gaussian = k2 = 0.

    Example:
        >>> sphere = lambda p: jnp.linalg.norm(p, axis=-1) - 0.5
        >>> curvatures(sphere, jnp.array([[0.5, 0.0, 0.0]])).mean  # [2.0]
    """
    points = _check_points(points, dims=(2, 3))
    return _curvatures_jit(phi_fn, points)


def max_abs_curvature(phi_fn: PhiFn, points: Float[ArrayLike, "m d"]) -> Float[Array, " m"]:
    """max(|k1|, |k2|) at each point: the curvature that sets h_curv = alpha / |kappa|.

    Args:
        phi_fn: level-set callable (m, d) -> (m,).
        points: (m, d) points.

    Returns:
        (m,) non-negative curvature magnitudes.
    """
    c = curvatures(phi_fn, points)
    return jnp.maximum(jnp.abs(c.k1), jnp.abs(c.k2))
