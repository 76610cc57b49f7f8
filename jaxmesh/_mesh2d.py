"""The conforming 2D mesher, periodic or not (paper sections 4.3-4.5 and 4.7 in 2D).

Stages (timed in ``mesh.metadata["timings"]``):

1. interfaces: every inclusion's zero contour on its own window (:mod:`._contours`), cut by the
   box lines, resampled to h along the curve, nodes projected onto phi = 0 by Newton along the
   gradient (JAX, this module);
2. box edges: nodes on the master edges x = 0, y = 0 between the crossings, copied to x = Lx, y = Ly;
3. interior nodes: periodic quadtree (:mod:`._octree`) for a size field, else a jittered hexagonal
   lattice; nodes closer than ``removal_fraction * h`` to an interface or a box edge removed;
4. a Delaunay triangulation containing every interface and box segment (:mod:`._triangulate2d`:
   encroaching interior nodes removed, remaining segments split, the rest flipped in);
5. truss relaxation (:mod:`._truss`) of the interior nodes, box-edge nodes sliding on their edge
   with periodic partners coupled, corners, crossings and interface nodes fixed (the interface
   curves were already equidistributed in stage 1); every retriangulation keeps the interface
   segments (box segments are hull edges; they are rebuilt from the node order afterwards);
6. edge flips of non-constrained edges that raise the worse quality of their two triangles, then
   Delaunay refinement of what is still below ``min_angle`` (thin gaps between an interface and a
   box edge, shallow crossings), splits mirrored on the box and projected on the interfaces.

Non-periodic microstructures (``ms.periodic`` False): the box clips every inclusion (the part
outside is dropped, never wrapped), the four box sides get their own nodes between the corners and
their crossings, box-edge nodes slide along their side alone, the interior nodes are clipped to the
box (non-periodic quadtree, or a hex lattice without wrap) and splits of box segments are not
mirrored; the result has ``periodic=False`` and no periodic pairs.

Labels: flood fill across constrained edges; each component is voted on by the triangles along its
interface segments (inside or outside that segment's own inclusion, its level set at the centroid).

Level sets reach NumPy through one jitted Newton kernel that takes the inclusion's level set as a
jaxpr plus constants, so that all inclusions of one kind (e.g. every analytic ellipse) share one
compilation.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ._contours import (
    BOX_EDGE,
    FIXED,
    INTERFACE,
    PSLG,
    Arc,
    assemble_box_pslg,
    assemble_pslg,
    box_window_axes,
    capped_axes_2d,
    capped_values,
    clip_loop,
    cut_loop,
    extract_box_loops,
    extract_loops,
    join_capped_crossings,
    rebuild_box_segments,
    resample_polyline,
    window_grid,
)
from ._errors import MeshingError
from ._surface import as_size_fn
from ._triangulate2d import (
    component_labels,
    distance_to_segments,
    conforming_delaunay,
    constrained_delaunay,
    flood_fill,
    improve_by_flips,
    interface_sides,
    orient_ccw,
    refine_bad_triangles,
)

_CHUNK = 512  # fixed batch of the jitted level-set kernel: one compilation per level-set structure


@dataclass(frozen=True)
class Mesh2DConfig:
    """Parameters of :func:`mesh_2d` (validated on construction).

    Attributes:
        window_step: contour window spacing as a fraction of the smallest h around the inclusion
            (also never coarser than the level-set grid step).
        removal_fraction: interior nodes closer than this times h to an interface or box edge go.
        min_loop_segments: fewest segments on a closed interface loop.
        interior: "auto" (quadtree for a size field when available, else hex), "hex" or "quadtree".
        jitter: random displacement of interior nodes, fraction of h (breaks co-circular sets).
        newton_iterations: projection steps onto phi = 0.
        split_rounds: segment-recovery rounds before the remaining segments are flipped in.
        relax: run the truss relaxation (stage 5).
        slide_box_nodes: box-edge nodes slide along their edge during the relaxation.
        truss: a ``TrussConfig`` for the relaxation (None: the engine's defaults with fscale 1
            and 30 retriangulations, see ``_default_truss``).
        flip_rounds: rounds of quality edge flips (stage 6).
        min_angle: Delaunay refinement target (degrees) for what the truss left below it (thin
            gaps between interfaces and box edges); geometric corners sharper than it stay.
        refine_rounds: refinement rounds (0: off). refine_min_edge: no refinement of triangles
            whose shortest edge is below this fraction of h.

    Example:
        >>> Mesh2DConfig(removal_fraction=0.6, relax=False)
    """

    window_step: float = 0.25
    removal_fraction: float = 0.5
    min_loop_segments: int = 6
    interior: str = "auto"
    jitter: float = 1e-3
    newton_iterations: int = 20
    split_rounds: int = 12
    relax: bool = True
    slide_box_nodes: bool = True
    truss: object | None = None
    flip_rounds: int = 50
    min_angle: float = 20.5
    refine_rounds: int = 20
    refine_min_edge: float = 0.05

    def __post_init__(self):
        for name in ("window_step", "removal_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 1):
                raise ValueError(f"Mesh2DConfig.{name}: expected a number in (0, 1], got {v!r}; hint: e.g. 0.25")
        if not (isinstance(self.min_angle, (int, float)) and 0 <= self.min_angle <= 30):
            raise ValueError(f"Mesh2DConfig.min_angle: expected degrees in [0, 30], got {self.min_angle!r}")
        if not (isinstance(self.refine_min_edge, (int, float)) and 0 < self.refine_min_edge <= 1):
            raise ValueError(f"Mesh2DConfig.refine_min_edge: expected a fraction in (0, 1], got {self.refine_min_edge!r}")
        for name in ("min_loop_segments", "newton_iterations", "split_rounds", "flip_rounds", "refine_rounds"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= (3 if name == "min_loop_segments" else 0)):
                raise ValueError(f"Mesh2DConfig.{name}: expected a non-negative integer (>= 3 for loops), got {v!r}")
        if self.interior not in ("auto", "hex", "quadtree"):
            raise ValueError(f"Mesh2DConfig.interior: expected 'auto', 'hex' or 'quadtree', got {self.interior!r}")
        if not (isinstance(self.jitter, (int, float)) and 0 <= self.jitter < 0.5):
            raise ValueError(f"Mesh2DConfig.jitter: expected a fraction of h in [0, 0.5), got {self.jitter!r}")


# ----------------------------------------------------------------------------- JAX level-set kernels
@functools.partial(jax.jit, static_argnums=0)
def _project_kernel(jaxpr, consts, points, free, n_iter, tol):
    """Newton along the (free part of the) gradient onto phi = 0, at most n_iter steps, until
    max |phi| <= tol; returns (points, phi before, phi after).

    The level set arrives as a jaxpr of x (2,) -> phi plus its constants: inclusions whose
    jaxprs print the same (e.g. all ellipses, whatever their parameters) share one compilation."""
    phi = lambda x: jax.core.eval_jaxpr(jaxpr, consts, x)[0]  # noqa: E731
    vg = jax.vmap(jax.value_and_grad(phi))

    def body(carry):
        i, p, _ = carry
        v, g = vg(p)
        g = g * free
        p = p - (v / jnp.maximum(jnp.sum(g * g, axis=1), 1e-300))[:, None] * g
        return i + 1, p, jnp.max(jnp.abs(v) * jnp.any(free != 0, axis=1))

    _, out, _ = jax.lax.while_loop(lambda c: (c[0] < n_iter) & (c[2] > tol), body, (0, points, jnp.inf))
    return out, jax.vmap(phi)(points), jax.vmap(phi)(out)


_STRUCTURES: dict[str, object] = {}  # printed jaxpr -> the one representative that gets compiled


class _LevelSet:
    """One inclusion's level set seen from NumPy: values and Newton projection in fixed-size chunks."""

    def __init__(self, phi_fn, n_iter: int, scale: float):
        self.n_iter = n_iter
        self.tol = 100.0 * float(jnp.finfo(jnp.result_type(float)).eps) * scale
        closed = jax.make_jaxpr(lambda x: phi_fn(x[None, :])[0])(jnp.zeros(2))
        if len(_STRUCTURES) > 256:
            _STRUCTURES.clear()
        self._jaxpr = _STRUCTURES.setdefault(str(closed.jaxpr), closed.jaxpr)
        self._consts = closed.consts

    def _run(self, points, free, n_iter):
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        free = np.broadcast_to(np.asarray(free, dtype=float), points.shape)
        m = len(points)
        outs = [np.empty((m, 2)), np.empty(m), np.empty(m)]
        for s in range(0, m, _CHUNK):
            e = min(m, s + _CHUNK)
            p = np.zeros((_CHUNK, 2))
            f = np.zeros((_CHUNK, 2))
            p[: e - s], f[: e - s] = points[s:e], free[s:e]
            p[e - s:] = points[s]  # padding rows: a valid point, frozen
            res = _project_kernel(self._jaxpr, self._consts, jnp.asarray(p), jnp.asarray(f), n_iter, self.tol)
            for o, r in zip(outs, res):
                o[s:e] = np.asarray(r)[: e - s]
        return outs

    def values(self, points) -> np.ndarray:
        return self._run(points, 0.0, 0)[1]

    def project(self, points, free=1.0) -> tuple[np.ndarray, np.ndarray]:
        """Projected points and |phi| after projection."""
        p, _, v = self._run(points, free, self.n_iter)
        return p, np.abs(v)


