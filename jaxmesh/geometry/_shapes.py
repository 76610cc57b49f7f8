"""Analytic signed-distance functions of spheres and ellipsoids (2D and 3D), in JAX.

The callables returned here are pure and differentiable with respect to the query points and
to the shape parameters (center, radius, axes, rotation), so they can be jitted, vmapped and
used as `phi_fns` of `Microstructure.from_functions`. Convention: negative inside.

The ellipsoid distance is exact: the closest surface point is found from the 1-D
Lagrange-multiplier equation, solved per point with `optimistix.Newton` (vmapped); gradients
through the root use the implicit-function theorem (optimistix's `ImplicitAdjoint`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._generate import unit_ball_volume

__all__ = ["ellipsoid_sdf", "ellipsoid_volume", "sphere_sdf", "sphere_volume"]

SDFFn = Callable[[Float[ArrayLike, "... d"]], Float[Array, "..."]]


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_vector(name: str, value, dim: int | None = None) -> int:
    shape = np.shape(value)
    if len(shape) != 1 or shape[0] not in (2, 3):
        raise ValueError(
            f"{name}: expected a vector of shape (2,) or (3,), got shape {shape}. "
            "Hint: one coordinate per axis of the 2D or 3D box."
        )
    if dim is not None and shape[0] != dim:
        raise ValueError(
            f"{name}: expected shape ({dim},) to match the center, got {shape}. "
            "Hint: center, axes and rotation must have the same dimension."
        )
    if _is_concrete(value) and not np.all(np.isfinite(np.asarray(value, dtype=float))):
        raise ValueError(f"{name}: expected finite values, got {np.asarray(value)}.")
    return shape[0]


def _check_positive(name: str, value) -> None:
    if _is_concrete(value):
        v = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(
                f"{name}: expected strictly positive finite values, got {v}. "
                "Hint: radii and semi-axes are lengths, e.g. 0.1 in a unit box."
            )


def _as_points(x, dim: int, name: str) -> tuple[Array, tuple[int, ...]]:
    x = jnp.asarray(x)
    if x.ndim < 1 or x.shape[-1] != dim:
        raise ValueError(f"{name}: expected points (..., {dim}), got shape {x.shape}.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x.reshape(-1, dim), x.shape[:-1]


def _safe_norm(v: Array) -> Array:
    """Euclidean norm over the last axis whose gradient stays finite at 0."""
    sq = jnp.sum(v * v, axis=-1)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _sphere_phi(center, radius, x):
    pts, lead = _as_points(x, center.shape[0], "sphere_sdf")
    return (_safe_norm(pts - center.astype(pts.dtype)) - radius).reshape(lead)


def sphere_sdf(center: Float[ArrayLike, " d"], radius: float | Float[ArrayLike, ""]) -> SDFFn:
    """Exact signed distance to a sphere (3D) or circle (2D), negative inside.

    Args:
        center: (d,) with d in {2, 3}.
        radius: positive scalar.

    Returns:
        phi_fn mapping points (..., d) to distances (...): a jax.tree_util.Partial, so that
        functions of equal parameter shapes share one compilation under jit.

    Example:
        >>> phi = sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.2)
        >>> phi(jnp.array([[0.5, 0.5, 0.9]]))  # -> [0.2]
    """
    dim = _check_vector("sphere_sdf center", center)
    if np.ndim(radius) != 0:
        raise ValueError(f"sphere_sdf radius: expected a scalar, got shape {np.shape(radius)}.")
    _check_positive("sphere_sdf radius", radius)

    return jax.tree_util.Partial(_sphere_phi, jnp.asarray(center), jnp.asarray(radius))


def _residual(s, args):
    """Lagrange equation sum_i (a_i y_i / (a_i^2 - a_min^2 + s))^2 - 1 in the shifted multiplier s."""
    y, a, off = args
    den = off + s
    r = jnp.where(den > 0, a * y / jnp.where(den > 0, den, 1.0), 0.0)
    return jnp.sum(r * r) - 1.0


def _local_sdf(y: Array, a: Array) -> Array:
    """Signed distance of one local point y (d,) to the axis-aligned ellipsoid with semi-axes a (d,).

    Works in units of a_max so that tolerances are scale free. The multiplier t of the closest point
    p_i = a_i^2 y_i / (a_i^2 + t) is shifted to s = t + a_min^2 > 0 so that the term of the smallest
    axis, a_k y_k / s, keeps full relative precision near the medial plane.
    """
    scale = jnp.max(a)
    y = y / scale
    a = a / scale
    a2 = a * a
    a2min = jnp.min(a2)
    is_min = a2 <= a2min * (1.0 + 1e-12)
    off = jnp.where(is_min, 0.0, a2 - a2min)
    off_safe = jnp.where(is_min, 1.0, off)

    # Degenerate (medial) case: y has no component on the smallest axes and the point is deep
    # inside, so no root s > 0 exists; the closest point lies off the symmetry plane.
    ymin_zero = jnp.all(jnp.where(is_min, y == 0, True))
    q = jnp.where(is_min, 0.0, a * y / off_safe)
    f_rest = jnp.sum(q * q) - 1.0
    deg = ymin_zero & (f_rest < 0)

    y_d = jnp.where(deg, y, 0.0)  # the centre is always a valid degenerate input
    qd = jnp.where(is_min, 0.0, a * y_d / off_safe)
    gap_d = jnp.where(is_min, 0.0, y_d * a2min / off_safe)  # y_i - p_i on the other axes
    dist2_d = jnp.sum(gap_d * gap_d) + a2min * (1.0 - jnp.sum(qd * qd))
    sdf_deg = -jnp.sqrt(jnp.where(deg, dist2_d, 1.0))

    # Regular case: Newton on the convex, decreasing residual from a start left of the root
    # (each term equals 1 at s = a_i|y_i| - off_i), so the iterates rise monotonically.
    y_n = jnp.where(deg, a, y)  # a harmless non-degenerate stand-in where deg holds
    tiny = jnp.finfo(y.dtype).tiny ** 0.5
    s0 = jnp.maximum(jnp.max(a * jnp.abs(y_n) - off), tiny)
    s0 = jax.lax.stop_gradient(s0)
    eps = float(jnp.finfo(y.dtype).eps)
    solver = optx.Newton(rtol=64 * eps, atol=64 * eps)
    sol = optx.root_find(
        _residual,
        solver,
        s0,
        args=(y_n, a, off),
        options={"lower": s0},
        max_steps=64,
        throw=False,
    )
    s = sol.value
    den = off + s
    n = jnp.where(den > 0, y_n / jnp.where(den > 0, den, 1.0), 0.0)
    sdf_reg = (s - a2min) * _safe_norm(n)
    return scale * jnp.where(deg, sdf_deg, sdf_reg)


def _ellipsoid_phi(center, axes, rotation, x):
    pts, lead = _as_points(x, center.shape[0], "ellipsoid_sdf")
    local = (pts - center.astype(pts.dtype)) @ rotation.astype(pts.dtype)  # y_j = R[:, j] . (x - c)
    return jax.vmap(_local_sdf, in_axes=(0, None))(local, axes.astype(pts.dtype)).reshape(lead)


def ellipsoid_sdf(
    center: Float[ArrayLike, " d"],
    axes: Float[ArrayLike, " d"],
    rotation: Float[ArrayLike, "d d"] | None = None,
) -> SDFFn:
    """Exact signed distance to an ellipsoid (3D) or ellipse (2D), negative inside.

    The closest surface point p of a local point y (principal frame) is p_i = a_i^2 y_i / (a_i^2 + t)
    with t the largest root of sum_i (a_i y_i / (a_i^2 + t))^2 = 1, solved by a vmapped
    `optimistix.Newton`; the medial case (point inside on the plane of the smallest axis, where
    no such root exists) is handled in closed form. The gradient is finite everywhere except on
    the medial axis (the segment / disk inside where the closest point is not unique).

    Args:
        center: (d,) with d in {2, 3}.
        axes: (d,) positive semi-axes a_i.
        rotation: (d, d) orthonormal matrix whose columns are the principal directions of
            axes[0], axes[1], ...; identity if None.

    Returns:
        phi_fn mapping points (..., d) to signed distances (...) (a jax.tree_util.Partial).

    Example:
        >>> phi = ellipsoid_sdf(jnp.zeros(2), jnp.array([2.0, 1.0]))
        >>> phi(jnp.array([[3.0, 0.0], [0.0, 0.0]]))  # -> [1.0, -1.0]
    """
    dim = _check_vector("ellipsoid_sdf center", center)
    _check_vector("ellipsoid_sdf axes", axes, dim)
    _check_positive("ellipsoid_sdf axes", axes)
    if rotation is None:
        rotation = np.eye(dim)
    if np.shape(rotation) != (dim, dim):
        raise ValueError(
            f"ellipsoid_sdf rotation: expected shape ({dim}, {dim}), got {np.shape(rotation)}. "
            "Hint: columns are the principal axes; pass None for axis-aligned."
        )
    if _is_concrete(rotation):
        r = np.asarray(rotation, dtype=float)
        if not np.allclose(r.T @ r, np.eye(dim), atol=1e-6):
            raise ValueError(
                "ellipsoid_sdf rotation: expected an orthonormal matrix (R^T R = I), got "
                f"R^T R =\n{r.T @ r}\nHint: orthonormalise it, e.g. with np.linalg.qr."
            )

    return jax.tree_util.Partial(_ellipsoid_phi, jnp.asarray(center), jnp.asarray(axes), jnp.asarray(rotation))


def centre_and_spread(fn) -> tuple[Array, Array] | None:
    """(centre (d,), R - r) of a sphere_sdf / ellipsoid_sdf function: the shape lies between the balls
    of radii r and R about the centre (its smallest and largest semi-axes); None for any other
    function. Traced parameters give traced results."""
    if not isinstance(fn, jax.tree_util.Partial) or fn.keywords:
        return None
    if fn.func is _sphere_phi:
        return fn.args[0], jnp.zeros(())
    if fn.func is _ellipsoid_phi:
        return fn.args[0], jnp.max(fn.args[1]) - jnp.min(fn.args[1])
    return None


def with_centre(fn, centre):
    """The sphere_sdf / ellipsoid_sdf function fn moved to centre (same size and orientation); None
    for any other function."""
    if centre_and_spread(fn) is None:
        return None
    return jax.tree_util.Partial(fn.func, jnp.asarray(centre, dtype=fn.args[0].dtype), *fn.args[1:])


def ellipsoid_volume(axes: Float[ArrayLike, " d"]):
    """Volume (3D) or area (2D) of the ellipsoid with semi-axes axes (d,): omega_d * prod(a_i).

    Works on floats, NumPy and JAX arrays (differentiable); returns a scalar of the same kind.
    """
    dim = np.shape(axes)[-1] if np.ndim(axes) else 1
    prod = axes[0]
    for i in range(1, dim):
        prod = prod * axes[i]
    return unit_ball_volume(dim) * prod


def sphere_volume(radius, dim: int = 3):
    """Volume (dim=3) or area (dim=2) of a ball of the given radius: omega_d * r^d."""
    if dim not in (2, 3):
        raise ValueError(f"sphere_volume: expected dim 2 or 3, got {dim}.")
    return unit_ball_volume(dim) * radius**dim
