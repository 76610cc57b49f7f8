"""Pure JAX kernels of the truss analogy: bar energy, target lengths, reactions, ball-vertex springs.

Forces are never written by hand: each mechanism is an energy and the nodal forces are
``-jax.grad`` of it, so the same code serves the Euler steps and differentiation.
Paper: section 3.2 (eq. 8-10), 4.4 (eq. 21, alpha ramp), 4.7 (ball-vertex springs).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "safe_norm",
    "bar_lengths",
    "bar_force",
    "bar_energy",
    "truss_energy",
    "truss_forces",
    "size_at",
    "target_lengths",
    "alpha_schedule",
    "phi_and_grad",
    "surface_reaction_energy",
    "tet_quality",
    "ball_vertex_energy",
]


def safe_norm(x: Float[Array, "... d"], axis: int = -1) -> Float[Array, "..."]:
    """Euclidean norm with a finite (zero) gradient at the origin (double-where trick)."""
    sq = jnp.sum(x * x, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def bar_lengths(points: Float[Array, "n d"], bars: Int[Array, "m 2"]) -> Float[Array, " m"]:
    """Current bar lengths |p[j] - p[i]| (safe sqrt: finite gradients for zero-length bars)."""
    return safe_norm(points[bars[:, 1]] - points[bars[:, 0]])


def bar_force(l, l0, alpha=1.0, *, cutoff: bool = False):
    """Closed-form scalar bar force f(l, l0) = k (alpha l0 - l), k = (l + l0) / (2 l0) (eq. 9, 21).

    Positive = repulsive (the bar pushes its nodes apart). With ``cutoff`` the force is zero
    for l > alpha l0 (the purely repulsive field of eq. 8). Broadcasts over arrays.
    """
    f = (l + l0) / (2.0 * l0) * (alpha * l0 - l)
    return jnp.where(l > alpha * l0, 0.0, f) if cutoff else f


def bar_energy(l, l0, alpha=1.0, *, cutoff: bool = False):
    """Energy of one bar, the antiderivative with E'(l) = -f(l, l0), E(0) = 0.

    E(l) = -alpha l0 l / 2 - (alpha - 1) l^2 / 4 + l^3 / (6 l0). With ``cutoff`` the energy is
    frozen at its value at l = alpha l0 beyond it, so that the force vanishes there (eq. 8).

    Args:
        l: bar lengths, any shape. l0: target lengths (> 0), broadcastable. alpha: ramp factor.
        cutoff: repulsive-only variant.

    Returns:
        energies with the broadcast shape of the inputs.
    """
    if cutoff:
        l = jnp.minimum(l, alpha * l0)
    return -0.5 * alpha * l0 * l - 0.25 * (alpha - 1.0) * l * l + l * l * l / (6.0 * l0)


def truss_energy(
    points: Float[Array, "n d"],
    bars: Int[Array, "m 2"],
    bar_mask: Bool[Array, " m"],
    l0: Float[Array, " m"],
    alpha=1.0,
    *,
    cutoff: bool = False,
) -> Float[Array, ""]:
    """Total energy of the padded truss; padding bars (mask False) contribute exactly 0."""
    l = bar_lengths(points, bars)
    l0 = jnp.where(bar_mask, l0, 1.0)  # keep 1 / l0 finite on padding
    return jnp.sum(jnp.where(bar_mask, bar_energy(l, l0, alpha, cutoff=cutoff), 0.0))


def truss_forces(points, bars, bar_mask, l0, alpha=1.0, *, cutoff: bool = False) -> Float[Array, "n d"]:
    """Nodal bar forces -dE/dp (n, d); l0 is held fixed (it is an argument, not a function of p)."""
    return -jax.grad(truss_energy)(points, bars, bar_mask, l0, alpha, cutoff=cutoff)


def size_at(h_fn: Callable, x: Float[Array, "m d"], h_params: Any = None) -> Float[Array, " m"]:
    """Evaluate a size function: ``h_fn(x)`` or ``h_fn(x, h_params)`` when params are given."""
    h = h_fn(x) if h_params is None else h_fn(x, h_params)
    return jnp.broadcast_to(jnp.asarray(h, dtype=x.dtype), x.shape[:1])


def target_lengths(
    points: Float[Array, "n d"],
    bars: Int[Array, "m 2"],
    bar_mask: Bool[Array, " m"],
    h_fn: Callable,
    h_params: Any = None,
    *,
    fscale=1.2,
    power: int = 2,
) -> tuple[Float[Array, " m"], Float[Array, ""]]:
    """Target lengths l0 = scale * h(midpoint), scaled as in distmesh.

    ``scale = fscale * (sum l^power / sum h^power)^(1/power)`` over the real bars, so that
    sum l0^power = fscale^power * sum l^power: the truss is slightly compressed and pushes
    nodes outwards. ``power`` is the dimension of the mesh (2 triangles, 3 tets).

    Returns:
        (l0 (m,), with 1 on padding bars; scale, a scalar that maps h to lengths).
    """
    mid = 0.5 * (points[bars[:, 0]] + points[bars[:, 1]])
    h = jnp.where(bar_mask, size_at(h_fn, mid, h_params), 1.0)
    l = bar_lengths(points, bars)
    num = jnp.sum(jnp.where(bar_mask, l**power, 0.0))
    den = jnp.sum(jnp.where(bar_mask, h**power, 0.0))
    ok = (num > 0) & (den > 0)  # no real bar (e.g. springs only): fall back to l0 = fscale * h
    scale = fscale * jnp.where(ok, num / jnp.where(ok, den, 1.0), 1.0) ** (1.0 / power)
    return jnp.where(bar_mask, h * scale, 1.0), scale


def alpha_schedule(iteration, ramp_iterations, alpha_start=1e-3):
    """Exponential alpha ramp (eq. 21, Fig. 13): alpha_start at iteration 0, exactly 1 from ramp on.

    alpha(i) = alpha_start ** (1 - i / ramp) for i < ramp, else 1; a ramp <= 0 or
    alpha_start >= 1 gives alpha = 1 throughout. Works on Python numbers and traced arrays.
    """
    ramp = jnp.asarray(ramp_iterations)
    a0 = jnp.asarray(alpha_start)
    a0 = a0 if jnp.issubdtype(a0.dtype, jnp.floating) else a0.astype(jnp.result_type(float))
    a0 = jnp.clip(a0, jnp.finfo(a0.dtype).tiny, 1.0)
    t = jnp.clip(jnp.asarray(iteration) / jnp.maximum(ramp, 1), 0.0, 1.0)
    return jnp.where(ramp > 0, a0 ** (1.0 - t), 1.0)


def phi_and_grad(phi_fn: Callable, points: Float[Array, "n d"], phi_params: Any = None, mask=None):
    """Level-set values and gradients at every point: ((n,), (n, d)).

    ``phi_fn`` maps points (n, d) -> (n,) pointwise (value i depends on point i only), so one
    vector-Jacobian product with ones gives all gradients. With ``mask`` (n,) bool, phi is only
    evaluated at the masked points (the others are replaced by a masked point, and get phi = 0,
    grad = 0), so a level set that is singular away from the surface (the centre of a sphere)
    cannot inject NaN into the forces or their derivatives.
    """
    fn = phi_fn if phi_params is None else (lambda x: phi_fn(x, phi_params))
    x = points
    if mask is not None:
        anchor = points[jnp.argmax(mask)]  # any masked point: phi is regular there
        x = jnp.where(mask[:, None], points, anchor)
    phi, vjp = jax.vjp(lambda y: jnp.reshape(fn(y), points.shape[:1]).astype(points.dtype), x)
    (grad,) = vjp(jnp.ones_like(phi))
    if mask is not None:
        phi, grad = jnp.where(mask, phi, 0.0), jnp.where(mask[:, None], grad, 0.0)
    return phi, grad


def surface_reaction_energy(points, on_surface: Bool[Array, " n"], phi_fn: Callable, phi_params: Any = None):
    """0.5 * sum phi^2 over surface nodes; its negative gradient is the reaction -phi grad phi (eq. 10)."""
    fn = phi_fn if phi_params is None else (lambda x: phi_fn(x, phi_params))
    phi = jnp.reshape(fn(points), points.shape[:1])
    return 0.5 * jnp.sum(jnp.where(on_surface, phi * phi, 0.0))


def _tet_geometry(points, tets):
    """Signed 6*volume (m,), face areas opposite each vertex (m, 4), circumradius (m,)."""
    x = points[tets]  # (m, 4, 3)
    a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    vol6 = jnp.sum(a * jnp.cross(b, c), axis=-1)
    opp = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
    area = jnp.stack(
        [0.5 * safe_norm(jnp.cross(x[:, j] - x[:, i], x[:, k] - x[:, i])) for i, j, k in opp], axis=1
    )
    num = (
        jnp.sum(a * a, -1)[:, None] * jnp.cross(b, c)
        + jnp.sum(b * b, -1)[:, None] * jnp.cross(c, a)
        + jnp.sum(c * c, -1)[:, None] * jnp.cross(a, b)
    )
    den = 2.0 * jnp.abs(vol6)
    r_circ = jnp.where(den > 0, safe_norm(num) / jnp.where(den > 0, den, 1.0), jnp.inf)
    return vol6, area, r_circ


def tet_quality(points: Float[Array, "n 3"], tets: Int[Array, "m 4"]) -> Float[Array, " m"]:
    """Tetrahedron quality q = 3 r_in / r_circ (1 regular, 0 flat), in JAX."""
    vol6, area, r_circ = _tet_geometry(points, tets)
    total = jnp.sum(area, axis=1)
    r_in = 0.5 * jnp.abs(vol6) / jnp.where(total > 0, total, 1.0)
    return 3.0 * r_in / r_circ


def ball_vertex_energy(
    points: Float[Array, "n 3"],
    tets: Int[Array, "m 4"],
    tet_mask: Bool[Array, " m"],
    h,
    *,
    quality_threshold=0.3,
    stiffness=1.0,
) -> Float[Array, ""]:
    """Ball-vertex springs against slivers (section 4.7, Fig. 18).

    In each real tet with quality below ``quality_threshold``, the vertex a closest to its
    opposite face bcd is tied to its normal projection e on that face by a linear spring that
    only pushes (repulsive): E = stiffness/2 * max(0, t - |ae|)^2 with t = sqrt(2/3) h, the
    height of the regular tet of edge h. Its gradient pushes a along the face normal and gives
    the reaction to b, c, d. The choice of tets and of a is piecewise constant (no gradient).

    Args:
        points: (n, 3). tets: (m, 4) int. tet_mask: (m,) bool, False on padding.
        h: target edge length per tet (m,) or a scalar.
        quality_threshold: tets with q = 3 r_in / r_circ below it get a spring.
        stiffness: spring constant.

    Returns:
        scalar energy.
    """
    vol6, area, r_circ = _tet_geometry(points, tets)
    total = jnp.sum(area, axis=1)
    q = 3.0 * 0.5 * jnp.abs(vol6) / jnp.where(total > 0, total, 1.0) / r_circ
    height = jnp.abs(vol6)[:, None] / (2.0 * jnp.where(area > 0, area, 1.0))  # 3V / A per vertex
    pick = jax.lax.stop_gradient(jnp.argmin(height, axis=1))
    dist = jnp.take_along_axis(height, pick[:, None], axis=1)[:, 0]
    target = jnp.sqrt(2.0 / 3.0) * jnp.broadcast_to(h, dist.shape)
    gap = jnp.maximum(target - dist, 0.0)
    active = tet_mask & jax.lax.stop_gradient(q < quality_threshold)
    return 0.5 * stiffness * jnp.sum(jnp.where(active, gap * gap, 0.0))
