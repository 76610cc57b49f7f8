"""A mesh's nodes as a differentiable function of its level set, at fixed topology.

`move_interface_nodes(mesh, phi_fn, params)` returns the mesh's points with every interface node
moved along a fixed direction onto the zero set of phi_fn(., params). Each move is a 1-D root found
by optimistix's Newton, differentiated by the implicit-function theorem (ImplicitAdjoint), so
jax.grad of anything computed from the points (a phase volume, a stiffness matrix) gives its shape
derivative with respect to params (level-set grid values, radii, centres). Interior nodes stay; the
map is for gradients and small changes: remesh after a large one.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._mesh import Mesh, on_box_planes


def _edges_and_measures(points, cells):
    """Edge vectors (m, d, d), row r = x_{r+1} - x_0, and unsigned measures (m,) of the cells."""
    x = jnp.asarray(points)[np.asarray(cells)]
    edges = x[:, 1:] - x[:, :1]
    return edges, jnp.abs(jnp.linalg.det(edges)) / (2.0 if x.shape[-1] == 2 else 6.0)


def _measures_and_gradients(points, cells):
    """JAX twin of `_homogenize._p1_gradients` (no flat-cell check): cell measures (m,) and the constant
    P1 shape-function gradients (m, d+1, d)."""
    edges, measures = _edges_and_measures(points, cells)
    inverse_t = jnp.swapaxes(jnp.linalg.inv(edges), 1, 2)
    return measures, jnp.concatenate([-inverse_t.sum(axis=1, keepdims=True), inverse_t], axis=1)


def _directions(grad, locked):
    """Unit directions: the level set's gradient without the locked axes; zero where too little is left
    (a node on a box edge whose interface is nearly perpendicular to it, a box corner)."""
    free = jnp.where(locked, 0.0, grad)
    norm = jnp.linalg.norm(free, axis=1, keepdims=True)
    full = jnp.linalg.norm(grad, axis=1, keepdims=True)
    usable = norm > 0.1 * full
    return jnp.where(usable, free / jnp.where(usable, norm, 1.0), 0.0)


def move_interface_nodes(mesh: Mesh, phi_fn: Callable, params, *, reference=None, rtol: float = 1e-12,
                         max_steps: int = 32):
    """The mesh's points, its interface nodes moved onto the zero set of phi_fn(points, params).

    Each interface node x0 moves to x0 + t d, phi_fn(x0 + t d, params) = c, with c = 0, or with
    reference given c = phi_fn(x0, reference): the level of phi_fn through the node, so that at
    params = reference the points are the mesh's exactly, whatever interpolant phi_fn is (the global
    B-spline of a grid of many inclusions is not the mesher's per-inclusion one: their zero sets part
    by a fraction of a grid step; `benchmarks/bench_shape_derivative.py`). d is the unit gradient of
    phi_fn at x0 (held fixed: it does not depend on params) without its components across the box
    planes the node lies on (trace nodes stay on their face, box-edge nodes on their edge; box
    corners stay). Periodic copies are set to the exact translates of the nodes on the 0 faces. Only
    points are returned; cells, labels and pairs are the mesh's.

    Args:
        mesh: a `Mesh` from `mesh_rve` (2D or 3D) of the level set phi_fn(., reference) (or one close
            to it: its interface nodes are moved from where they are).
        phi_fn: (points (k, d), params) -> (k,) JAX-traceable, negative inside the inclusions: one
            field for all of them (the minimum over inclusions, as a level-set file holds).
        params: a pytree of arrays (grid values, radii, ...), the variable of jax.grad / jax.jvp.
        reference: None (nodes go to the zero set), or the params the mesh was made from (nodes keep
            the level of phi_fn through them; no derivative flows through it).
        rtol, max_steps: the Newton solver's tolerance (relative to the box) and step limit.
    Returns:
        (n, d) JAX array of points, differentiable with respect to params.

    Example:
        >>> phi = lambda x, r: jnp.linalg.norm(x - 0.5, axis=1) - r
        >>> volume = lambda r: phase_volume(move_interface_nodes(mesh, phi, r), mesh.cells, mesh.phase == 1)
        >>> jax.grad(volume)(0.2)  # ~ the area of the sphere's interface
    """
    if not isinstance(mesh, Mesh):
        raise ValueError(f"expected a jaxmesh Mesh, got {type(mesh).__name__}; hint: mesh_rve(...) returns one")
    if not callable(phi_fn):
        raise ValueError(f"expected phi_fn a callable (points, params) -> values, got {type(phi_fn).__name__}")
    nodes = mesh.interface_nodes()
    box = np.asarray(mesh.box, dtype=float)
    start = jnp.asarray(mesh.points[nodes])
    locked = jnp.asarray(on_box_planes(mesh.points[nodes], box).any(axis=2))
    level = 0.0 if reference is None else jax.lax.stop_gradient(phi_fn(start, reference))
    grad = jax.grad(lambda x: jnp.sum(phi_fn(x, params)))(start)
    direction = jax.lax.stop_gradient(_directions(grad, locked))
    scale = float(box.max())

    moves = jnp.any(direction != 0, axis=1)

    def residual(t, p):  # one root per node: the Jacobian is diagonal, tagged so; a node that cannot move: t = 0
        return jnp.where(moves, phi_fn(start + t[:, None] * direction, p) - level, t)

    solver = optx.Newton(rtol=rtol, atol=rtol * scale, linear_solver=lx.Diagonal())
    sol = optx.root_find(residual, solver, jnp.zeros(len(nodes), start.dtype), args=params,
                         tags=frozenset({lx.diagonal_tag}), max_steps=max_steps, throw=False)
    moved = start + sol.value[:, None] * direction
    points = jnp.asarray(mesh.points).at[nodes].set(moved)
    for _ in range(mesh.dim):  # a box-edge node's copies chain over up to d axes
        for axis, pairs in sorted(mesh.periodic_pairs.items()):
            shift = jnp.zeros(mesh.dim).at[axis].set(box[axis])
            points = points.at[pairs[:, 1]].set(points[pairs[:, 0]] + shift)
    return points


def phase_volume(points, cells, selected) -> jax.Array:
    """Sum of |volume| (area in 2D) of the selected cells, differentiable in points.

    Args:
        points: (n, d) JAX or NumPy array; cells: (m, d + 1) ids; selected: (m,) bool mask.
    """
    return jnp.sum(_edges_and_measures(points, np.asarray(cells)[np.asarray(selected, dtype=bool)])[1])


def _traced_cell_conductivity(mesh: Mesh, conductivity, by: str):
    """`_homogenize._cell_conductivity` for values that may be JAX tracers (jax.grad by a conductivity).

    Concrete values take the NumPy path and its checks. Otherwise each value is replaced by its slot in
    the flattened values and the same function resolves ids, keys and shapes, so one set of rules
    applies. Every value gets the usual checks where it is known: concrete ones, and tracers of an eager
    jax.grad, which carry theirs; under jit or vmap a used value that is not positive and finite
    raises equinox's runtime error with the same message.
    """
    from ._homogenize import _cell_conductivity

    if isinstance(conductivity, Mapping):  # its keys are checked below, not sorted by jax.tree
        keys = list(conductivity)
        leaves = [conductivity[key] for key in keys]
        rebuild = lambda values: dict(zip(keys, values))  # noqa: E731
    else:
        leaves, treedef = jax.tree.flatten(conductivity)
        rebuild = lambda values: jax.tree.unflatten(treedef, values)  # noqa: E731
    traced = [isinstance(leaf, jax.core.Tracer) for leaf in leaves]
    if not any(traced):
        return _cell_conductivity(mesh, conductivity, by)
    known = [_known_value(leaf) if t else leaf for leaf, t in zip(leaves, traced)]
    # the values known get the usual checks; an abstract one stands in as ones of its shape
    _cell_conductivity(mesh, rebuild([np.ones(np.shape(leaf)) if v is None else v for leaf, v in zip(leaves, known)]), by)
    sizes = [int(np.size(leaf)) for leaf in leaves]
    starts = np.cumsum([0] + sizes)
    slots = [np.arange(a, b, dtype=float).reshape(np.shape(leaf)) + 1.0
             for a, b, leaf in zip(starts[:-1], starts[1:], leaves)]
    cell_slot = _cell_conductivity(mesh, rebuild(slots), by).astype(np.int64) - 1
    values = jnp.concatenate([_slot_values(leaf, t) for leaf, t in zip(leaves, traced)])
    if any(v is None for v in known):
        used = jnp.asarray(np.unique(cell_slot))
        values = eqx.error_if(values, ~jnp.all(jnp.isfinite(values[used]) & (values[used] > 0)),
                              f"conductivity: every {by}'s value must be positive and finite, got one that is not "
                              "(a traced value, checked at run time)")
    return values[cell_slot]


def _known_value(tracer):
    """The value an eager tracer (jax.grad outside jit) carries, or None (jit, vmap, older jax)."""
    try:
        value = tracer.to_concrete_value()
    except AttributeError:
        return None
    return None if value is None else np.asarray(value)


def _slot_values(leaf, traced: bool):
    if traced:
        return jnp.ravel(leaf).astype(float)
    try:
        return jnp.asarray(np.ravel(np.asarray(leaf, dtype=float)))
    except (TypeError, ValueError):  # not a number: the value of an id absent from the mesh (checked above)
        return jnp.zeros(np.size(leaf))


def effective_conductivity(mesh: Mesh, points, conductivity, *, by: str = "inclusion_id", rtol: float = 1e-10,
                           max_steps: int | None = None) -> jax.Array:
    """`homogenize_conductivity`'s P1 periodic cell problems in JAX, differentiable in the points and
    in the conductivities.

    The same discretisation (one unknown per class of periodic nodes, one class pinned), solved by
    lineax's conjugate gradients with a Jacobi preconditioner and differentiated through the linear
    solves, so jax.grad of the tensor with respect to `move_interface_nodes`' params gives the
    effective conductivity's shape derivative.

    Args:
        mesh: a periodic `Mesh` (its cells, labels and periodic pairs; its own points only set the CG's
            absolute tolerance and are checked for flat cells).
        points: (n, d) node positions, e.g. `move_interface_nodes(mesh, phi_fn, params)`.
        conductivity, by: as `homogenize_conductivity` (one positive value per id); the values may be
            traced (jax.grad with respect to them; checked like concrete ones in an eager jax.grad, at run
            time under jit).
        rtol, max_steps: the CG tolerance and step limit (None: 10 n).
    Returns:
        (d, d) effective conductivity tensor.

    Example:
        >>> k = lambda r: effective_conductivity(mesh, move_interface_nodes(mesh, phi, r, reference=r0),
        ...                                      {0: 1.0, 1: 10.0}, by="phase")[0, 0]
        >>> jax.grad(k)(r0)
        >>> jax.grad(lambda k1: effective_conductivity(mesh, mesh.points, {0: 1.0, 1: k1}, by="phase")[0, 0])(10.0)
    """
    from ._homogenize import _p1_gradients, _periodic_classes

    if not isinstance(mesh, Mesh):
        raise ValueError(f"expected a jaxmesh Mesh, got {type(mesh).__name__}; hint: mesh_rve(...) returns one")
    classes, n_classes = _periodic_classes(mesh)
    d = mesh.dim
    k = _traced_cell_conductivity(mesh, conductivity, by)
    measure, grads = _measures_and_gradients(points, mesh.cells)  # grads (m, d+1, d)
    weight = jnp.asarray(k) * measure
    dtype = weight.dtype
    owner = jnp.asarray(classes[mesh.cells])  # (m, d+1) class of each cell vertex
    free = jnp.ones(n_classes, dtype=dtype).at[0].set(0.0)  # class 0 pinned: the constant is free

    def to_classes(per_vertex):  # (m, d+1) -> (n_classes,)
        return jax.ops.segment_sum(per_vertex.ravel(), owner.ravel(), n_classes)

    def fluctuation_gradient(w):  # (m, d)
        return jnp.einsum("mad,ma->md", grads, w[owner])

    def stiffness(w):
        flux = weight[:, None] * fluctuation_gradient(free * w)
        return free * to_classes(jnp.einsum("mad,md->ma", grads, flux)) + (1.0 - free) * w

    structure = jax.ShapeDtypeStruct((n_classes,), dtype)
    operator = lx.FunctionLinearOperator(stiffness, structure, tags=(lx.symmetric_tag, lx.positive_semidefinite_tag))
    # Jacobi; it changes the iterations, not the solution, so no derivative flows through it (lineax's rule)
    diagonal = jax.lax.stop_gradient(free * to_classes(weight[:, None] * jnp.sum(grads**2, axis=2)) + (1.0 - free))
    preconditioner = lx.TaggedLinearOperator(lx.DiagonalLinearOperator(1.0 / diagonal), lx.positive_semidefinite_tag)
    # lineax's CG scales the residual entrywise by atol + rtol |load|, and most loads are 0 (nodes off the
    # interfaces): atol from the loads at the mesh's own points, a concrete number under jit and grad by the
    # points (a JAX scalar without derivative when the conductivities are traced)
    grads0, measure0 = _p1_gradients(np.asarray(mesh.points, float), np.asarray(mesh.cells))  # refuses flat cells
    if isinstance(k, np.ndarray):
        loads0 = (k * measure0)[:, None, None] * grads0
        load_scale = max(float(np.abs(np.bincount(classes[mesh.cells].ravel(), loads0[..., j].ravel())).max())
                         for j in range(d))
    else:  # traced conductivities: the same scale as a JAX scalar, no derivative through it
        loads0 = jax.lax.stop_gradient(k * measure0)[:, None, None] * grads0
        load_scale = jnp.max(jnp.abs(jnp.stack([jax.ops.segment_sum(loads0[..., j].ravel(),
                                                                    classes[mesh.cells].ravel(), n_classes)
                                                for j in range(d)])))
    solver = lx.CG(rtol=rtol, atol=rtol * load_scale, max_steps=max_steps or 10 * n_classes)
    total = []
    for j in range(d):
        unit = jnp.zeros(d, dtype=dtype).at[j].set(1.0)
        load = -free * to_classes(jnp.einsum("mad,d->ma", grads, unit) * weight[:, None])
        w = lx.linear_solve(operator, load, solver, options={"preconditioner": preconditioner}).value
        total.append(unit + fluctuation_gradient(w))
    total = jnp.stack(total, axis=1)  # (m, d, d): row j is E_j + grad w_j
    return jnp.einsum("m,mis,mjs->ij", weight, total, total) / float(np.prod(mesh.box))