# ----------------------------------------------------------------------------- inputs
def _as_microstructure(microstructure):
    from .geometry._microstructure import Microstructure

    if isinstance(microstructure, Microstructure):
        ms = microstructure
    elif isinstance(microstructure, np.ndarray) and microstructure.ndim == 2:
        if np.issubdtype(microstructure.dtype, np.integer) or microstructure.dtype == bool:
            ms = Microstructure.from_labels(microstructure)
        else:
            ms = Microstructure.from_levelset(microstructure)
    else:
        raise ValueError(
            f"expected a 2D Microstructure or a 2D level-set/label array, got {type(microstructure).__name__}; "
            "hint: build one with Microstructure.from_levelset / from_labels / from_functions or load_input"
        )
    if ms.dim != 2:
        raise ValueError(f"expected a 2D microstructure, got dimension {ms.dim}; hint: mesh_2d meshes 2D RVEs only")
    if len(ms.inclusions) == 0:
        raise ValueError("expected at least one inclusion, got none; hint: check the sign (negative inside)")
    return ms


@dataclass
class _Size:
    np_fn: object  # (m, 2) -> (m,) NumPy
    jax_fn: object  # JAX callable
    h_min: float
    field: object = None  # the SizeField, if any
    desc: object = None  # float h or "field", for the metadata


