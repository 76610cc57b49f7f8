"""The size function h(x) (paper section 4.2): source sizes on the interfaces, gradient limiting.

Pipeline: source points x_sp = crossings of phi = 0 on the grid edges (:func:`interface_sources`);
sizes there h0 = min(iis, DN2 / nb_el, alpha / |kappa|) (eq. 12, 13, 17, 19, :func:`source_sizes`),
and at most the thickness of a layer the box cuts off (:func:`box_gaps`);
the field h(x) = min(h_max, min_sp h0(x_sp) + g |x - x_sp|) with PERIODIC distances (eq. 20,
:func:`limit_gradient`) on the level-set grid, wrapped in a :class:`SizeField`.

Eq. 20 is not evaluated by brute force (O(grid x sources)) but as a shortest path on the grid
graph: every node within ``reach`` cells of a source gets the exact cone value h0_s + g |x - x_s|
(seeds), then val_i = min(val_i, val_j + g |x_i - x_j|) over a stencil of primitive offsets with
max |o_a| <= ``radius`` (98 in 3D, 16 in 2D for radius 2), periodic via jnp.roll, in a
lax.while_loop until nothing changes (multi-hop sweeps first, so far nodes are reached in log2 n
sweeps). The fixed point is unique: a min over a fixed set of paths, hence continuous and
piecewise smooth in every input, so jax.grad matches finite differences. Gradients come from the
path itself (predecessors recovered by one argmin pass, collapsed by pointer jumping): h = h0_s +
g (|x_seed - x_s| + stencil length); the search runs under stop_gradient.
Error vs the exact Euclidean formula (one-sided: h >= exact, every path is at least as long as
the straight segment): a sub-cell detour at the seed ring plus the stencil anisotropy along the
way; for the defaults measured <= 0.3 g spacing + 4 % of g |x - x_s| (radius 1: ~1.5 g spacing +
11 %), mean ~0.15 g spacing (tests/test_sizing.py checks it against brute force).
Cost O(grid * stencil * (log2 n + 2)) plus one argmin pass (benchmarks/bench_sizing_octree.py).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int
from scipy import ndimage

from ._periodic import minimum_image, points_near, wrap
from .geometry._components import _gradient
from .geometry._differential import curvatures
from .geometry._microstructure import _traceable
from .geometry._grid import interpolate_linear

# elements per unit volume of a mesh of regular simplices of edge h: 1 / vol(simplex) = c_d / h^d
_SIMPLEX_DENSITY = {2: 4.0 / math.sqrt(3.0), 3: 6.0 * math.sqrt(2.0)}
_PARAMS = ("iis", "nb_el", "curv_alpha", "grad", "h_max", "h_min")


def _is_concrete(x) -> bool:
    return x is not None and not isinstance(x, jax.core.Tracer)


class SizeParams(eqx.Module):
    """Parameters of the size function (all differentiable: pass JAX scalars to jax.grad).

    Attributes:
        iis: initial interface size, the largest element size on any interface (eq. 12).
        nb_el: number of elements across the gap to the nearest other inclusion (eq. 13).
        curv_alpha: h_curv = curv_alpha / |kappa| (eq. 17). Default 0.5: a sphere of radius R
            gets h = R / 2, i.e. ~12.6 edges per great circle and a chord sag of ~3 % of R.
        grad: gradient limiting factor g, |grad h| <= g (eq. 18, 20).
        h_max: cap of h far from the interfaces; None -> 4 * iis.
        h_min: floor of the source sizes (tiny gaps, sharp corners); None -> iis / 100.

    Example:
        >>> SizeParams(iis=0.03, grad=0.25)
    """

    iis: float | Array = 0.05
    nb_el: float | Array = 3.0
    curv_alpha: float | Array = 0.5
    grad: float | Array = 0.3
    h_max: float | Array | None = None
    h_min: float | Array | None = None

    def __check_init__(self):
        v = {}
        for name in _PARAMS:
            x = getattr(self, name)
            if _is_concrete(x):
                arr = np.asarray(x, dtype=float)
                if arr.shape != () or not np.isfinite(arr) or arr <= 0:
                    raise ValueError(f"SizeParams.{name} expected a positive finite scalar, got {x!r}. "
                                     "Hint: e.g. SizeParams(iis=0.05, nb_el=3, curv_alpha=0.5, grad=0.3).")
                v[name] = float(arr)
        if v.get("grad", 0.0) > 10.0:
            raise ValueError(f"SizeParams.grad expected a gradient limit in (0, 10], got {v['grad']}. "
                             "Hint: 0.2-0.5 gives smooth size transitions.")
        if "iis" in v and v.get("h_max", np.inf) < v["iis"]:
            raise ValueError(f"SizeParams.h_max expected >= iis = {v['iis']}, got {v['h_max']}. "
                             "Hint: h_max caps sizes far from the interfaces, iis the interface size.")
        if "iis" in v and v.get("h_min", 0.0) > v["iis"]:
            raise ValueError(f"SizeParams.h_min expected <= iis = {v['iis']}, got {v['h_min']}. "
                             "Hint: h_min is a floor for small gaps and sharp features.")

    def resolved(self) -> tuple[Array, Array, Array, Array, Array, Array]:
        """(iis, nb_el, curv_alpha, grad, h_max, h_min) as JAX scalars, defaults filled in."""
        arr = functools.partial(jnp.asarray, dtype=float)
        iis = arr(self.iis)
        h_max = 4.0 * iis if self.h_max is None else arr(self.h_max)
        h_min = iis / 100.0 if self.h_min is None else arr(self.h_min)
        return iis, arr(self.nb_el), arr(self.curv_alpha), arr(self.grad), h_max, h_min


def check_params_against_box(params: SizeParams, box: Sequence[float]) -> None:
    """ValueError when iis is larger than the box or smaller than 1e-4 of it."""
    if not _is_concrete(params.iis):
        return
    iis, lo, hi = float(params.iis), min(box), max(box)
    if iis > lo:
        raise ValueError(f"SizeParams.iis expected <= the smallest box length {lo}, got {iis}. "
                         "Hint: iis is an element size on the interfaces, a fraction of the cell.")
    if iis < 1e-4 * hi:
        raise ValueError(f"SizeParams.iis expected >= 1e-4 * box = {1e-4 * hi:g}, got {iis:g}. "
                         "Hint: that asks for > 10^8 elements per axis; check the units of iis and box.")


# ----------------------------------------------------------------------------- source points
class SourceEdges(NamedTuple):
    """Grid edges crossed by phi = 0 (NumPy): flat node indices a, b and the edge axis. Not periodic,
    an edge from the last slice towards x = L has b = a and `before` the node before a (its far
    value is the linear continuation 2 phi_a - phi_before, as the level sets go on); -1 elsewhere."""

    a: np.ndarray
    b: np.ndarray
    axis: np.ndarray
    before: np.ndarray | None = None


def interface_edges(values: ArrayLike, periodic: bool = True) -> SourceEdges:
    """Edges (a, a + e_axis) whose end nodes differ in sign (phi < 0 vs phi >= 0).

    Args:
        values: (nx, ny[, nz]) concrete level-set samples (NumPy or JAX, not traced).
        periodic: include the wrap-around edges (n-1 -> 0).

    Returns:
        :class:`SourceEdges`, each (s,): a fixed sign pattern, so that crossings computed from it
        are differentiable in the values (:func:`interface_sources`).
    """
    values = np.asarray(values)
    inside = values < 0
    flat = np.arange(inside.size).reshape(inside.shape)
    found = []
    for axis in range(inside.ndim):
        cross = inside != np.roll(inside, -1, axis=axis)
        if not periodic:  # the last slice's edges end at x = L, where phi is the linear continuation
            last = (slice(None),) * axis + (-1,)
            beyond = 2 * values[last] - values[(slice(None),) * axis + (-2,)]
            cross[last] = inside[last] != (beyond < 0)
        b = np.roll(flat, -1, axis=axis)
        before = np.full(inside.shape, -1)
        if not periodic:
            b[last] = flat[last]
            before[last] = np.take(flat, -2, axis=axis)
        found.append((flat[cross], b[cross], np.full(int(cross.sum()), axis), before[cross]))
    return SourceEdges(*(np.concatenate(x).astype(np.int64) for x in zip(*found)))


def _check_grid(values, box) -> tuple[float, ...]:
    shape = np.shape(values)
    if len(shape) not in (2, 3) or min(shape) < 2:
        raise ValueError(f"expected a 2D or 3D level-set grid, got shape {shape}. "
                         "Hint: values[i, j(, k)] = phi at node (i, j(, k)).")
    box = tuple(float(b) for b in (np.ones(len(shape)) if box is None else box))
    if len(box) != len(shape) or not all(np.isfinite(b) and b > 0 for b in box):
        raise ValueError(f"expected {len(shape)} positive box lengths for grid shape {shape}, got {box}. "
                         "Hint: one length per grid axis.")
    return box


def interface_sources(field, box: Sequence[float] | None = None, *, labels: ArrayLike | None = None,
                      periodic: bool | None = None, edges: SourceEdges | None = None
                      ) -> tuple[Float[Array, "s d"], np.ndarray]:
    """Source points on the interfaces at grid precision: the crossings of phi = 0 on grid edges.

    The crossing on edge (a, b) sits at x_a + t h e_axis, t = phi_a / (phi_a - phi_b) (linear
    interpolation), wrapped into [0, L); differentiable in the values for a fixed sign pattern
    (pass ``edges`` from :func:`interface_edges` to call it on traced values).

    Args:
        field: a Microstructure (uses dn1, nearest_id, box, periodic) or (nx, ny[, nz]) values.
        box: (d,) lengths for raw values (default unit cell); ignored for a Microstructure.
        labels: optional int grid of inclusion ids for raw values (default: all ids 1).
        periodic: include crossings through the periodic faces (default True / microstructure's).
        edges: precomputed sign pattern.

    Returns:
        points (s, d) JAX array and ids (s,) NumPy int: the label at the edge's inside node.

    Example:
        >>> pts, ids = interface_sources(ms)  # ms: Microstructure
    """
    if hasattr(field, "dn1"):
        values, box, labels = field.dn1, field.box, field.nearest_id
        periodic = field.periodic if periodic is None else periodic
    else:
        values = field
    periodic = True if periodic is None else bool(periodic)
    box = _check_grid(values, box)
    if edges is None:
        if isinstance(values, jax.core.Tracer):
            raise ValueError("interface_sources expected concrete values to find the sign pattern, got a "
                             "tracer. Hint: compute edges = interface_edges(values) outside the transform.")
        if not np.all(np.isfinite(np.asarray(values))):
            raise ValueError("interface_sources expected finite level-set values, got NaN/inf. "
                             "Hint: fill undefined samples with a large positive distance.")
        edges = interface_edges(values, periodic)
    shape = np.shape(values)
    phi = jnp.asarray(values).reshape(-1)
    pa, pb = phi[edges.a], phi[edges.b]
    if edges.before is not None and (edges.before >= 0).any():
        pb = jnp.where(jnp.asarray(edges.before >= 0), 2 * pa - phi[edges.before], pb)
    spacing = np.asarray(box) / np.asarray(shape)
    base = np.stack(np.unravel_index(edges.a, shape), axis=-1) * spacing
    step = np.eye(len(shape))[edges.axis] * spacing
    points = wrap(jnp.asarray(base) + (pa / (pa - pb))[:, None] * jnp.asarray(step), jnp.asarray(box))
    if labels is None:
        return points, np.ones(edges.a.size, dtype=np.int64)
    inside_a = np.asarray(values).reshape(-1)[edges.a] < 0
    return points, np.asarray(labels).reshape(-1)[np.where(inside_a, edges.a, edges.b)].astype(np.int64)


def source_sizes(points: Float[ArrayLike, "s d"], ids: Int[ArrayLike, " s"],
                 dn2_at_points: Float[ArrayLike, " s"], kappa_at_points: Float[ArrayLike, " s"],
                 iis, nb_el, curv_alpha, h_min=None, box_gap_at_points: Float[ArrayLike, " s"] | None = None
                 ) -> Float[Array, " s"]:
    """h0 = max(h_min, min(iis, DN2 / nb_el, alpha / |kappa|, box gap / min(nb_el, 1))) at the
    source points (eq. 12-19).

    Args:
        points: (s, d) source points and ids: (s,) their inclusion ids (sizes are pointwise:
            both only fix s and are checked).
        dn2_at_points: (s,) distance to the second nearest inclusion at each source.
        kappa_at_points: (s,) max |principal curvature| of the source's own inclusion.
        iis, nb_el, curv_alpha: scalars (JAX scalars to differentiate); h_min: optional floor.
        box_gap_at_points: optional (s,) :func:`box_gaps`: one element across such a layer (fewer
            when nb_el < 1).

    Returns:
        (s,) source sizes h0.
    """
    s = np.shape(points)[0]
    checked = [("ids", ids), ("dn2_at_points", dn2_at_points), ("kappa_at_points", kappa_at_points)]
    if box_gap_at_points is not None:
        checked.append(("box_gap_at_points", box_gap_at_points))
    for name, arr in checked:
        if np.shape(arr) != (s,):
            raise ValueError(f"source_sizes expected {name} of shape ({s},) (one per source point), "
                             f"got {np.shape(arr)}. Hint: evaluate it at the source points.")
    kappa = jnp.maximum(jnp.abs(jnp.asarray(kappa_at_points)), 1e-300)  # flat: h_curv huge
    h0 = jnp.minimum(jnp.minimum(iis, jnp.asarray(dn2_at_points) / nb_el), curv_alpha / kappa)
    if box_gap_at_points is not None:  # no material gap (the phase goes on through the face): one element across
        h0 = jnp.minimum(h0, jnp.asarray(box_gap_at_points) / jnp.minimum(nb_el, 1.0))
    return h0 if h_min is None else jnp.maximum(h0, h_min)


# ----------------------------------------------------------------------------- gradient limiting
def _grid_coordinates(grid_shape, box, dtype) -> Array:
    axes = [jnp.arange(n, dtype=dtype) * (L / n) for n, L in zip(grid_shape, box)]
    return jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1)


def _delta(x, src, box, periodic):
    return minimum_image(x - src, jnp.asarray(box, dtype=x.dtype)) if periodic else x - src


def _shift(a: Array, shift, axis: int, periodic: bool) -> Array:
    """a[i - shift] along axis; inf where that falls off a non-periodic grid."""
    out = jnp.roll(a, shift, axis=axis)
    if not periodic:
        i = jax.lax.broadcasted_iota(jnp.int32, a.shape, axis) - shift
        out = jnp.where((i >= 0) & (i < a.shape[axis]), out, jnp.inf)
    return out


def _stencil(d: int, radius: int, spacing) -> tuple[Array, np.ndarray]:
    """Primitive integer offsets o, max |o_a| <= radius ((2, 0) is two (1, 0) steps), lengths |o|."""
    offs = np.array([o for o in itertools.product(range(-radius, radius + 1), repeat=d) if math.gcd(*o) == 1])
    return jnp.asarray(offs, dtype=jnp.int32), np.sqrt(np.sum((offs * np.asarray(spacing)) ** 2, axis=1))


def _seed(h0, src, g, coords, box, periodic, reach) -> tuple[Array, Array]:
    """Exact cone values h0_s + g |x - x_s| on the (2 reach)^d nodes around each source:
    the best value per node (inf: none) and its source index (-1: none)."""
    shape, d = coords.shape[:-1], coords.shape[-1]
    spacing = jnp.asarray([L / n for L, n in zip(box, shape)], dtype=coords.dtype)
    base = jnp.floor(src / spacing).astype(jnp.int32)
    n_arr = jnp.asarray(shape, dtype=jnp.int32)
    strides = jnp.asarray([math.prod(shape[a + 1 :]) for a in range(d)], dtype=jnp.int32)
    corners = jnp.asarray(list(itertools.product(range(1 - reach, 1 + reach), repeat=d)), dtype=jnp.int32)
    flat_coords = coords.reshape(-1, d)

    def cone_at(j):  # one corner offset at a time: memory O(sources), not O(sources * corners)
        node = base + corners[j]
        flat = (node % n_arr if periodic else jnp.clip(node, 0, n_arr - 1)) @ strides
        delta = _delta(flat_coords[flat], src, box, periodic)
        return flat, h0 + g * jnp.sqrt(jnp.sum(delta * delta, axis=-1))  # inf: padded sources

    def scatter_val(j, val):
        flat, cval = cone_at(j)
        return val.at[flat].min(cval)

    def scatter_idx(j, idx):
        flat, cval = cone_at(j)
        win = (cval == val[flat]) & jnp.isfinite(cval)
        return idx.at[flat].max(jnp.where(win, jnp.arange(h0.shape[0], dtype=jnp.int32), -1))

    val = jnp.full(math.prod(shape), jnp.inf, dtype=coords.dtype)
    val = jax.lax.fori_loop(0, corners.shape[0], scatter_val, val)
    idx = jax.lax.fori_loop(0, corners.shape[0], scatter_idx, jnp.full(val.shape, -1, jnp.int32))
    return val.reshape(shape), idx.reshape(shape)


def _relax(seed_val, steps, offs, periodic, tol=1e-12) -> Array:
    """Shortest-path values val_i = min(seed_i, min_o val_{i-o} + g |o|) on the grid graph.

    First one sweep per hop length k = 2^m .. 2 (2^m <= n/2) with the straight moves k o (k steps
    of o: paths of the same graph, so the fixed point is unchanged, but far nodes are reached in
    log2 n sweeps), then unit sweeps until nothing changes (typically two).
    """
    d = seed_val.ndim

    def sweep(val, k):
        def visit(j, val):  # Gauss-Seidel over the stencil: each offset sees the previous ones
            nb = val
            for a in range(d):
                nb = _shift(nb, offs[j, a] * k, a, periodic)
            return jnp.minimum(val, nb + k * steps[j])

        return jax.lax.fori_loop(0, offs.shape[0], visit, val)

    top = int(math.log2(max(max(seed_val.shape) // 2, 1)))
    hops = jnp.asarray([2**m for m in range(top, 0, -1)], dtype=jnp.int32)
    val = jax.lax.fori_loop(0, hops.size, lambda i, v: sweep(v, hops[i]), seed_val)

    def body(c):
        new = sweep(c[0], 1)
        return new, jnp.any(new < c[0] * (1.0 - tol))

    return jax.lax.while_loop(lambda c: c[1], body, (val, jnp.bool_(True)))[0]


def _path_to_seed(val, seed_val, steps, lengths, offs, periodic) -> tuple[Array, Array]:
    """Per node: the flat index of the seed node its shortest path starts from, and the stencil
    length of that path. Predecessor = best stencil neighbour (itself if its own seed is best);
    the predecessor forest is collapsed by pointer jumping (log2 of the longest path rounds)."""
    shape, d = val.shape, val.ndim

    def visit(j, c):
        nb = val
        for a in range(d):
            nb = _shift(nb, offs[j, a], a, periodic)
        better = nb + steps[j] < c[0]
        return jnp.where(better, nb + steps[j], c[0]), jnp.where(better, j, c[1])

    _, arg = jax.lax.fori_loop(0, offs.shape[0], visit, (seed_val, jnp.full(shape, -1, jnp.int32)))
    index = jnp.stack([jax.lax.broadcasted_iota(jnp.int32, shape, a) for a in range(d)], axis=-1)
    has = arg[..., None] >= 0
    pred = (index - jnp.where(has, offs[jnp.maximum(arg, 0)], 0)) % jnp.asarray(shape, dtype=jnp.int32)
    ptr = (pred @ jnp.asarray([math.prod(shape[a + 1 :]) for a in range(d)], dtype=jnp.int32)).reshape(-1)
    length = jnp.where(arg >= 0, jnp.asarray(lengths, val.dtype)[jnp.maximum(arg, 0)], 0.0).reshape(-1)

    def jump(c):
        ptr, length, _ = c
        return ptr[ptr], length + length[ptr], jnp.any(ptr[ptr] != ptr)

    ptr, length, _ = jax.lax.while_loop(lambda c: c[2], jump, (ptr, length, jnp.bool_(True)))
    return ptr.reshape(shape), length.reshape(shape)


@functools.partial(jax.jit, static_argnames=("grid_shape", "box", "periodic", "radius", "reach"))
def _limit_gradient(h0, sources, g, h_max, grid_shape, box, periodic, radius, reach):
    coords = _grid_coordinates(grid_shape, box, sources.dtype)
    offs, lengths = _stencil(len(grid_shape), radius, [L / n for L, n in zip(box, grid_shape)])
    # the path search runs on constants; gradients flow through the final evaluation only
    h0_c, src_c, g_c = (jax.lax.stop_gradient(x) for x in (h0, sources, g))
    steps = g_c * jnp.asarray(lengths, dtype=sources.dtype)
    seed_val, seed_idx = _seed(h0_c, src_c, g_c, coords, box, periodic, reach)
    val = _relax(seed_val, steps, offs, periodic)
    root, length = _path_to_seed(val, seed_val, steps, lengths, offs, periodic)
    idx = seed_idx.reshape(-1)[root]
    safe = jnp.maximum(idx, 0)
    delta = _delta(coords.reshape(-1, coords.shape[-1])[root], sources[safe], box, periodic)
    r2 = jnp.sum(delta * delta, axis=-1)
    dist = jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)  # safe sqrt: finite grads at 0
    return jnp.minimum(jnp.where(idx >= 0, h0[safe] + g * (dist + length), h_max), h_max)


def limit_gradient(h0: Float[ArrayLike, " s"], sources: Float[ArrayLike, "s d"], box: Sequence[float],
                   grid_shape: Sequence[int], g, h_max, *, periodic: bool = True, radius: int = 2,
                   reach: int = 2) -> Float[Array, "..."]:
    """h(x) = min(h_max, min_s h0_s + g |x - x_s|) on the node-centred grid (eq. 20).

    Distances are minimum-image distances when ``periodic``; see the module docstring for the
    algorithm and its (one-sided) error. Sources are padded to a power-of-two capacity.

    Args:
        h0: (s,) source sizes; sources: (s, d) source points.
        box: (d,) cell lengths; grid_shape: (nx, ny[, nz]), node i at i * L / n.
        g: gradient limit; h_max: cap (JAX scalars to differentiate).
        periodic: periodic distances and propagation.
        radius: stencil radius (1: 3^d - 1 offsets, cheaper, ~3x the error); reach: seed ring in cells.

    Returns:
        (nx, ny[, nz]) sizes h.
    """
    grid_shape, box = tuple(int(n) for n in grid_shape), tuple(float(b) for b in box)
    d = len(grid_shape)
    if d not in (2, 3) or len(box) != d or min(grid_shape) < 2:
        raise ValueError(f"limit_gradient expected a 2D/3D grid_shape and a box of the same length, got "
                         f"{grid_shape} and {box}. Hint: pass microstructure.grid_shape and .box.")
    if radius not in (1, 2, 3) or reach not in (1, 2, 3):
        raise ValueError(f"limit_gradient expected radius and reach in 1..3, got {radius!r}, {reach!r}. "
                         "Hint: the defaults (2, 2) balance accuracy and cost.")
    sources = jnp.asarray(sources, dtype=float)
    h0 = jnp.asarray(h0, dtype=sources.dtype)
    if sources.ndim != 2 or sources.shape[1] != d or h0.shape != (sources.shape[0],):
        raise ValueError(f"limit_gradient expected sources (s, {d}) and h0 (s,), got {sources.shape} and "
                         f"{h0.shape}. Hint: one size per source point.")
    if _is_concrete(h0) and h0.size and not bool(jnp.all(h0 > 0)):
        raise ValueError("limit_gradient expected positive source sizes h0, got h0 <= 0 or NaN. "
                         "Hint: set SizeParams.h_min.")
    s = sources.shape[0]
    cap = 1 << max(s - 1, 0).bit_length()  # capacity bucket: fewer recompilations
    h0 = jnp.concatenate([h0, jnp.full(cap - s, jnp.inf, dtype=h0.dtype)])
    sources = jnp.concatenate([sources, jnp.zeros((cap - s, d), dtype=sources.dtype)])
    g, h_max = jnp.asarray(g, dtype=sources.dtype), jnp.asarray(h_max, dtype=sources.dtype)
    return _limit_gradient(h0, sources, g, h_max, grid_shape, box, bool(periodic), int(radius), int(reach))


def predicted_element_count(h: Float[ArrayLike, "..."], box: Sequence[float]) -> Array:
    """Expected number of elements, c_d * integral of h^-d over the box (differentiable).

    c_d = 1 / volume of the regular simplex of unit edge (4 / sqrt(3) in 2D, 6 sqrt(2) in 3D): an
    estimate; meshes of nearly regular simplices come within a small factor.

    Args:
        h: (nx, ny[, nz]) size grid (node-centred periodic: the mean is the integral / volume).
        box: (d,) lengths.

    Returns:
        scalar count.
    """
    h = jnp.asarray(h)
    if h.ndim not in _SIMPLEX_DENSITY or len(box) != h.ndim:
        raise ValueError(f"predicted_element_count expected a 2D/3D size grid and one box length per axis, "
                         f"got shape {h.shape} and box {box}. Hint: pass SizeField.values and .box.")
    return _SIMPLEX_DENSITY[h.ndim] * math.prod(box) * jnp.mean(h ** (-h.ndim))


def cellwise_element_count(h: np.ndarray, box: Sequence[float], steep: float = 1.5, samples: int = 4) -> float:
    """c_d * integral of h^-d with h multilinear in each periodic grid cell (NumPy, not differentiable).

    `predicted_element_count` weighs each node's h^-d by a whole cell: where a gap far below the grid
    step sets h at one node, that overcounts by orders of magnitude (see the test with one fine node
    in a graded field). Cells whose corner sizes differ by more than `steep` times are sampled at
    samples^d midpoints instead; smooth cells use the mean of their corners (the node mean, up to the
    order of summation).
    """
    h = np.asarray(h, dtype=float)
    d = h.ndim
    bits = list(itertools.product((0, 1), repeat=d))

    def corner(bit):  # (cells,) h at this corner of every cell (cell i spans nodes i .. i + 1)
        return np.roll(h, tuple(-b for b in bit), axis=tuple(range(d))).ravel()

    density, lo, hi = np.zeros(h.size), np.full(h.size, np.inf), np.zeros(h.size)
    for bit in bits:  # one corner at a time: no (cells, 2^d) array for the whole grid
        c = corner(bit)
        density += c ** -float(d) / len(bits)
        np.minimum(lo, c, out=lo)
        np.maximum(hi, c, out=hi)
    sharp = np.flatnonzero(hi > steep * lo)
    if sharp.size:
        corners = np.stack([corner(bit)[sharp] for bit in bits], axis=-1)
        t = (np.arange(samples) + 0.5) / samples
        pts = np.stack(np.meshgrid(*[t] * d, indexing="ij"), axis=-1).reshape(-1, d)
        weights = np.prod([np.where(np.asarray(bit)[None, :] == 1, pts[:, [k]], 1 - pts[:, [k]])
                           for k, bit in enumerate(np.asarray(bits).T)], axis=0)  # (samples^d, 2^d)
        for start in range(0, sharp.size, 1 << 14):
            rows = slice(start, start + (1 << 14))
            density[sharp[rows]] = ((corners[rows] @ weights.T) ** -float(d)).mean(axis=1)
    return float(_SIMPLEX_DENSITY[d] * math.prod(box) * density.mean())


# ----------------------------------------------------------------------------- size field
class SizeField(eqx.Module):
    """h(x) sampled on the level-set grid, interpolated like the level sets (periodic linear).

    Attributes:
        values: (nx, ny[, nz]) sizes at the grid nodes; box: (d,) cell lengths (static).
        source_points: (s, d) interface source points, or None; source_h0: (s,) their sizes.
        curvature_averaged: ids of the inclusions whose curvature was averaged (`size_sources`).

    Example:
        >>> h = size_function(ms, SizeParams(iis=0.05))
        >>> h(jnp.array([[0.5, 0.5, 0.5]]))
    """

    values: Float[Array, "..."]
    box: tuple[float, ...] = eqx.field(static=True, converter=lambda b: tuple(float(x) for x in b))
    source_points: Float[Array, "s d"] | None = None
    source_h0: Float[Array, " s"] | None = None
    curvature_averaged: tuple[int, ...] = eqx.field(static=True, default=())  # see SizeSources

    def __call__(self, points: Float[ArrayLike, "m d"]) -> Float[Array, " m"]:
        """h at (m, d) points (periodic)."""
        return interpolate_linear(self.values, self.box, points)

    def h_fn(self) -> Callable[[Array], Array]:
        """Closure points (m, d) -> h (m,), traceable and differentiable."""
        values, box = self.values, self.box
        return lambda points: interpolate_linear(values, box, points)

    def element_count(self) -> Array:
        """:func:`predicted_element_count` of this field."""
        return predicted_element_count(self.values, self.box)


class SizeSources(NamedTuple):
    """Parameter-independent inputs of the size function (compute once, reuse)."""

    points: Array  # (s, d) interface source points
    ids: np.ndarray  # (s,) inclusion ids
    dn2: Array  # (s,) DN2 at the sources (linear interpolation of the grid), or the self_gaps when narrower
    kappa: Array  # (s,) max |principal curvature| of each source's own inclusion
    box_gap: np.ndarray | None = None  # (s,) box_gaps (None: no such term)
    curvature_averaged: tuple[int, ...] = ()  # ids of the inclusions whose curvature was averaged


def _max_abs_from(mean: np.ndarray, gaussian: np.ndarray, dim: int) -> np.ndarray:
    """max(|k1|, |k2|) = |mean| + sqrt(mean^2 - gaussian) (3D), |curvature| (2D)."""
    if dim == 2:
        return np.abs(mean)
    return np.abs(mean) + np.sqrt(np.maximum(mean * mean - gaussian, 0.0))


def _averaged_over_neighbours(points: np.ndarray, values: tuple[np.ndarray, ...], radius: float, box,
                              periodic: bool) -> tuple[np.ndarray, ...]:
    """Each value averaged over the points within radius (`points_near`: minimum image when periodic)."""
    near = points_near(points, points, np.full(len(points), radius), box, periodic)
    rows = np.repeat(np.arange(len(points)), [len(n) for n in near])  # each point is its own neighbour
    cols = np.concatenate(near)
    count = np.bincount(rows, minlength=len(points))
    return tuple(np.bincount(rows, weights=v[cols], minlength=len(points)) / count for v in values)


AUTO_CURVATURE_AVERAGE = 1.5  # grid steps: one ripple period of a field sampled from voxels
# An interface ripples when half of it curves with radii under two grid steps (median pointwise
# |kappa| step above 0.5) and the average cancels most of it (median below 0.4 of the pointwise).
# Measured (median kappa step, ratio): distance transforms of voxel spheres and quantised fields
# (1.0-1.3, 0.12-0.25); smooth shapes, thresholded random fields, labelled images, rounded boxes,
# a needle tip (0.05-0.87, 0.36-1.8 where above 0.5: 0.86 and more).
_RIPPLE_CURVATURE_STEPS = 0.5
_RIPPLE_RATIO = 0.4


def _curvature(phi_fn: Callable, points: np.ndarray, average: float | None, step: float, box,
               periodic: bool) -> tuple[np.ndarray, bool]:
    """(max |principal curvature| of one inclusion at (m, d) points, whether it was averaged).

    average > 0: from its mean and Gaussian curvatures averaged over the points within that many
    grid steps (`_averaged_over_neighbours`). Ripples finer than the grid (the cubic interpolant
    of a field sampled from voxels: a distance transform of an image, a quantised field) alternate
    in sign and cancel; a curvature the grid resolves keeps its value (a sphere's exactly).
    0: pointwise. None: averaged over AUTO_CURVATURE_AVERAGE steps where the interface ripples
    (see _RIPPLE_RATIO), else pointwise.
    """
    mean, gaussian, pointwise = _curvature_terms(phi_fn, points)
    typical = np.median(pointwise)
    if average == 0.0 or (average is None and typical * step <= _RIPPLE_CURVATURE_STEPS):
        return pointwise, False
    radius = (AUTO_CURVATURE_AVERAGE if average is None else average) * step
    averaged = _max_abs_from(*_averaged_over_neighbours(points, (mean, gaussian), radius, box, periodic),
                             points.shape[1])
    if average is None and not np.median(averaged) < _RIPPLE_RATIO * typical:
        return pointwise, False
    return averaged, True


def _mean_gaussian_max_abs(phi_fn: Callable, points: Array) -> tuple[Array, Array, Array]:
    c = curvatures(phi_fn, points)
    return c.mean, c.gaussian, jnp.maximum(jnp.abs(c.k1), jnp.abs(c.k2))


def _curvature_terms(phi_fn: Callable, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, Gaussian, max |principal|) curvatures of one inclusion at (m, d) points, padded to a
    power-of-two bucket.

    A PyTree phi_fn (Partial, eqx.Module: grid-based inclusions) is traced, so one compilation
    serves all inclusions of a bucket; an opaque closure (analytic inclusions) would compile once
    per inclusion (~1 s), so it runs op by op instead (~0.1 s once a bucket's primitives exist).
    """
    m = points.shape[0]
    size = max(64, 1 << (m - 1).bit_length())
    padded = jnp.asarray(np.concatenate([points, np.repeat(points[-1:], size - m, axis=0)]))
    if _traceable(phi_fn):
        out = _mean_gaussian_max_abs(phi_fn, padded)
    else:
        with jax.disable_jit():
            out = _mean_gaussian_max_abs(phi_fn, padded)
    return tuple(np.asarray(v)[:m] for v in out)


def _grid_normals(dn1: np.ndarray, box, points, periodic: bool = True) -> np.ndarray:
    """Unit normals at (s, d) points from central differences of dn1 (linear interpolation);
    not periodic: one-sided differences on the border slices and the points clamped to the last
    node (a periodic difference there would take the far side's values)."""
    spacing = np.asarray(box) / np.asarray(dn1.shape)
    grad = _gradient(dn1, spacing, periodic)
    if not periodic:
        points = jnp.clip(jnp.asarray(points), 0.0, jnp.asarray((np.asarray(dn1.shape) - 1) * spacing))
    g = np.stack([np.asarray(interpolate_linear(jnp.asarray(c), box, points)) for c in grad], axis=-1)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-300)


def box_gaps(points: np.ndarray, normals: np.ndarray, box, max_angle: float = 20.0) -> np.ndarray:
    """Per surface point: the distance to the nearest box face, edge or corner that the surface
    faces (its normal within max_angle degrees of the direction to it), inf where there is none.

    Such a point borders a layer as thin as that distance between the surface and the box: a cap
    the box cuts off, or an inclusion (or its trace on a face) passing close to a plane, an edge or
    a corner without crossing it. The box faces are meshed as constraints, so the layer needs
    elements about that thin (paper section 6 sees flat elements there); the generator's box_gap
    keeps its own inclusions clear of such layers.
    A point on a box plane (a trace) faces by its normal within that plane: its trace running along
    a box edge bounds a strip of the face as thin as the distance to that edge (the sliver of an
    inclusion the box cuts along an edge: its normal, halfway between the two planes, faces neither).
    """
    pts = np.asarray(points, dtype=float)
    box = np.asarray(box, dtype=float)
    to_plane = minimum_image(pts, box)  # offset from the nearest box plane per axis
    normals = np.asarray(normals, dtype=float)
    in_plane = np.where(np.abs(to_plane) <= 1e-9 * box, 0.0, normals)
    norm = np.linalg.norm(in_plane, axis=1, keepdims=True)
    normals = np.where(norm > 1e-3, in_plane / np.maximum(norm, 1e-300), normals)
    cos_min = math.cos(math.radians(max_angle))
    gap = np.full(len(pts), np.inf)
    for k in range(1, pts.shape[1] + 1):
        for axes in itertools.combinations(range(pts.shape[1]), k):
            v = to_plane[:, list(axes)]
            dist = np.linalg.norm(v, axis=1)
            facing = np.abs(np.sum(normals[:, list(axes)] * v, axis=1)) >= cos_min * dist
            gap = np.where(facing & (dist > 0), np.minimum(gap, dist), gap)
    return gap


def edge_gap_sources(microstructure, reach_steps: float = 2.0, samples_per_step: int = 4
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain 3D boxes: points on the box edges that lie on a plane x_k = L (beyond the last sample)
    where an inclusion's level set comes closest to the edge without crossing it (a local minimum of
    its phi along the edge, positive and below reach_steps grid steps) or crosses it by less than half
    a step (a minimum in (-step/2, 0)), as (points (k, 3), inclusion ids (k,), gaps (k,) = |phi| there).

    Such a layer of matrix beside the edge, or sliver of inclusion across it, lies within the last grid
    cell, where no grid edge crosses the interface (the plane x_k = L holds no node), so no interface
    source sees it; its box-face triangles kept the box's h against a layer a fraction of a step thick
    and the volume recovery diverged there. The three edges through the origin hold samples.
    """
    ms = microstructure
    if ms.periodic or ms.dim != 3:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)
    box = np.asarray(ms.box, dtype=float)
    step = min(ms.spacing)
    points, ids, gaps = [], [], []
    for axis in range(3):
        across = [a for a in range(3) if a != axis]
        t = np.linspace(0.0, box[axis], int(np.ceil(box[axis] / step * samples_per_step)) + 1)
        for corner in itertools.product(*[(0.0, box[a]) for a in across]):
            if not any(corner):  # an edge through the origin: sampled, its grid edges' crossings are sources
                continue
            line = np.zeros((len(t), 3))
            line[:, axis], line[:, across] = t, corner
            for index, sel, vals in ms.evaluate_near(line, reach_steps * step):
                v = np.full(len(t), np.inf)
                v[sel] = vals
                before, after = np.r_[np.inf, v[:-1]], np.r_[v[1:], np.inf]
                thin = ((v > 0) & (v < reach_steps * step)) | ((v < 0) & (v > -0.5 * step))
                low = thin & (v <= before) & (v <= after)
                points.append(line[low])
                ids.append(np.full(int(low.sum()), ms.inclusions[index].id))
                gaps.append(np.abs(v[low]))
    if not points:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(points), np.concatenate(ids).astype(np.int64), np.concatenate(gaps)


def self_gaps(points: np.ndarray, ids: np.ndarray, normals: np.ndarray, dn1: np.ndarray, nearest_id: np.ndarray,
              box, periodic: bool = True, max_steps: int = 16) -> np.ndarray:
    """Per surface point: the width of the matrix in front of it when the other side is the same
    inclusion (a concave inclusion's own narrow gap: a neck between two lobes, a torus hole), inf
    where the outward ray meets another inclusion first or nothing within max_steps grid steps.

    DN2 measures the gap to the second nearest inclusion only; without this term a surface meshed
    coarser than its own gap folds onto itself. Rays march from 1.5 steps out in half steps on the
    linear interpolant of dn1 (the distance to the nearest inclusion).
    """
    pts = np.asarray(points, dtype=float)
    gap = np.full(len(pts), np.inf)
    if not len(pts):
        return gap
    spacing = np.asarray(box, dtype=float) / np.asarray(dn1.shape)
    step = float(spacing.min())
    ts = step * np.arange(1.5, max_steps + 0.25, 0.5)
    mode = "grid-wrap" if periodic else "nearest"
    for lo in range(0, len(pts), 1 << 15):  # chunks: (chunk, rays) samples stay small
        sl = slice(lo, lo + (1 << 15))
        x = pts[sl, None, :] + ts[None, :, None] * normals[sl, None, :]
        coords = (x / spacing).reshape(-1, pts.shape[1]).T
        inside = ndimage.map_coordinates(dn1, coords, order=1, mode=mode).reshape(x.shape[:2]) < 0
        owner = ndimage.map_coordinates(nearest_id, coords, order=0, mode=mode).reshape(x.shape[:2])
        hit = inside.any(axis=1)
        first = np.argmax(inside, axis=1)
        own = hit & (owner[np.arange(len(first)), first] == ids[sl])
        own &= np.linalg.norm(normals[sl], axis=1) > 0.5  # no direction (a flat spot of dn1): no ray
        gap[sl] = np.where(own, ts[first], np.inf)
    return gap


_MAX_CURVATURE_STEPS = 2.0  # |kappa| <= 2 / grid step: radii of half a step and more


def check_curvature_average(value, name: str = "curvature_average") -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0.0 <= value <= 8.0:
        raise ValueError(f"{name}: expected None or grid steps in [0, 8], got {value!r}; hint: 0 pointwise, "
                         f"{AUTO_CURVATURE_AVERAGE:g} for a field sampled from voxels, None to decide per inclusion")


def size_sources(microstructure, curvature_average: float | None = None) -> SizeSources:
    """Sources, their DN2 (or own gap, `self_gaps`), box gaps and curvature (each inclusion's own
    phi_fn, capped at 2 / grid step) for a Microstructure.

    curvature_average: grid steps over which each inclusion's mean and Gaussian curvatures are
    averaged (see `_curvature`); 0: pointwise; None (default): averaged over 1.5 steps on the
    inclusions whose interfaces ripple at the grid scale, pointwise elsewhere.
    """
    ms = microstructure
    if curvature_average is not None:
        check_curvature_average(curvature_average)
    points, ids = interface_sources(ms)
    # DN2 may be inf (a single inclusion): clamp to a length no periodic distance exceeds
    dn2_grid = np.clip(np.asarray(ms.dn2, dtype=float), 0.0, float(np.linalg.norm(ms.box)))
    kappa, pts, averaged = np.zeros(ids.size), np.asarray(points), []
    step = min(b / n for b, n in zip(ms.box, ms.grid_shape))
    for inc in ms.inclusions:
        sel = np.nonzero(ids == inc.id)[0]
        if sel.size:
            kappa[sel], was_averaged = _curvature(inc.phi_fn, pts[sel], curvature_average, step, ms.box,
                                                  ms.periodic)
            if was_averaged:
                averaged.append(inc.id)
    # radii of curvature below half a grid step are kinks of the sampled field (a thresholded or
    # first-order distance), not resolved geometry: without a cap they set h down to its floor
    kappa = np.minimum(kappa, _MAX_CURVATURE_STEPS / step)
    dn1_grid = np.asarray(ms.dn1, dtype=float)
    normals = _grid_normals(dn1_grid, ms.box, points, ms.periodic)
    own_gap = self_gaps(pts, ids, normals, dn1_grid, np.asarray(ms.nearest_id), ms.box, ms.periodic)
    dn2 = jnp.minimum(interpolate_linear(jnp.asarray(dn2_grid), ms.box, points), jnp.asarray(own_gap))
    box_gap = box_gaps(pts, normals, ms.box)
    edge_points, edge_ids, edge_gaps = edge_gap_sources(ms)
    if len(edge_points):  # layers beside a plain box's edges that no crossing sees: sources of their own
        points = jnp.concatenate([jnp.asarray(points), jnp.asarray(edge_points, dtype=jnp.asarray(points).dtype)])
        ids = np.concatenate([np.asarray(ids), edge_ids])
        dn2 = jnp.concatenate([dn2, interpolate_linear(jnp.asarray(dn2_grid), ms.box, jnp.asarray(edge_points))])
        kappa = np.concatenate([kappa, np.zeros(len(edge_points))])
        box_gap = np.concatenate([box_gap, edge_gaps])
    # finer sizes would be lost in the grid interpolation of h (and the grid resolves no thinner layer);
    # finite, so that jax.grad through box_gap / nb_el stays finite where the term is not the minimum
    box_gap = np.clip(box_gap, step / 6.0, float(np.linalg.norm(ms.box)))
    return SizeSources(points, ids, dn2, jnp.asarray(kappa), box_gap, tuple(averaged))


def size_function(microstructure, params: SizeParams | None = None, *,
                  sources: SizeSources | None = None, curvature_average: float | None = None) -> SizeField:
    """The size function h(x) of a microstructure on its level-set grid (paper section 4.2).

    Args:
        microstructure: a Microstructure (box, periodic, grid_shape, dn1, dn2, nearest_id,
            inclusions with phi_fn).
        params: :class:`SizeParams` (JAX scalars inside are differentiated through).
        sources: optional precomputed :func:`size_sources` (it does not depend on params).
        curvature_average: grid steps over which :func:`size_sources` averages the curvature (0:
            pointwise; None: 1.5 on the inclusions whose interfaces ripple at the grid scale, as the
            interpolant of a field sampled from voxels does).

    Returns:
        :class:`SizeField` on microstructure.grid_shape.

    Example:
        >>> field = size_function(ms, SizeParams(iis=0.04))
        >>> float(field.element_count())
    """
    params = SizeParams() if params is None else params
    check_params_against_box(params, microstructure.box)
    src = size_sources(microstructure, curvature_average) if sources is None else sources
    iis, nb_el, alpha, g, h_max, h_min = params.resolved()
    h0 = source_sizes(src.points, src.ids, src.dn2, src.kappa, iis, nb_el, alpha, h_min, src.box_gap)
    h = limit_gradient(h0, src.points, microstructure.box, microstructure.grid_shape, g, h_max,
                       periodic=microstructure.periodic)
    return SizeField(h, microstructure.box, src.points, h0, src.curvature_averaged)
