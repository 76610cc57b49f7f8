"""Node constraints of the truss: fixed nodes, box faces/edges/corners, interfaces, periodicity.

Paper section 4.4: surface nodes move tangentially and are pushed back onto phi = 0, box nodes
keep their face coordinate(s), and the nodes of a periodic class receive the average of their
forces so that they move together.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._energy import ball_vertex_energy, phi_and_grad, size_at, target_lengths, truss_energy

__all__ = [
    "NodeConstraints",
    "make_constraints",
    "average_periodic",
    "filter_forces",
    "newton_damping",
    "project_to_surface",
    "impose_periodicity",
    "truss_step",
]


class NodeConstraints(eqx.Module):
    """Per-node constraints, all arrays with shapes fixed by (n, d).

    Attributes:
        fixed: (n,) bool, nodes that never move.
        locked_axes: (n, d) bool, coordinates that never change (box face: 1 axis, edge: 2,
            corner: 3).
        on_surface: (n,) bool, interface nodes: normal motion removed, then projected onto phi = 0.
        periodic_rep: (n,) int, representative of the node's periodic class (itself if unpaired);
            a representative is its own representative.
        periodic_offset: (n, d) float, p[i] == p[periodic_rep[i]] + periodic_offset[i].

    Build it with :func:`make_constraints`, which also spreads the constraints over each periodic
    class (the representative drives the motion of the class).
    """

    fixed: Bool[Array, " n"]
    locked_axes: Bool[Array, "n d"]
    on_surface: Bool[Array, " n"]
    periodic_rep: Int[Array, " n"]
    periodic_offset: Float[Array, "n d"]

    def __check_init__(self):
        n, d = self.locked_axes.shape
        for name, shape in (
            ("fixed", (n,)),
            ("on_surface", (n,)),
            ("periodic_rep", (n,)),
            ("periodic_offset", (n, d)),
        ):
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(
                    f"NodeConstraints.{name}: expected shape {shape} (from locked_axes {(n, d)}), "
                    f"got {got}. Hint: build it with make_constraints(n, d, ...)."
                )

    @property
    def n(self) -> int:
        return self.locked_axes.shape[0]

    @property
    def d(self) -> int:
        return self.locked_axes.shape[1]


def _node_mask(name: str, value, n: int) -> np.ndarray:
    """Accept None, an (n,) bool mask or an array of node indices; return an (n,) bool mask."""
    if value is None:
        return np.zeros(n, dtype=bool)
    v = np.asarray(value)
    if v.dtype == bool:
        if v.shape != (n,):
            raise ValueError(f"{name}: expected a bool mask of shape ({n},), got shape {v.shape}.")
        return v.copy()
    if v.size and (not np.issubdtype(v.dtype, np.integer) or v.ndim != 1 or v.min() < 0 or v.max() >= n):
        raise ValueError(
            f"{name}: expected a bool mask ({n},) or 1-D node indices in [0, {n}), got dtype {v.dtype}, "
            f"shape {v.shape}. Hint: np.flatnonzero(mask) gives indices."
        )
    m = np.zeros(n, dtype=bool)
    m[v.astype(np.int64)] = True
    return m


def _periodic_classes(n: int, d: int, pairs, tol: float):
    """Weighted union-find over (i, j, offset) pairs with p[j] = p[i] + offset."""
    parent = np.arange(n)
    off = np.zeros((n, d))  # p[x] = p[parent[x]] + off[x]

    def find(x):
        path = []
        while parent[x] != x:
            path.append(x)
            x = parent[x]
        acc = np.zeros(d)
        for y in reversed(path):  # compress: every node on the path points at the root
            acc = acc + off[y]
            off[y] = acc.copy()
            parent[y] = x
        return x

    for k, pair in enumerate(pairs):
        if len(pair) != 3:
            raise ValueError(f"periodic_pairs[{k}]: expected (i, j, offset), got {pair!r}.")
        i, j, o = int(pair[0]), int(pair[1]), np.asarray(pair[2], dtype=float).reshape(-1)
        if not (0 <= i < n and 0 <= j < n) or o.shape != (d,) or not np.all(np.isfinite(o)):
            raise ValueError(
                f"periodic_pairs[{k}]: expected node indices in [0, {n}) and a finite offset of length "
                f"{d}, got ({i}, {j}, {o.tolist()}). Hint: offset = p[j] - p[i], e.g. (L, 0)."
            )
        ri, rj = find(i), find(j)
        rel = off[i] + o - off[j]  # p[rj] = p[ri] + rel (a root's own offset is 0)
        if ri == rj:
            if np.max(np.abs(rel)) > tol:
                raise ValueError(
                    f"periodic_pairs[{k}] = ({i}, {j}, {o.tolist()}) contradicts earlier pairs: the class "
                    f"already implies p[{j}] - p[{i}] = {(o - rel).tolist()}. Hint: check the offsets' signs."
                )
            continue
        if ri < rj:  # the smallest index becomes the representative
            parent[rj], off[rj] = ri, rel
        else:
            parent[ri], off[ri] = rj, -rel
    rep = np.array([find(x) for x in range(n)], dtype=np.int64)
    offset = np.where((rep == np.arange(n))[:, None], 0.0, off)
    return rep, offset


def make_constraints(
    n: int,
    d: int,
    *,
    fixed=None,
    locked_axes=None,
    on_surface=None,
    periodic_pairs: Sequence | None = None,
    dtype=None,
) -> NodeConstraints:
    """Build :class:`NodeConstraints` for n nodes in d dimensions.

    Constraints are spread over each periodic class (fixed if any member is fixed, an axis
    locked if locked on any member, on the surface if any member is), because the class moves
    as one body driven by its representative.

    Args:
        n, d: number of nodes and dimension.
        fixed: (n,) bool mask or node indices.
        locked_axes: (n, d) bool.
        on_surface: (n,) bool mask or node indices.
        periodic_pairs: sequence of (i, j, offset) meaning p[j] == p[i] + offset (offset (d,),
            e.g. the box length along one axis); chains and cycles (corners) are allowed and must
            be consistent.
        dtype: float dtype of the offsets (default: JAX's default float).

    Returns:
        NodeConstraints.

    Example:
        >>> c = make_constraints(4, 2, fixed=[0], periodic_pairs=[(1, 2, (1.0, 0.0))])
    """
    if int(n) != n or n < 1 or int(d) != d or d < 1:
        raise ValueError(f"n, d: expected positive integers, got n={n!r}, d={d!r}.")
    n, d = int(n), int(d)
    fx = _node_mask("fixed", fixed, n)
    surf = _node_mask("on_surface", on_surface, n)
    if locked_axes is None:
        lk = np.zeros((n, d), dtype=bool)
    else:
        lk = np.asarray(locked_axes)
        if lk.dtype != bool or lk.shape != (n, d):
            raise ValueError(f"locked_axes: expected a bool array of shape ({n}, {d}), got {lk.dtype} {lk.shape}.")
        lk = lk.copy()
    pairs = list(periodic_pairs) if periodic_pairs is not None else []
    scale = max([1.0] + [float(np.max(np.abs(np.asarray(p[2], dtype=float)))) for p in pairs if len(p) == 3])
    rep, offset = _periodic_classes(n, d, pairs, tol=1e-9 * scale)
    if pairs:  # spread constraints over each class: OR over members, gathered back
        fx_c = np.zeros(n, dtype=bool)
        np.logical_or.at(fx_c, rep, fx)
        surf_c = np.zeros(n, dtype=bool)
        np.logical_or.at(surf_c, rep, surf)
        lk_c = np.zeros((n, d), dtype=bool)
        np.logical_or.at(lk_c, rep, lk)
        fx, surf, lk = fx_c[rep], surf_c[rep], lk_c[rep]
    ftype = jnp.result_type(float) if dtype is None else dtype
    return NodeConstraints(
        fixed=jnp.asarray(fx),
        locked_axes=jnp.asarray(lk),
        on_surface=jnp.asarray(surf),
        periodic_rep=jnp.asarray(rep, dtype=jnp.int32),
        periodic_offset=jnp.asarray(offset, dtype=ftype),
    )


def average_periodic(forces: Float[Array, "n d"], constraints: NodeConstraints) -> Float[Array, "n d"]:
    """Give every node of a periodic class the class-average force (segment_sum over representatives)."""
    n = forces.shape[0]
    rep = constraints.periodic_rep
    total = jax.ops.segment_sum(forces, rep, num_segments=n)
    count = jax.ops.segment_sum(jnp.ones((n,), forces.dtype), rep, num_segments=n)
    return (total / jnp.maximum(count, 1.0)[:, None])[rep]


def _unit_free_normals(normals, locked):
    """Normals with locked components removed, normalised (zero where nothing is left)."""
    g = jnp.where(locked, 0.0, normals)
    sq = jnp.sum(g * g, axis=-1, keepdims=True)
    ok = sq > 0
    return jnp.where(ok, g / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0), sq


def filter_forces(
    forces: Float[Array, "n d"],
    constraints: NodeConstraints,
    normals: Float[Array, "n d"] | None = None,
) -> Float[Array, "n d"]:
    """Remove the force components that the constraints forbid.

    Locked components are zeroed; on surface nodes the component along the surface normal is
    removed within the free (unlocked) subspace, so a surface node on a box plane slides along
    the trace of the surface in that plane; fixed nodes get zero.

    Args:
        forces: (n, d). constraints: NodeConstraints.
        normals: (n, d) level-set gradients (any length) at the nodes; required if any node is
            on a surface.
    """
    f = jnp.where(constraints.locked_axes, 0.0, forces)
    if normals is not None:
        u, _ = _unit_free_normals(normals, constraints.locked_axes)
        tangential = f - jnp.sum(f * u, axis=-1, keepdims=True) * u
        f = jnp.where(constraints.on_surface[:, None], tangential, f)
    return jnp.where(constraints.fixed[:, None], 0.0, f)


def newton_damping(grad: Float[Array, "n d"]) -> Float[Array, " n"]:
    """Factor min(1, 2 |grad phi|) on a Newton step: a distance-like field has |grad| ~ 1, and
    near a saddle of the interpolated field (|grad| -> 0) a full step could jump to a periodic image."""
    return jnp.minimum(1.0, 2.0 * jnp.sqrt(jnp.sum(grad * grad, axis=-1)))


def project_to_surface(
    points: Float[Array, "n d"],
    constraints: NodeConstraints,
    phi_fn: Callable,
    phi_params: Any = None,
    n_newton: int = 2,
) -> Float[Array, "n d"]:
    """Newton steps p -= phi g / |g|^2 on surface nodes (g = grad phi without locked components).

    Nodes that are fixed or not on the surface are returned unchanged; a node whose free
    gradient vanishes (surface tangent to its box plane) is left where it is.
    """
    move = constraints.on_surface & ~constraints.fixed
    for _ in range(n_newton):
        phi, g = phi_and_grad(phi_fn, points, phi_params, mask=move)
        damping = newton_damping(g)
        g = jnp.where(constraints.locked_axes, 0.0, g)
        sq = jnp.sum(g * g, axis=-1)
        ok = move & (sq > 0)
        step = jnp.where(ok, damping * phi / jnp.where(ok, sq, 1.0), 0.0)
        points = points - step[:, None] * g
    return points


def impose_periodicity(points: Float[Array, "n d"], constraints: NodeConstraints) -> Float[Array, "n d"]:
    """Re-impose p[i] = p[rep[i]] + offset[i] exactly (representatives are unchanged)."""
    return points[constraints.periodic_rep] + constraints.periodic_offset.astype(points.dtype)


def truss_step(
    points: Float[Array, "n d"],
    alpha,
    bars: Int[Array, "m 2"],
    bar_mask: Bool[Array, " m"],
    constraints: NodeConstraints,
    dt,
    h_fn: Callable,
    h_params: Any = None,
    surface_phi_fn: Callable | None = None,
    phi_params: Any = None,
    *,
    fscale=1.2,
    power: int = 2,
    cutoff: bool = False,
    n_newton: int = 2,
    tets: Int[Array, "t 4"] | None = None,
    tet_mask: Bool[Array, " t"] | None = None,
    ball_vertex_stiffness=0.0,
    ball_vertex_quality=0.3,
) -> Float[Array, "n d"]:
    """One constrained forward-Euler step p + dt F (eq. 7, 11); pure and differentiable.

    F = -grad(bar energy [+ ball-vertex energy]) - phi grad phi on surface nodes; then periodic
    averaging, constraint filtering, the move, Newton projection onto phi = 0 and exact
    re-imposition of the periodic translations.

    Returns:
        new points (n, d).
    """
    l0, scale = target_lengths(points, bars, bar_mask, h_fn, h_params, fscale=fscale, power=power)
    use_bv = tets is not None

    def energy(x):
        e = truss_energy(x, bars, bar_mask, l0, alpha, cutoff=cutoff)
        if use_bv:
            h_tet = scale * size_at(h_fn, jnp.mean(points[tets], axis=1), h_params)
            e = e + ball_vertex_energy(
                x, tets, tet_mask, h_tet, quality_threshold=ball_vertex_quality, stiffness=ball_vertex_stiffness
            )
        return e

    forces = -jax.grad(energy)(points)
    normals = None
    if surface_phi_fn is not None:
        phi, normals = phi_and_grad(surface_phi_fn, points, phi_params, mask=constraints.on_surface)
        forces = forces - phi[:, None] * normals  # reaction -phi grad phi (eq. 10), surface nodes only
    forces = filter_forces(average_periodic(forces, constraints), constraints, normals)
    new = points + dt * forces
    if surface_phi_fn is not None:
        new = project_to_surface(new, constraints, surface_phi_fn, phi_params, n_newton)
    return impose_periodicity(new, constraints)