def _resolve_size(ms, h, size_kwargs, curvature_average: float | None = None) -> _Size:
    box = np.asarray(ms.box, dtype=float)
    if h is None or size_kwargs:
        if h is not None:
            raise ValueError("expected either h or size-function parameters (iis, nb_el, ...), got both; "
                             "hint: pass h=None to use the size function")
        from ._pipeline import default_iis
        from ._sizing import SizeParams, size_function

        h = size_function(ms, SizeParams(**{"iis": default_iis(ms.box), **size_kwargs}),
                          curvature_average=curvature_average)
    if isinstance(h, (int, float, np.floating, np.integer)) and not isinstance(h, bool):
        h = float(h)
        if not (np.isfinite(h) and 0 < h <= 0.25 * box.min()):
            raise ValueError(
                f"expected a size h in (0, {0.25 * box.min():g}] (a quarter of the shortest box side), got {h!r}; "
                "hint: h is the target edge length, e.g. a tenth of the inclusion radius"
            )
        return _Size(lambda p: np.full(len(p), h), lambda p: jnp.full(p.shape[:-1], h, dtype=p.dtype), h, None, h)
    if hasattr(h, "h_fn") and hasattr(h, "values"):
        values = np.asarray(h.values, dtype=float)
        if values.ndim != 2 or not np.all(np.isfinite(values)) or values.min() <= 0:
            raise ValueError(f"expected a 2D size field with positive finite values, got shape {values.shape}")
        # not periodic: clamped at the last grid node, where the grid interpolation blends the far side in
        fn = h.h_fn() if ms.periodic else as_size_fn(h, ms.box, periodic=False)
        return _Size(lambda p: np.asarray(fn(jnp.asarray(p, dtype=float))), fn, float(values.min()), h, "field")
    raise ValueError(f"expected h None, a float or a SizeField, got {type(h).__name__}; hint: e.g. h=0.02")


