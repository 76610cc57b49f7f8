"""Truss relaxation driver: jitted lax.scan of forward-Euler steps, NumPy topology between scans.

Paper section 3.2 (stop rules, retriangulation, dt retry), 4.4 (alpha ramp, periodic averaging,
surface constraint), 4.7 (ball-vertex springs). DESIGN.md section 1 "The truss engine".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._constraints import NodeConstraints, impose_periodicity, truss_step
from ._energy import alpha_schedule, bar_lengths, size_at, target_lengths
from ._topology import bucket_capacity, edges_from_simplices, pad_rows

__all__ = ["TrussConfig", "RelaxResult", "relax", "relax_fixed_topology"]

# status codes of a scan chunk
RUNNING, CONVERGED, RETRIANGULATE, MAX_ITERATIONS, DIVERGED = 0, 1, 2, 3, 4
_TRACES = {"chunk": 0}  # incremented at trace time: tests check that retriangulation reuses the compiled scan


@dataclasses.dataclass(frozen=True)
class TrussConfig:
    """Parameters of the truss relaxation (paper section 3.2 defaults), validated on creation.

    Attributes:
        dt: forward-Euler time step (> 0).
        fscale: target lengths are fscale times the average current length (distmesh, >= 1 usually).
        alpha_ramp_iterations: iterations over which alpha rises exponentially to 1 (0: alpha = 1).
        alpha_start: alpha at iteration 0 (eq. 21; ~0 starts as Laplacian-like smoothing).
        repulsive_cutoff: zero force in bars longer than alpha * l0 (eq. 8).
        max_iterations: Euler steps per triangulation.
        max_retriangulations: retriangulations per attempt.
        retriangulate_tol: retriangulate when a bar length changed by more than this fraction
            since the last triangulation.
        stop_tol: converged when, after the alpha ramp, no bar length changes by more than this
            fraction in one step.
        dt_retry_factor: dt multiplier for a retry after divergence or non-convergence.
        max_dt_retries: number of such retries.
        scan_chunk: Euler steps per jitted lax.scan call between host-side checks.
        scale_exponent: exponent of the distmesh length scaling; None = the mesh dimension
            (simplex columns - 1 in relax, the point dimension in relax_fixed_topology).
        newton_steps: Newton projections onto phi = 0 after each move.
        box_tolerance: a node further than box_tolerance * L outside [0, L] means divergence.
        ball_vertex_stiffness: > 0 adds ball-vertex springs (tets only, section 4.7); keep
            dt * stiffness * (springs at a node) below ~1 or the explicit steps oscillate.
        ball_vertex_quality: tets with quality below it get a ball-vertex spring.
        final_triangulation: triangulate the final points once more for the returned simplices.
    """

    dt: float = 0.2
    fscale: float = 1.2
    alpha_ramp_iterations: int = 30
    alpha_start: float = 1e-3
    repulsive_cutoff: bool = False
    max_iterations: int = 50
    max_retriangulations: int = 10
    retriangulate_tol: float = 0.1
    stop_tol: float = 1e-3
    dt_retry_factor: float = 0.2
    max_dt_retries: int = 1
    scan_chunk: int = 10
    scale_exponent: int | None = None
    newton_steps: int = 2
    box_tolerance: float = 1e-6
    ball_vertex_stiffness: float = 0.0
    ball_vertex_quality: float = 0.3
    final_triangulation: bool = True

    def __post_init__(self):
        def bad(name, want):
            v = getattr(self, name)
            raise ValueError(f"TrussConfig.{name}: expected {want}, got {v!r}. Hint: see the TrussConfig docstring.")

        def is_int(v):
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

        for name in ("dt", "fscale", "retriangulate_tol", "stop_tol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                bad(name, "a finite number > 0")
        if not (0 < self.alpha_start <= 1):
            bad("alpha_start", "a number in (0, 1]")
        if not (0 < self.dt_retry_factor <= 1):
            bad("dt_retry_factor", "a number in (0, 1]")
        for name in ("alpha_ramp_iterations", "max_retriangulations", "max_dt_retries", "newton_steps"):
            if not (is_int(getattr(self, name)) and getattr(self, name) >= 0):
                bad(name, "an integer >= 0")
        for name in ("max_iterations", "scan_chunk"):
            if not (is_int(getattr(self, name)) and getattr(self, name) >= 1):
                bad(name, "an integer >= 1")
        if self.scale_exponent is not None and not (is_int(self.scale_exponent) and self.scale_exponent >= 1):
            bad("scale_exponent", "None or an integer >= 1")
        if not (self.box_tolerance >= 0):
            bad("box_tolerance", "a number >= 0")
        if not (self.ball_vertex_stiffness >= 0):
            bad("ball_vertex_stiffness", "a number >= 0")
        if not (0 < self.ball_vertex_quality <= 1):
            bad("ball_vertex_quality", "a number in (0, 1]")


@dataclasses.dataclass
class RelaxResult:
    """Outcome of :func:`relax`.

    Attributes:
        points: (n, d) NumPy final points.
        simplices: (m, k) NumPy simplices of the final points (from triangulate_fn).
        n_iterations: Euler steps taken in the returned attempt.
        n_retriangulations: retriangulations in the returned attempt.
        stop_reason: "converged" | "max_retriangulations" | "max_iterations" | "diverged".
        dt: time step of the returned attempt.
        history: one dict per scan chunk (attempt, dt, triangulation, iteration, steps, alpha,
            max_move, max_change, status, n_bars, capacity).
    """

    points: np.ndarray
    simplices: np.ndarray
    n_iterations: int
    n_retriangulations: int
    stop_reason: str
    dt: float
    history: list


class _Static(NamedTuple):  # hashable: static under eqx.filter_jit
    n_steps: int
    cutoff: bool
    power: int
    n_newton: int
    ball_vertex: bool


def _check_points(points, constraints):
    if not isinstance(constraints, NodeConstraints):
        raise ValueError(
            f"constraints: expected NodeConstraints, got {type(constraints).__name__}. Hint: make_constraints(n, d)."
        )
    if points.ndim != 2 or points.shape != constraints.locked_axes.shape:
        raise ValueError(
            f"points: expected shape {tuple(constraints.locked_axes.shape)} to match the constraints, "
            f"got {tuple(points.shape)}. Hint: make_constraints(len(points), points.shape[1], ...)."
        )


def relax_fixed_topology(
    points: Float[Array, "n d"],
    bars: Int[Array, "m 2"],
    bar_mask: Bool[Array, " m"],
    h_fn: Callable,
    constraints: NodeConstraints,
    n_steps: int,
    *,
    surface_phi_fn: Callable | None = None,
    config: TrussConfig = TrussConfig(),
    alpha0=1.0,
    h_params: Any = None,
    phi_params: Any = None,
    tets: Int[Array, "t 4"] | None = None,
    tet_mask: Bool[Array, " t"] | None = None,
) -> Float[Array, "n d"]:
    """Run ``n_steps`` constrained Euler steps at fixed topology in one lax.scan (no stop rules).

    Pure and jit-able; differentiable with jax.grad w.r.t. points, h_params / an eqx.Module
    h_fn, phi_params / an eqx.Module surface_phi_fn (or anything they close over).

    Args:
        points: (n, d) initial points. bars: (m, 2) int, bar_mask: (m,) bool (padding False).
        h_fn: size function points (k, d) -> (k,), or (points, h_params) -> (k,).
        constraints: NodeConstraints for n nodes.
        n_steps: number of steps (static).
        surface_phi_fn: level set for on_surface nodes, points -> (k,) (or (points, phi_params)).
        config: TrussConfig (dt, fscale, alpha ramp length, cutoff, newton_steps, ball vertex).
        alpha0: alpha at step 0; alpha ramps exponentially to 1 over config.alpha_ramp_iterations
            (1.0: no ramp).
        tets, tet_mask: (t, 4) tets and mask for ball-vertex springs (config.ball_vertex_stiffness > 0).

    Returns:
        final points (n, d), a JAX array.

    Example:
        >>> p = relax_fixed_topology(p0, bars, mask, lambda x: jnp.ones(len(x)), cons, 20)
    """
    _check_points(points, constraints)
    if int(n_steps) != n_steps or n_steps < 0:
        raise ValueError(f"n_steps: expected an integer >= 0, got {n_steps!r}.")
    power = config.scale_exponent or points.shape[1]
    use_bv = tets is not None and config.ball_vertex_stiffness > 0
    if use_bv and tet_mask is None:
        tet_mask = jnp.ones(tets.shape[0], dtype=bool)

    def body(p, i):
        alpha = alpha_schedule(i, config.alpha_ramp_iterations, alpha0)
        p = truss_step(
            p, alpha, bars, bar_mask, constraints, config.dt, h_fn, h_params, surface_phi_fn, phi_params,
            fscale=config.fscale, power=power, cutoff=config.repulsive_cutoff, n_newton=config.newton_steps,
            tets=tets if use_bv else None, tet_mask=tet_mask if use_bv else None,
            ball_vertex_stiffness=config.ball_vertex_stiffness, ball_vertex_quality=config.ball_vertex_quality,
        )  # fmt: skip
        return p, None

    out, _ = jax.lax.scan(body, points, jnp.arange(int(n_steps)))
    return out


@eqx.filter_jit
def _run_chunk(p, bars, bar_mask, l_ref, l_norm, cons, tets, tet_mask, sc, h_fn, h_params, phi_fn, phi_params, st: _Static):
    """Up to st.n_steps Euler steps; the state freezes at the first stop event (status != RUNNING)."""
    _TRACES["chunk"] += 1

    def body(carry, _):
        p, status, it, li = carry
        alpha = alpha_schedule(it, sc["ramp"], sc["alpha_start"])

        def step(q):
            return truss_step(
                q, alpha, bars, bar_mask, cons, sc["dt"], h_fn, h_params, phi_fn, phi_params,
                fscale=sc["fscale"], power=st.power, cutoff=st.cutoff, n_newton=st.n_newton,
                tets=tets if st.ball_vertex else None, tet_mask=tet_mask,
                ball_vertex_stiffness=sc["bv_k"], ball_vertex_quality=sc["bv_q"],
            )  # fmt: skip

        # after a stop event the chunk's remaining steps are skipped, not computed and discarded
        new = jax.lax.cond(status == RUNNING, step, lambda q: q, p)
        l_old, l_new = bar_lengths(p, bars), bar_lengths(new, bars)
        move = jnp.max(jnp.where(bar_mask, jnp.abs(l_new - l_old) / l_norm, 0.0))
        change = jnp.max(jnp.where(bar_mask, jnp.abs(l_new - l_ref) / l_norm, 0.0))
        bad = ~jnp.all(jnp.isfinite(new)) | jnp.any((new < sc["lo"]) | (new > sc["hi"]))
        running = status == RUNNING
        ok = running & ~bad
        event = jnp.select(
            [bad, (alpha >= 1.0) & (move < sc["stop_tol"]), change > sc["retri_tol"], li + 1 >= sc["max_it"]],
            [DIVERGED, CONVERGED, RETRIANGULATE, MAX_ITERATIONS],
            RUNNING,
        )
        status = jnp.where(running, event, status)
        p = jnp.where(ok, new, p)
        nan = jnp.asarray(jnp.nan, p.dtype)
        trace = (jnp.where(ok, alpha, nan), jnp.where(ok, move, nan), jnp.where(ok, change, nan))
        return (p, status, it + ok, li + ok), trace

    init = (p, jnp.asarray(RUNNING, jnp.int32), sc["it0"], sc["li0"])
    (p, status, it, li), trace = jax.lax.scan(body, init, None, length=st.n_steps)
    return p, status, it, li, trace


@eqx.filter_jit
def _reference_lengths(p, bars, bar_mask, h_fn, h_params, power: int):
    """Bar lengths at a triangulation, and the target lengths (fscale 1) that normalise their
    changes: the tiny bars of a random start would otherwise trigger a retriangulation per step."""
    l_norm, _ = target_lengths(p, bars, bar_mask, h_fn, h_params, fscale=1.0, power=power)
    return bar_lengths(p, bars), l_norm


def _triangulate(triangulate_fn, points_np, n):
    simplices = np.asarray(triangulate_fn(points_np))
    if simplices.ndim != 2 or simplices.shape[0] == 0 or simplices.shape[1] < 2:
        raise ValueError(
            f"triangulate_fn: expected a non-empty (m, k) integer array of simplices, got shape {simplices.shape}."
        )
    if not np.issubdtype(simplices.dtype, np.integer) or simplices.min() < 0 or simplices.max() >= n:
        raise ValueError(f"triangulate_fn: expected integer node indices in [0, {n}), got dtype {simplices.dtype}.")
    return simplices


def relax(
    points,
    triangulate_fn: Callable[[np.ndarray], np.ndarray],
    h_fn: Callable,
    constraints: NodeConstraints,
    *,
    surface_phi_fn: Callable | None = None,
    config: TrussConfig = TrussConfig(),
    h_params: Any = None,
    phi_params: Any = None,
    box=None,
) -> RelaxResult:
    """Relax a point set with the truss analogy, retriangulating between jitted scans.

    Loop (paper 3.2): triangulate -> bars (unique edges, padded to a power-of-two capacity that
    only grows, so the compiled scan is reused) -> chunks of ``scan_chunk`` Euler steps until a
    stop event -> converged: done; a bar changed by > retriangulate_tol or max_iterations
    reached: retriangulate (at most max_retriangulations times); NaN or a node outside ``box``:
    diverged. A diverged or unconverged attempt restarts from the initial points with
    dt * dt_retry_factor, at most max_dt_retries times; the returned attempt is the last one that
    did not diverge (else the last one). The alpha ramp runs over the global iteration count of
    an attempt, and convergence is only declared once alpha = 1.

    Bar length changes (retriangulate_tol, stop_tol) are measured relative to each bar's target
    length at the last triangulation (scale * h at its midpoint), not to its current length. A
    retriangulation that returns exactly the same bars only resets the reference lengths and is
    not counted. The scan is compiled once per (n, d, dtype, bar capacity, callables): pass the
    same ``h_fn`` / ``surface_phi_fn`` objects (module-level functions or eqx.Modules whose
    arrays are traced) to reuse it across calls; a fresh lambda per call re-traces.

    Args:
        points: (n, d) initial points (periodic translates are re-imposed at the start).
        triangulate_fn: NumPy callable points (n, d) -> simplices (m, k) (Delaunay, constrained,
            flips...). Its simplices give the bars and the returned cells.
        h_fn: JAX size function points (k, d) -> (k,) > 0, or (points, h_params) -> (k,); may be an
            eqx.Module.
        constraints: NodeConstraints for the n nodes.
        surface_phi_fn: JAX level set (k, d) -> (k,) for on_surface nodes (or (points, phi_params)).
        config: TrussConfig.
        h_params, phi_params: optional pytrees passed to h_fn / surface_phi_fn (arrays are traced).
        box: optional (d,) lengths of [0, L]; a node leaving it (beyond box_tolerance) = divergence.

    Returns:
        RelaxResult.

    Example:
        >>> res = relax(p0, lambda p: Delaunay(p).simplices, lambda x: jnp.full(len(x), 0.1), cons)
    """
    if not callable(triangulate_fn) or not callable(h_fn):
        raise ValueError("triangulate_fn and h_fn: expected callables. Hint: triangulate_fn(points) -> simplices.")
    if surface_phi_fn is not None and not callable(surface_phi_fn):
        raise ValueError(f"surface_phi_fn: expected a callable or None, got {type(surface_phi_fn).__name__}.")
    if not isinstance(config, TrussConfig):
        raise ValueError(f"config: expected TrussConfig, got {type(config).__name__}.")
    p0 = jnp.asarray(points)
    if not jnp.issubdtype(p0.dtype, jnp.floating):
        p0 = p0.astype(jnp.result_type(float))
    _check_points(p0, constraints)
    n, d = p0.shape
    if not bool(jnp.all(jnp.isfinite(p0))):
        raise ValueError("points: expected finite coordinates, got NaN or inf.")
    if surface_phi_fn is None and bool(jnp.any(constraints.on_surface)):
        raise ValueError("surface_phi_fn: some nodes are on_surface but no level set was given. Hint: pass surface_phi_fn.")
    h0 = np.asarray(size_at(h_fn, p0, h_params))
    if not (np.all(np.isfinite(h0)) and np.all(h0 > 0)):
        raise ValueError(f"h_fn: expected finite sizes > 0 at the points, got min {np.nanmin(h0)!r}.")
    lo = jnp.full((d,), -jnp.inf, p0.dtype)
    hi = jnp.full((d,), jnp.inf, p0.dtype)
    if box is not None:
        b = np.asarray(box, dtype=float).reshape(-1)
        if b.shape != (d,) or not np.all(b > 0):
            raise ValueError(f"box: expected {d} positive lengths, got {np.asarray(box).tolist()}.")
        lo, hi = jnp.asarray(-config.box_tolerance * b, p0.dtype), jnp.asarray((1 + config.box_tolerance) * b, p0.dtype)
    p0 = impose_periodicity(p0, constraints)
    cons = jax.tree_util.tree_map(lambda x: x.astype(p0.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, constraints)

    dt = float(config.dt)
    attempts = []
    history: list = []
    for attempt in range(config.max_dt_retries + 1):
        res = _attempt(p0, cons, triangulate_fn, h_fn, h_params, surface_phi_fn, phi_params, config, dt, lo, hi)
        for rec in res[-1]:
            rec["attempt"] = attempt
        history.extend(res[-1])
        attempts.append(res)
        if res[1] == "converged":
            break
        dt *= config.dt_retry_factor
    ok = [a for a in attempts if a[1] != "diverged"]
    p, reason, n_it, n_retri, simplices, dt_used, _ = ok[-1] if ok else attempts[-1]
    p_np = np.asarray(p)
    if config.final_triangulation:
        simplices = _triangulate(triangulate_fn, p_np, n)
    return RelaxResult(p_np, simplices, n_it, n_retri, reason, dt_used, history)


def _attempt(p0, cons, triangulate_fn, h_fn, h_params, phi_fn, phi_params, config, dt, lo, hi):
    """One run from p0 at a given dt: returns (points, reason, iterations, retriangulations, simplices, dt, history).

    A retriangulation request whose new triangulation has exactly the old bars only resets the
    reference lengths: it is not a topology change and is not counted (the iteration counter of
    the triangulation keeps running, so max_iterations still bounds the work).
    """
    n, d = p0.shape
    dtype = p0.dtype
    p, it, li, n_retri = p0, 0, 0, 0
    bar_cap = tet_cap = None
    history = []
    # NumPy scalars: no eager JAX dispatch per chunk (they are traced, so dt retries reuse the scan)
    scalars = {
        "dt": np.asarray(dt, dtype), "fscale": np.asarray(config.fscale, dtype),
        "ramp": np.asarray(config.alpha_ramp_iterations, np.int32),
        "alpha_start": np.asarray(config.alpha_start, dtype),
        "stop_tol": np.asarray(config.stop_tol, dtype), "retri_tol": np.asarray(config.retriangulate_tol, dtype),
        "max_it": np.asarray(config.max_iterations, np.int32), "lo": lo, "hi": hi,
        "bv_k": np.asarray(config.ball_vertex_stiffness, dtype), "bv_q": np.asarray(config.ball_vertex_quality, dtype),
    }  # fmt: skip
    simplices = _triangulate(triangulate_fn, np.asarray(p), n)
    edges = edges_from_simplices(simplices, n)
    while True:
        # at least 3 bars per node (a triangulated surface has about 3): the capacity then follows the
        # node count, so calls of one node capacity share a compilation
        bar_cap = bucket_capacity(max(len(edges), 3 * n), current=bar_cap)
        bars_np, mask_np = pad_rows(edges, bar_cap)
        bars, bar_mask = jnp.asarray(bars_np), jnp.asarray(mask_np)
        use_bv = config.ball_vertex_stiffness > 0 and simplices.shape[1] == 4 and d == 3
        tets = tet_mask = None
        if use_bv:
            tet_cap = bucket_capacity(len(simplices), current=tet_cap)
            t_np, tm_np = pad_rows(simplices, tet_cap)
            tets, tet_mask = jnp.asarray(t_np), jnp.asarray(tm_np)
        st = _Static(config.scan_chunk, config.repulsive_cutoff, config.scale_exponent or simplices.shape[1] - 1,
                     config.newton_steps, use_bv)  # fmt: skip
        l_ref, l_norm = _reference_lengths(p, bars, bar_mask, h_fn, h_params, st.power)
        status = RUNNING
        while status == RUNNING:
            sc = dict(scalars, it0=np.asarray(it, np.int32), li0=np.asarray(li, np.int32))
            p, status_a, it_a, li_a, (alphas, moves, changes) = _run_chunk(
                p, bars, bar_mask, l_ref, l_norm, cons, tets, tet_mask, sc, h_fn, h_params, phi_fn, phi_params, st
            )
            status, steps = int(status_a), int(it_a) - it
            it, li = int(it_a), int(li_a)
            last = (lambda a: float(np.asarray(a)[steps - 1])) if steps else (lambda a: float("nan"))
            history.append({
                "dt": dt, "triangulation": n_retri, "iteration": it, "steps": steps,
                "alpha": last(alphas), "max_move": last(moves), "max_change": last(changes),
                "status": ("running", "converged", "retriangulate", "max_iterations", "diverged")[status],
                "n_bars": len(edges), "capacity": bar_cap,
            })  # fmt: skip
        if status == CONVERGED:
            return p, "converged", it, n_retri, simplices, dt, history
        if status == DIVERGED:
            return p, "diverged", it, n_retri, simplices, dt, history
        new_simplices = _triangulate(triangulate_fn, np.asarray(p), n)
        new_edges = edges_from_simplices(new_simplices, n)
        if status == RETRIANGULATE and np.array_equal(new_edges, edges):
            simplices = new_simplices  # same bars: new reference lengths only
            continue
        if n_retri >= config.max_retriangulations:
            reason = "max_iterations" if status == MAX_ITERATIONS else "max_retriangulations"
            return p, reason, it, n_retri, simplices, dt, history
        n_retri, li = n_retri + 1, 0
        simplices, edges = new_simplices, new_edges