# ----------------------------------------------------------------------------- stages 1-2
def _interfaces(ms, levels, size: _Size, cfg: Mesh2DConfig) -> tuple[PSLG, dict]:
    """Stage 1 + 2: cut, resampled, projected interface arcs and the box-edge nodes (periodic, or
    each side of a non-periodic box on its own)."""
    box = np.asarray(ms.box, dtype=float)
    grid_step = float(np.min(box / np.asarray(ms.grid_shape)))
    arcs, crossings, residual = [], [], 0.0
    for inc in ms.inclusions:
        lvl = levels[inc.id]
        lo, hi = np.asarray(inc.lower, dtype=float), np.asarray(inc.upper, dtype=float)
        probe = lo + (hi - lo) * np.stack(np.meshgrid(*[np.linspace(0, 1, 5)] * 2, indexing="ij"), -1).reshape(-1, 2)
        step = min(grid_step, cfg.window_step * float(size.np_fn(probe).min()))
        margin = 2 * grid_step + 3 * step
        capped = capped_axes_2d(lo, hi, box, margin) if ms.periodic else ()
        if ms.periodic:
            cap = 2 * step  # contours closed off beyond the box along the axes where the inclusion percolates
            origin, shape = window_grid(lo, hi, step, margin, box, capped, cap)
            ij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), -1).reshape(-1, 2)
            values = capped_values(lvl.values(origin + ij * step).reshape(tuple(shape)), origin, step, box, capped, cap)
            loops = extract_loops(values, origin, step, inc.id)
            cut = lambda *args: cut_loop(*args, keep_axes=capped)  # noqa: E731
        else:
            axes = box_window_axes(lo, hi, step, margin, box)
            xy = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
            values = lvl.values(xy).reshape(len(axes[0]), len(axes[1]))
            loops, cut = extract_box_loops(values, axes, box, inc.id), clip_loop
        pieces, cross = [], []
        for loop in loops:
            def refine(p, ax, lvl=lvl):
                return lvl.project(p, free=np.eye(2)[1 - np.asarray(ax)])[0]

            loop_pieces, loop_cross = cut(loop, box, refine, inc.id)
            pieces += [arc if arc.closed else replace(
                arc, start=(arc.start[0] + len(cross), arc.start[1]), end=(arc.end[0] + len(cross), arc.end[1]))
                for arc in loop_pieces]
            cross += loop_cross
        if capped:
            pieces, cross = join_capped_crossings(pieces, cross, capped, box, inc.id)
        mine, off = [], len(crossings)
        crossings.extend(cross)
        for arc in pieces:
            if arc.closed:
                nodes = resample_polyline(arc.points, True, size.np_fn, cfg.min_loop_segments)
                mine.append(Arc(inc.id, nodes, True))
            else:
                same_line = cross[arc.start[0]].axis == cross[arc.end[0]].axis and arc.start[1] == arc.end[1]
                nodes = resample_polyline(arc.points, False, size.np_fn, 2 if same_line else 1)
                s, e = (arc.start[0] + off, arc.start[1]), (arc.end[0] + off, arc.end[1])
                mine.append(Arc(inc.id, nodes, False, s, e))
        # one projection call for every free node of this inclusion (open arcs keep their crossings)
        free = [np.arange(len(a.points)) if a.closed else np.arange(1, len(a.points) - 1) for a in mine]
        stacked = np.concatenate([a.points[f] for a, f in zip(mine, free)])
        if len(stacked):
            projected, res = lvl.project(stacked)
            projected = _inside(projected, box)
            residual = max(residual, float(res.max()))
            at = 0
            for a, f in zip(mine, free):
                a.points[f] = projected[at : at + len(f)]
                at += len(f)
        arcs.extend(mine)
    pslg = (assemble_pslg if ms.periodic else assemble_box_pslg)(arcs, crossings, box, size.np_fn)
    return pslg, {"n_crossings": len(crossings), "n_arcs": len(arcs), "projection_residual": residual}


def _inside(points, box):
    """Keep interface nodes strictly inside the box (a near-tangent curve may graze an edge)."""
    eps = 1e-9 * box
    return np.clip(points, eps, box - eps)


def _project_fn(levels, box):
    box = np.asarray(box, dtype=float)

    def project(points, ids):
        out = np.array(points, dtype=float, copy=True)
        for i in np.unique(ids):
            sel = ids == i
            out[sel] = _inside(levels[int(i)].project(out[sel])[0], box)
        return out

    return project


# ----------------------------------------------------------------------------- stage 3
def _interior_nodes(ms, pslg: PSLG, size: _Size, cfg: Mesh2DConfig, rng) -> np.ndarray:
    """Free nodes: quadtree or jittered hex lattice, away from interfaces, box edges and constrained nodes."""
    box = np.asarray(ms.box, dtype=float)
    pts = None
    if size.field is not None and cfg.interior in ("auto", "quadtree"):
        try:
            from ._octree import periodic_octree_nodes
        except ImportError:
            if cfg.interior == "quadtree":
                raise
        else:
            # non-periodic: the clamped size (as the mesher sees it), not the grid's periodic blend
            h_grid = np.asarray(size.field.values) if ms.periodic else size.np_fn
            pts = np.asarray(periodic_octree_nodes(h_grid, tuple(box), periodic=ms.periodic).points, dtype=float)
    if pts is None:
        pts = _graded_hex(box, size, rng, periodic=ms.periodic)
    hp = size.np_fn(pts)
    pts = pts + cfg.jitter * hp[:, None] * rng.standard_normal(pts.shape)
    # interfaces and box edges are both segments of the PSLG: one distance test for all
    dist = distance_to_segments(pts, pslg.points, pslg.segments, 0.1 * size.h_min)
    keep = (dist > cfg.removal_fraction * hp) & np.all((pts > 0) & (pts < box), axis=1)
    return pts[keep]


def _hex(box, s, rng, periodic: bool = True) -> np.ndarray:
    """Hexagonal lattice of spacing s over the box, randomly offset; periodic: rows wrap in x,
    else the lattice overhangs the box by a spacing and is clipped to it (no gap along the sides)."""
    dy = s * np.sqrt(3.0) / 2.0
    if not periodic:
        rows = np.arange(-dy, box[1] + dy, dy) + rng.uniform(0, dy)
        xs = np.arange(-s, box[0] + s, s) + rng.uniform(0, s)
        pts = np.concatenate([np.stack([xs + 0.5 * s * (r % 2), np.full(xs.size, y)], 1) for r, y in enumerate(rows)])
        return pts[np.all((pts >= 0) & (pts <= box), axis=1)]
    rows = np.arange(0.0, box[1], dy) + rng.uniform(0, dy)
    xs = np.arange(0.0, box[0], s) + rng.uniform(0, s)
    return np.concatenate([np.stack([(xs + 0.5 * s * (r % 2)) % box[0], np.full(xs.size, y)], 1)
                           for r, y in enumerate(rows[rows < box[1]])])


def _graded_hex(box, size: _Size, rng, ratio: float = 1.5, periodic: bool = True) -> np.ndarray:
    """Hex lattices of spacing h_min * ratio^k, each kept where h falls in [s_k, s_k * ratio);
    then, of two nodes closer than 0.7 min(h), the coarser goes. Uniform h: one plain lattice."""
    if size.field is None:
        return _hex(box, size.h_min, rng, periodic)
    h_max = float(np.max(np.asarray(size.field.values)))
    parts, s = [], size.h_min
    while True:
        p = _hex(box, s, rng, periodic)
        hp = size.np_fn(p)
        last = s * ratio > h_max
        parts.append(p[(hp >= s / (1 + 1e-9)) & ((hp < s * ratio) | last)] if s > size.h_min else p[hp < s * ratio])
        if last:
            break
        s *= ratio
    pts = np.concatenate(parts)
    hp = size.np_fn(pts)
    pairs = cKDTree(pts).query_pairs(0.7 * float(hp.max()), output_type="ndarray")
    d = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
    close = pairs[d < 0.7 * np.minimum(hp[pairs[:, 0]], hp[pairs[:, 1]])]
    drop = np.where(hp[close[:, 0]] > hp[close[:, 1]], close[:, 0], close[:, 1])
    return np.delete(pts, np.unique(drop), axis=0)


# ----------------------------------------------------------------------------- stages 5-6, labels
def _default_truss():
    """The engine's defaults (alpha ramp, eq. 21) with fscale 1 and 30 retriangulations. The box is
    open (box nodes slide, no boundary projection as in distmesh), so the outward pressure of
    fscale 1.2 pushes interior nodes between box nodes and out of the box; measured on 30-ellipse
    RVEs, fscale 1 converges (mean q 0.98 uniform h, 0.92-0.94 graded) where 1.2 diverges."""
    from ._truss import TrussConfig

    return TrussConfig(fscale=1.0, max_retriangulations=30)


def _relax(points, pslg: PSLG, size: _Size, cfg: Mesh2DConfig):
    """Stage 5: truss relaxation with the constrained segments kept at every retriangulation."""
    from ._truss import make_constraints, relax

    n, box = len(points), np.asarray(pslg.box, dtype=float)
    kind = np.zeros(n, dtype=np.int8)
    kind[: pslg.n_points] = pslg.node_kind
    axis = np.full(n, -1, dtype=np.int64)
    axis[: pslg.n_points] = pslg.node_axis
    fixed = (kind == FIXED) | (kind == INTERFACE) | ((kind == BOX_EDGE) & (not cfg.slide_box_nodes))
    locked = np.zeros((n, 2), dtype=bool)
    on_box = np.nonzero(kind == BOX_EDGE)[0]
    locked[on_box, axis[on_box]] = True
    pairs = [(int(i), int(j), np.eye(2)[a] * box[a]) for a, pp in pslg.periodic_pairs.items() for i, j in pp]
    constraints = make_constraints(n, 2, fixed=fixed, locked_axes=locked, periodic_pairs=pairs)
    # box segments are hull edges of any Delaunay triangulation of the box; leaving them out lets
    # box nodes slide past one another (rebuild_box_segments restores them afterwards)
    segments = pslg.segments[pslg.segment_inclusion > 0]

    def triangulate(p):
        return constrained_delaunay(np.asarray(p, dtype=float), segments)

    res = relax(points, triangulate, size.jax_fn, constraints, config=cfg.truss or _default_truss(), box=tuple(box))
    if res.stop_reason == "diverged":  # keep the conforming start rather than a broken mesh
        return points, {"stop_reason": "diverged (kept the unrelaxed nodes)", "iterations": int(res.n_iterations),
                        "retriangulations": int(res.n_retriangulations)}
    out = np.array(res.points, dtype=float, copy=True)
    free = kind == 0
    eps = 1e-6 * size.h_min
    out[free] = np.clip(out[free], eps, box - eps)  # a free node never leaves the box
    if not pslg.periodic:  # a side node stays exactly on its side, between the corners
        a = axis[on_box]
        out[on_box, a] = points[on_box, a]
        out[on_box, 1 - a] = np.clip(out[on_box, 1 - a], eps, box[1 - a] - eps)
    info = {"stop_reason": res.stop_reason, "iterations": int(res.n_iterations),
            "retriangulations": int(res.n_retriangulations)}
    return out, info


def _labels(levels, points, tri, pslg: PSLG) -> np.ndarray:
    """Inclusion id per triangle: flood fill across free edges; each component is voted on by the
    triangles along its interface segments, inside (phi < 0) or outside the segment's own inclusion."""
    n_comp, comp = flood_fill(tri, pslg.segments, len(points))
    t, inc = interface_sides(tri, pslg.segments, pslg.segment_inclusion, len(points))
    cent = points[tri[t]].mean(axis=1)
    phi = np.empty(len(t))
    for i in np.unique(inc):
        sel = inc == i
        phi[sel] = levels[int(i)].values(cent[sel])
    lab, dissent = component_labels(comp[t], np.where(phi < 0, inc, 0), np.abs(phi) + 1e-300, n_comp)
    if np.any(dissent > 0.2):
        bad = int(np.argmax(dissent))
        raise MeshingError("labels", f"a region mixes inclusions (component {bad}); an interface is not closed",
                           int(lab[bad]))
    return lab[comp]


def mesh_2d(
    microstructure,
    h=None,
    *,
    config: Mesh2DConfig | None = None,
    seed: int = 0,
    iis: float | None = None,
    nb_el: float | None = None,
    curv_alpha: float | None = None,
    grad: float | None = None,
    h_max: float | None = None,
    curvature_average: float | None = None,
):
    """Conforming, labelled triangle mesh of a 2D microstructure, periodic or not (as it is).

    Args:
        microstructure: a 2D ``Microstructure`` (or a 2D level-set array, negative inside, or an
            integer label image, turned into a periodic one). Non-periodic: the mesh covers
            exactly the box, inclusions cut by it are clipped, there are no periodic pairs.
        h: target edge length: a float (uniform), a ``SizeField`` (``size_function``), or None for
            the size function with ``SizeParams(iis=..., nb_el=..., curv_alpha=..., grad=..., h_max=...)``
            (only the given ones; the others take SizeParams' defaults, and iis 0.05 times the box's mean
            side, as `MeshConfig`).
        config: :class:`Mesh2DConfig`. seed: random seed of the interior node jitter.
        curvature_average: grid steps over which the size function averages the curvature (see
            `size_function`; 0: pointwise; None: where the interface ripples at the grid scale).
    Returns:
        ``Mesh`` with triangles (counter-clockwise), ``inclusion_id`` per triangle (0 = matrix),
        ``periodic`` as the microstructure, ``periodic_pairs`` {0: (x=0 node, x=Lx node), 1: (y=0
        node, y=Ly node)} ({} when not periodic) and metadata (timings per stage, counts,
        relaxation report).

    Example:
        >>> ms = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5]), 0.2)], (1.0, 1.0), (64, 64))
        >>> mesh = mesh_2d(ms, h=0.025)
    """
    from ._mesh import Mesh

    cfg = Mesh2DConfig() if config is None else config
    if not isinstance(cfg, Mesh2DConfig):
        raise ValueError(f"expected config a Mesh2DConfig, got {type(cfg).__name__}; hint: Mesh2DConfig(...)")
    timings, t0 = {}, time.perf_counter()

    def lap(name):
        nonlocal t0
        now = time.perf_counter()
        timings[name] = now - t0
        t0 = now

    ms = _as_microstructure(microstructure)
    kw = {k: v for k, v in dict(iis=iis, nb_el=nb_el, curv_alpha=curv_alpha, grad=grad, h_max=h_max).items()
          if v is not None}
    size = _resolve_size(ms, h, kw, curvature_average)
    rng = np.random.default_rng(seed)
    box = np.asarray(ms.box, dtype=float)
    lap("size")
    levels = {inc.id: _LevelSet(inc.phi_fn, cfg.newton_iterations, float(box.max())) for inc in ms.inclusions}
    pslg, info = _interfaces(ms, levels, size, cfg)
    lap("interfaces_and_box")
    interior = _interior_nodes(ms, pslg, size, cfg, rng)
    lap("interior_nodes")
    pslg, interior, tri, rec = conforming_delaunay(pslg, interior, _project_fn(levels, box), max_rounds=cfg.split_rounds)
    points = np.vstack([pslg.points, interior])
    lap("triangulation")
    relax_info = {}
    if cfg.relax:
        points, relax_info = _relax(points, pslg, size, cfg)
        pslg = rebuild_box_segments(replace(pslg, points=points[: pslg.n_points]))
        tri = constrained_delaunay(points, pslg.segments)
    lap("relaxation")
    tri, n_flips = improve_by_flips(points, tri, pslg.segments, max_rounds=cfg.flip_rounds)
    refined = {}
    if cfg.refine_rounds:
        pslg, interior, tri, refined = refine_bad_triangles(
            pslg, points[pslg.n_points:], tri, _project_fn(levels, box), size.np_fn,
            min_angle=cfg.min_angle, min_edge=cfg.refine_min_edge, max_rounds=cfg.refine_rounds,
        )  # fmt: skip
        points = np.vstack([pslg.points, interior])
        if refined["rounds"]:
            tri, n_more = improve_by_flips(points, tri, pslg.segments, max_rounds=cfg.flip_rounds,
                                           angle_floor=cfg.min_angle)
            n_flips += n_more
    tri = orient_ccw(points, tri)
    lap("flips_and_refinement")
    inclusion_id = _labels(levels, points, tri, pslg)
    lap("labels")
    metadata = {
        "mesher": "mesh_2d",
        "h": size.desc,
        "seed": seed,
        "timings": timings,
        "counts": {
            "points": len(points), "triangles": len(tri), "constrained_nodes": pslg.n_points,
            "interior_nodes": len(interior), "segments": len(pslg.segments), **info, **rec, "quality_flips": n_flips,
            "refinement": refined,
        },
        "relaxation": relax_info,
    }
    pairs = {a: np.asarray(p, dtype=np.int64) for a, p in pslg.periodic_pairs.items()}
    return Mesh(points, tri, inclusion_id, tuple(float(b) for b in box), periodic=ms.periodic, periodic_pairs=pairs,
                metadata=metadata)


def mesh_file_2d(input_path, output_path, *, box=None, h=None, plot=None, periodic=None):
    """Read a 2D input, mesh it, validate, write the mesh (atomically) and optionally a PNG.

    Args:
        input_path: any input ``load_input`` reads (.npy, .npz, .tif, ...).
        output_path: mesh file, format by extension (``Mesh.write``).
        box: optional (Lx, Ly). h: as in :func:`mesh_2d`. plot: optional PNG path.
        periodic: overrides the file's periodic flag (None: the file's, else True; False: mesh a
            non-periodic box).
    Returns:
        The ``Mesh``. Raises MeshingError (stage "validate") without writing anything when the
        mesh fails validation.
    """
    from ._validate import validate
    from .io._read import load_input

    ms = load_input(Path(input_path), box=box, periodic=periodic)
    mesh = mesh_2d(ms, h=h)
    report = validate(mesh, ms)
    mesh.metadata["validation"] = report.to_dict()
    report.raise_if_invalid()
    mesh.write(output_path)
    if plot is not None:
        from ._plot import plot_mesh

        plot_mesh(mesh, plot)
    return mesh
