"""Inclusion surfaces (paper 4.4): per-inclusion marching cubes, projection onto phi = 0,
refinement / flips / truss relaxation, cutting by the box planes and wrapping into the box.

Each inclusion is meshed in its own UNWRAPPED coordinates (its bounds may stick out of [0, L)),
so that one node set serves every periodic copy: a node on the plane x = kL appears once here and
twice after wrapping (on x = 0 and x = L), which makes opposite traces exact translates.
The NumPy topology lives in ``_surface_ops``; this module holds the JAX glue.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from ._errors import MeshingError
from ._periodic import minimum_image, wrap
from ._quality import cross3, min_angles
from ._surface_ops import (
    TraceMismatch,
    apply_flips,
    collapse_edges,
    cut_plane,
    drop_unused_nodes,
    flip_edges,
    half_edges,
    hole_fillings,
    in_one_box_plane,
    match_opposite_traces,
    plane_chords,
    refine,
    snap_candidates,
    straddling,
    touching_plane_nodes,
    triangle_cells,
)
from ._truss import TrussConfig, make_constraints, phi_and_grad, relax
from ._truss._constraints import newton_damping
from ._truss._topology import pad_nodes_to_bucket
from .geometry._microstructure import evaluate


@dataclasses.dataclass(frozen=True)
class SurfaceConfig:
    """Parameters of the surface stage.

    Attributes:
        mc_step: marching-cubes grid step as a fraction of the local h (about one node per h^2).
        refine_ratio: edges longer than refine_ratio * h are split (1-to-4 refinement).
        collapse_ratio: edges shorter than collapse_ratio * h are collapsed (short trace pieces
            left by the box cuts would otherwise make needle triangles).
        snap_fraction: before a cut, vertices closer than snap_fraction * h to the plane are
            moved onto it (no sliver pieces).
        improve_rounds: refine / flip / relax rounds before the cut (and after it).
        newton_steps: Newton iterations of the projections onto phi = 0.
        truss: TrussConfig of the surface relaxations.
        face_truss: TrussConfig of the 2D box-face relaxations.
        face_clearance: face interior nodes closer than face_clearance * h to a constrained
            segment are dropped before the face triangulation.
        trace_grading: on the box faces, h is capped by the trace (and box-edge) node spacing
            plus trace_grading times the distance to that node, so that face triangles next to a
            trace match its spacing.
        face_min_angle: box-face triangles below this angle (degrees) get a circumcentre inserted
            (Delaunay refinement) when it does not encroach on a trace or box edge.
        check_intersections: run the triangle-triangle self-intersection check at the end.
    """

    mc_step: float = 1.0
    refine_ratio: float = 1.45
    collapse_ratio: float = 0.5
    snap_fraction: float = 0.3
    improve_rounds: int = 2
    newton_steps: int = 8
    # dt 0.2 hit the retriangulation limit within ~5 steps; improve() does the dt retry
    truss: TrussConfig = TrussConfig(dt=0.05, max_iterations=30, max_retriangulations=2, newton_steps=1,
                                     max_dt_retries=0, retriangulate_tol=0.3, scan_chunk=30)
    face_truss: TrussConfig = TrussConfig(dt=0.2, max_iterations=40, max_retriangulations=4)
    face_clearance: float = 0.6
    trace_grading: float = 0.3
    face_min_angle: float = 25.0
    check_intersections: bool = True

    def __post_init__(self):
        if not (isinstance(self.collapse_ratio, (int, float)) and 0 <= self.collapse_ratio < 0.5 * self.refine_ratio):
            raise ValueError(f"SurfaceConfig.collapse_ratio: expected a number in [0, refine_ratio / 2), got "
                             f"{self.collapse_ratio!r} (a collapse must not make an edge that refinement splits).")
        for name in ("mc_step", "refine_ratio", "face_clearance", "trace_grading"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"SurfaceConfig.{name}: expected a finite number > 0, got {v!r}.")
        if not (isinstance(self.face_min_angle, (int, float)) and 0 <= self.face_min_angle < 35):
            raise ValueError(f"SurfaceConfig.face_min_angle: expected degrees in [0, 35) (Delaunay refinement "
                             f"stops converging above ~33), got {self.face_min_angle!r}.")
        if not (0 <= self.snap_fraction < 0.5):
            raise ValueError(f"SurfaceConfig.snap_fraction: expected a number in [0, 0.5), got {self.snap_fraction!r}.")
        for name in ("improve_rounds", "newton_steps"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 0):
                raise ValueError(f"SurfaceConfig.{name}: expected an integer >= 0, got {v!r}.")
        for name in ("truss", "face_truss"):
            if not isinstance(getattr(self, name), TrussConfig):
                raise ValueError(f"SurfaceConfig.{name}: expected a TrussConfig, got {type(getattr(self, name)).__name__}.")


class ConstantSize(eqx.Module):
    """h(x) = h everywhere; a PyTree, so compiled relaxations are reused across calls."""

    h: jax.Array

    def __call__(self, points):
        return jnp.full(points.shape[:1], self.h, dtype=points.dtype)


class WrappedSize(eqx.Module):
    """h_fn evaluated at the points wrapped into the box (unwrapped surface coordinates), or, when
    not periodic, clamped into [0, upper] (upper: the last grid node of a sampled size field, whose
    periodic interpolation would blend the far side in beyond it)."""

    h_fn: Callable
    box: tuple[float, ...] = eqx.field(static=True)
    upper: tuple[float, ...] | None = eqx.field(static=True, default=None)  # None: periodic

    def __call__(self, points):
        if self.upper is None:
            L = jnp.asarray(self.box, dtype=points.dtype)
            inside = points - L * jnp.floor(points / L)
        else:
            inside = jnp.clip(points, 0.0, jnp.asarray(self.upper, dtype=points.dtype))
        return jnp.reshape(self.h_fn(inside), points.shape[:1])


def as_size_fn(h, box, periodic: bool = True) -> Callable:
    """A JAX size callable from a positive float or a callable points (m, d) -> (m,)."""
    if callable(h):
        box = tuple(float(b) for b in box)
        if periodic:
            return WrappedSize(h, box)
        shape = np.shape(getattr(h, "values", ()))
        upper = tuple(L * (n - 1) / n for L, n in zip(box, shape)) if len(shape) == len(box) else box
        return WrappedSize(h, box, upper)
    if isinstance(h, (int, float, np.floating, np.integer)) and np.isfinite(h) and h > 0:
        return ConstantSize(jnp.asarray(float(h)))
    raise ValueError(f"h: expected a float > 0 or a callable points (m, 3) -> (m,), got {h!r}. Hint: h = radius / 4.")


_apply_size = eqx.filter_jit(lambda h_fn, points: h_fn(points))


def evaluate_size(h_fn, points: np.ndarray) -> np.ndarray:
    """(m,) h at NumPy points (m, d), padded to a bucket so that one compilation serves many calls."""
    points = np.asarray(points, float)
    if len(points) == 0:
        return np.zeros(0)
    return _in_buckets(lambda p: _apply_size(h_fn, p), points.reshape(len(points), -1))


@eqx.filter_jit
def _newton(phi_fn, pts, locked, n_iter: int):
    def body(p, _):
        phi, g = phi_and_grad(phi_fn, p)
        damping = newton_damping(g)
        g = jnp.where(locked, 0.0, g)
        sq = jnp.sum(g * g, axis=-1)
        step = jnp.where(sq > 0, damping * phi / jnp.where(sq > 0, sq, 1.0), 0.0)
        return p - step[:, None] * g, None

    p, _ = jax.lax.scan(body, pts, None, length=n_iter)
    phi, g = phi_and_grad(phi_fn, p)
    return p, phi, g


# Row counts of the calls of pointwise kernels (`_in_buckets`): few, so that a cold run compiles each
# kernel at most three times per callable (each compile of `_newton` costs seconds; the padded rows little).
_BUCKETS = (64, 1024, 16384)


def _in_buckets(kernel, *arrays: np.ndarray):
    """kernel(*arrays) for a pointwise JAX kernel on NumPy arrays of k rows: padded (the last row
    repeated) to the smallest of _BUCKETS rows that holds them, in chunks of the largest. Returns
    the kernel's outputs (one array or a tuple) as NumPy arrays of k rows."""
    k = len(arrays[0])
    size = next((b for b in _BUCKETS if b >= k), _BUCKETS[-1])
    outs = []
    for start in range(0, k, size):
        rows = [a[start:start + size] for a in arrays]
        n = len(rows[0])
        padded = [jnp.asarray(np.concatenate([r, np.repeat(r[-1:], size - n, axis=0)])) for r in rows]
        outs.append(jax.tree.map(lambda x, n=n: np.asarray(x)[:n], kernel(*padded)))
    return jax.tree.map(lambda *parts: np.concatenate(parts), *outs)


def project(phi_fn, points: np.ndarray, locked: np.ndarray, n_iter: int = 8):
    """Newton projection p -= phi g/|g|^2 onto phi = 0 with the locked coordinates kept exactly.

    Args:
        phi_fn: JAX level set. points: (m, 3). locked: (m, 3) bool.
    Returns:
        (points (m, 3), phi (m,), grad (m, 3)) NumPy float64.
    """
    if len(points) == 0:
        return points.copy(), np.zeros(0), np.zeros((0, 3))
    p, lk = np.asarray(points, float), np.asarray(locked, bool)
    q, phi, g = _in_buckets(lambda a, b: _newton(phi_fn, a, b, int(n_iter)), p, lk)
    return np.where(lk, p, q), phi, g  # locked coordinates stay bit-identical


def refuse_nodes_off_the_level_set(points: np.ndarray, phi_fn, box, inclusion_id: int, step: float,
                                   rtol: float = 1e-6) -> None:
    """MeshingError when a surface node has stalled off phi = 0 after the last projections: |phi| above the
    validator's interface bound (rtol max(L)) and its distance estimate |phi| / |grad phi| above a
    hundredth of the marching-cubes step (a smaller residual is slow convergence, e.g. a trace node
    moving in its box plane, which later projections finish). Newton stalls at a ripple of an
    interpolated field finer than the grid (a tip sharper than a grid step of a field that is not a
    distance): a local extremum of phi just inside the interface, where it cannot reach zero."""
    _, phi, grad = project(phi_fn, points, np.ones(points.shape, bool), 0)
    off = (np.abs(phi) > rtol * float(np.max(box))) & (np.abs(phi) > 0.01 * step * np.linalg.norm(grad, axis=1))
    if not off.any():
        return
    k = int(np.argmax(np.abs(phi)))
    L = np.asarray(box, float)
    at = np.where((points[k] < 0) | (points[k] > L), wrap(points[k], L), points[k])  # a node at x = L stays there
    where = tuple(round(float(v), 4) for v in at)
    raise MeshingError("surfaces", f"{int(off.sum())} surface node(s) stay off the level set after projection "
                       f"(|phi| up to {abs(phi[k]):.2g}, |grad phi| {np.linalg.norm(grad[k]):.2g} there) near x = "
                       f"{where}: the interpolated field has a ripple there finer than the grid (e.g. a tip sharper "
                       "than a grid step of a field that is not a distance), on which the projection stalls; hint: "
                       "--redistance (MeshConfig(redistance=True)) makes the field a signed distance first, or "
                       "sample the field finer", inclusion_id, frame_dependent=False, redistance_helps=True)


def level_set_gradient(phi_fn, points: np.ndarray) -> np.ndarray:
    """(m, 3) gradients of phi_fn at NumPy points."""
    return project(phi_fn, points, np.ones((len(points), 3), bool), 0)[2]


def capped_axes(lower, upper, box, step: float, margin: float) -> tuple[int, ...]:
    """The axes along which a periodic inclusion is meshed closed off beyond the box (`BoxCapped`)
    and cut at x = 0 and L, its opposite traces then paired: where it reaches its own periodic image
    (a percolating network, an endless fibre) or comes within 0.05 steps of it (no marching-cubes
    window around it holds one copy only); and then also where a window with `margin` around its
    bounds would reach into its next copy. Elsewhere its closed unwrapped surface is cut and wrapped."""
    L = np.asarray(box, float)
    gap = L - (np.asarray(upper, float) - np.asarray(lower, float))
    capped = (gap < 0.001 * L) | (gap < 0.1 * step)
    if capped.any():
        capped |= gap < 2 * margin + 1e-6 * L
    return tuple(int(a) for a in np.flatnonzero(capped))


def _periodic_traces(points, tris, on_plane, phi_fn, box, axes, inclusion_id: int, config: SurfaceConfig):
    """The part of a percolating inclusion's cut surface inside the box along `axes`, its traces on
    opposite planes made translates (`match_opposite_traces`), and the free nodes next to them
    smoothed (neighbour mean projected onto phi = 0) where the matching moved or split a trace."""
    keep = (triangle_cells(points, tris, box)[:, list(axes)] == 0).all(axis=1)
    before = points.copy()
    n0 = len(points)
    try:
        points, tris, on_plane = match_opposite_traces(points, tris[keep], on_plane, box, axes)
    except TraceMismatch as err:
        raise MeshingError("surfaces", f"the inclusion percolates along axes {list(axes)} and its traces on opposite "
                           f"box planes cannot be paired: {err}", inclusion_id) from None
    changed = np.concatenate([np.flatnonzero((points[:n0] != before).any(axis=1)), np.arange(n0, len(points))])
    ring = np.unique(tris[np.isin(tris, changed).any(axis=1)])
    ring = np.unique(tris[np.isin(tris, ring).any(axis=1)])  # two rings
    ring = ring[~on_plane[ring].any(axis=1)]
    for _ in range(3):
        if not len(ring):
            break
        points[ring], _, _ = project(phi_fn, neighbour_mean(points, tris)[ring], np.zeros((len(ring), 3), bool),
                                     config.newton_steps)
    return points, tris, on_plane


def extract(phi_fn, lower, upper, step: float, box, periodic: bool = True, reach: float | None = None):
    """Marching cubes of one inclusion on a window around its (unwrapped) bounds.

    Periodic: the window stays within half a box of the inclusion centre: beyond it the periodic
    level set shows the next periodic image, which would leave an open piece of surface on the
    window edge. Not periodic: the window is the bounds plus 2.5 * max(step, reach) (no images),
    widened where the inside still reaches a face of it.
    Per axis, the sample spacing is at most `step` and at most the margin around the bounds.

    Returns:
        (points (n, 3), triangles (t, 3)) oriented with outward normals (positive enclosed volume).
    """
    lower, upper, L = (np.asarray(v, float) for v in (lower, upper, box))
    centre, half = (lower + upper) / 2, (upper - lower) / 2
    if periodic:
        margin = np.minimum(2.5 * step, 0.5 * L - half - 1e-6 * L)
    else:
        margin = np.full(3, 2.5 * max(step, reach or 0.0))
    if (margin < 0.05 * step).any():
        raise MeshingError("surfaces", f"the inclusion spans {np.max(2 * half / L):.0%} of the box along an axis; "
                           "an inclusion must fit in half the box around its centre (with a margin)")
    width = half + margin
    lo, size = centre - width, 2 * width
    for attempt in range(_WINDOW_GROWTH):
        n = np.ceil(size / np.minimum(step, margin)).astype(int) + 1
        spacing = size / (n - 1)
        axes = [lo[a] + spacing[a] * np.arange(n[a]) for a in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        vals = evaluate(phi_fn, grid).reshape(n)
        # not periodic: the inside can overhang its bounds beyond the box (a piece the box cuts to a
        # sliver along an edge widens in its continuation up to the cap): a window face it reaches
        # would leave the surface open there, so that face moves out
        if periodic or attempt == _WINDOW_GROWTH - 1:  # the last window is the one sampled
            break
        low_open = np.array([(vals.take(0, axis=a) < 0).any() for a in range(3)])
        high_open = np.array([(vals.take(-1, axis=a) < 0).any() for a in range(3)])
        if not (low_open | high_open).any():
            break
        lo, size = lo - margin * low_open, size + margin * (low_open.astype(float) + high_open)
    vals = np.where(vals == 0.0, 1e-12 * step, vals)  # no vertex exactly on a grid node
    verts, faces, _, _ = marching_cubes(vals, 0.0, spacing=tuple(spacing), allow_degenerate=False)
    pts = verts.astype(np.float64) + lo
    tris = faces.astype(np.int64)
    if enclosed_volume(pts, tris) < 0:
        tris = tris[:, ::-1].copy()
    return pts, tris


def enclosed_volume(points: np.ndarray, tris: np.ndarray) -> float:
    """Divergence-theorem volume of a closed oriented triangle set (positive for outward normals)."""
    p = points[tris]
    return float(np.einsum("ij,ij->i", p[:, 0], cross3(p[:, 1], p[:, 2])).sum() / 6.0)


def _relax(points, tris, on_plane, phi_fn, h_fn, box, truss: TrussConfig, cut: bool, newton_steps: int):
    """Truss relaxation on the surface; flips (not across a box plane) are the retriangulation.
    Nodes on one box plane slide along their trace, nodes on two planes are fixed; the result is
    projected onto phi = 0 with newton_steps Newton iterations."""
    n = len(points)
    p, cap = pad_nodes_to_bucket(points)
    fixed = np.zeros(cap, bool)
    fixed[n:] = True
    fixed[:n] = on_plane.sum(axis=1) >= 2
    locked = np.zeros((cap, 3), bool)
    locked[:n] = on_plane
    cons = make_constraints(cap, 3, fixed=fixed, locked_axes=locked, on_surface=~fixed)
    state = {"tris": tris}

    def triangulate(q):
        allowed = None
        if cut:
            cells = triangle_cells(q[:n], state["tris"], box)
            allowed = lambda t1, t2: (cells[t1] == cells[t2]).all(axis=1)  # noqa: E731
        state["tris"], _ = flip_edges(q[:n], state["tris"], allowed, on_plane=on_plane)
        return state["tris"]

    res = relax(p, triangulate, h_fn, cons, surface_phi_fn=phi_fn, config=truss)
    # the steps project loosely (truss.newton_steps); converge onto phi = 0 once at the end
    q, _, _ = project(phi_fn, np.array(res.points[:n]), on_plane | fixed[:n, None], newton_steps)
    return q, state["tris"], res


def folded(points, tris, phi_fn) -> np.ndarray:
    """(t,) bool: triangles whose normal opposes the level-set gradient at their centroid (folds)."""
    p = points[tris]
    nrm = cross3(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    g = level_set_gradient(phi_fn, p.mean(axis=1))
    return np.einsum("ij,ij->i", nrm, g) <= 0


def unfold(points, tris, on_plane, phi_fn, newton_steps: int, rounds: int = 5) -> np.ndarray:
    """Move the free nodes around folded triangles to their neighbours' mean, projected onto phi = 0,
    until no fold is left (at most `rounds` times). A relaxation that leaves one fold is otherwise
    dropped whole, and the marching-cubes needles it was fixing stay (seen: 1 deg triangles)."""
    points = points.copy()
    for _ in range(rounds):
        bad = folded(points, tris, phi_fn)
        if not bad.any():
            break
        ring = np.unique(tris[np.isin(tris, tris[bad]).any(axis=1)])
        ring = ring[~on_plane[ring].any(axis=1)]  # plane nodes stay on their traces
        if not len(ring):
            break
        mean = neighbour_mean(points, tris)[ring]
        points[ring], _, _ = project(phi_fn, mean, np.zeros((len(ring), 3), bool), newton_steps)
    return points


def flip_plane_chords(points, tris, on_plane, phi_fn) -> np.ndarray:
    """Flip the edges along which the cut surface touches a box plane (`plane_chords`) where both
    new triangles agree with the level set's gradient. Returns the triangles."""
    pairs = plane_chords(points, tris, on_plane)
    if not len(pairs[0]):
        return tris
    u, v, c, d = pairs[:4]
    ok = ~(folded(points, np.stack([u, d, c], 1), phi_fn) | folded(points, np.stack([d, v, c], 1), phi_fn))
    tris = tris.copy()
    apply_flips(tris, pairs, np.flatnonzero(ok), half_edges(tris, len(points))[0])
    return tris


def remove_fold_nodes(points, tris, on_plane, phi_fn, box, rounds: int = 3):
    """Remove the free nodes of folded triangles, filling each hole (`hole_fillings`: the node's star,
    or the star and one triangle beside it) with the fan of largest smallest angle in which no
    triangle folds, lies in a box plane or straddles one (the cut is done). Seen beside shallow box
    cuts, where no resampling helped: a degree-3 node pushed through its ring, and one tenting over
    a chord on the plane whose flip would fold (the surface crossed itself at both).
    Returns (points, tris, on_plane)."""
    for _ in range(rounds):
        bad = folded(points, tris, phi_fn)
        if not bad.any():
            break
        nodes, count = np.unique(tris[bad], return_counts=True)
        free = ~on_plane[nodes].any(axis=1)
        nodes = nodes[free][np.argsort(-count[free], kind="stable")]
        removed_any = False
        for node in nodes.tolist():
            fillings = hole_fillings(tris, node) if bad[(tris == node).any(axis=1)].any() else []
            if not fillings:
                continue  # its folds went with an earlier node's
            new = np.vstack([fan for _, fan in fillings])
            ok = ~(folded(points, new, phi_fn) | in_one_box_plane(points, on_plane, new)
                   | straddling(points, new, box))
            angle = min_angles(points, new)
            parts = np.split(np.arange(len(new)), np.cumsum([len(fan) for _, fan in fillings])[:-1])
            scores = [angle[part].min() if ok[part].all() else -1.0 for part in parts]
            best = int(np.argmax(scores))
            if scores[best] <= 0:
                continue
            removed, fan = fillings[best]
            tris = np.vstack([np.delete(tris, removed, axis=0), fan])
            bad = np.concatenate([np.delete(bad, removed), np.zeros(len(fan), bool)])
            removed_any = True
        if not removed_any:
            break
        points, tris, on_plane = drop_unused_nodes(points, tris, on_plane)
    return points, tris, on_plane


def neighbour_mean(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(n, 3) mean of each node's edge neighbours on the surface tris."""
    edges, _ = half_edges(tris, len(points))
    total = np.zeros_like(points)
    np.add.at(total, edges[:, 0], points[edges[:, 1]])
    np.add.at(total, edges[:, 1], points[edges[:, 0]])
    return total / np.maximum(np.bincount(edges.ravel(), minlength=len(points)), 1)[:, None]


_KEEP_ANGLE = 25.0  # degrees: a relaxation may lower the smallest angle only down to this


def improve(points, tris, on_plane, phi_fn, h_fn, box, config: SurfaceConfig, cut: bool):
    """Rounds of edge collapses (edges < collapse_ratio * h, needles), 1-to-4 refinement (edges >
    refine_ratio * h), quality flips and truss relaxation.

    Folds a relaxation leaves are smoothed out (`unfold`); around a triangle it still folds, or takes
    below both the old smallest angle and _KEEP_ANGLE, the nodes go back (`revert_around_defects`,
    never box-plane nodes); where that does not clear them the relaxation is retried with dt / 5 and
    otherwise dropped (back off, never delete triangles).
    Returns (points, tris, on_plane).
    """
    truss = config.truss
    for _ in range(config.improve_rounds):
        points, tris, on_plane = _collapse_short(points, tris, on_plane, h_fn, config.collapse_ratio,
                                                 config.refine_ratio)
        edges, _ = half_edges(tris, len(points))
        length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
        h_mid = evaluate_size(h_fn, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]]))
        split = length > config.refine_ratio * h_mid
        if split.any():
            n0 = len(points)
            points, tris, parents = refine(points, tris, split)
            flags = on_plane[parents[:, 0]] & on_plane[parents[:, 1]]
            on_plane = np.vstack([on_plane, flags])
            new = np.arange(n0, len(points))
            points[new], _, _ = project(phi_fn, points[new], flags, config.newton_steps)
        cells = triangle_cells(points, tris, box) if cut else None
        allowed = (lambda t1, t2: (cells[t1] == cells[t2]).all(axis=1)) if cut else None
        tris, _ = flip_edges(points, tris, allowed, on_plane=on_plane)
        worst = min_angles(points, tris).min()
        for attempt in range(2):
            cfg = truss if attempt == 0 else dataclasses.replace(truss, dt=truss.dt * truss.dt_retry_factor)
            q, t, _ = _relax(points, tris, on_plane, phi_fn, h_fn, box, cfg, cut, config.newton_steps)
            q = unfold(q, t, on_plane, phi_fn, config.newton_steps)
            q = revert_around_defects(points, q, t, phi_fn, min(worst, _KEEP_ANGLE), on_plane.any(axis=1))
            if q is not None:
                points, tris = q, t
                break
    return points, tris, on_plane


def revert_around_defects(before, after, tris, phi_fn, min_angle: float, pinned: np.ndarray, rings: int = 3):
    """The relaxed nodes `after`, except around the defects of tris that the relaxation made: there
    the nodes go back to `before`, over a ring of triangles that grows while defects remain (at
    most `rings` times). None when some remain, or when going back would move a `pinned` node (one on
    a box plane: a partial revert there once left a shallow cut cap the volume recovery could not
    close). A defect is a triangle below min_angle degrees, or folded (`folded`) where it was not with
    the nodes `before`: a fold the relaxation found (seen at a saddle of a level set, where the
    gradient disagrees with the marching-cubes triangle) made every relaxation of a large surface
    count as failed, one fold in 35k triangles throwing all away.
    """
    after = after.copy()
    had_fold = folded(before, tris, phi_fn)

    def defects(x):
        return (folded(x, tris, phi_fn) & ~had_fold) | (min_angles(x, tris) < min_angle)

    for _ in range(rings):
        bad = defects(after)
        if not bad.any():
            return after
        nodes = np.unique(tris[np.isin(tris, tris[bad]).any(axis=1)])
        if pinned[nodes].any():
            return None
        after[nodes] = before[nodes]
    return None if defects(after).any() else after


def _collapse_short(points, tris, on_plane, h_fn, ratio: float, refine_ratio: float, passes: int = 3):
    """Collapse edges shorter than ratio * h, and the shortest edge of needles (a triangle below
    20 degrees) when it is under 0.8 h: relaxation alone does not separate two close nodes."""
    for _ in range(passes):
        edges, tri_edge = half_edges(tris, len(points))
        length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
        h_mid = evaluate_size(h_fn, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]]))
        short = length < ratio * h_mid
        needle = min_angles(points, tris) < 20.0
        if needle.any():
            shortest = tri_edge[needle, np.argmin(length[tri_edge[needle]], axis=1)]
            short[shortest[length[shortest] < 0.8 * h_mid[shortest]]] = True
        points, tris, on_plane, done = collapse_edges(points, tris, on_plane, short, refine_ratio * h_mid)
        if done == 0:
            break
    return points, tris, on_plane


def cut_by_box(points, tris, on_plane, phi_fn, box, h_fn, config: SurfaceConfig):
    """Cut an unwrapped closed surface by every box plane k L_a it crosses.

    Vertices within snap_fraction * h of a plane are first moved onto it (projected along the
    plane onto phi = 0; reverted where that fails), then crossing triangles are split at new
    vertices on the plane and on the level set. Returns (points, tris, on_plane).
    """
    L = np.asarray(box, float)
    for a in range(3):
        lo, hi = points[:, a].min(), points[:, a].max()
        for k in range(int(np.ceil(lo / L[a])), int(np.floor(hi / L[a])) + 1):
            value = k * L[a]
            h_loc = evaluate_size(h_fn, points)
            # a cap shallower than the snap distance would be flattened onto the plane whole, leaving
            # a trace on one side without its translate: snap within half the cap's depth at most
            depth = min(points[:, a].max() - value, value - points[:, a].min())
            tol = min(config.snap_fraction * float(np.min(h_loc)), 0.5 * depth)
            cand = snap_candidates(points, tris, on_plane, a, value, tol)
            if cand.size:
                old = points[cand].copy()
                moved = old.copy()
                moved[:, a] = value
                flags = on_plane[cand].copy()
                flags[:, a] = True
                q, phi, _ = project(phi_fn, moved, flags, config.newton_steps)
                good = (np.abs(phi) < 1e-9 * tol) & (np.linalg.norm(q - old, axis=1) < 2 * tol)
                good &= _clear_of_others(points, cand, q, 0.25 * tol)
                points[cand[good]] = q[good]
                on_plane[cand[good]] = flags[good]
            points, tris, on_plane, new = cut_plane(points, tris, on_plane, a, value)
            if new.size:
                points[new], _, _ = project(phi_fn, points[new], on_plane[new], config.newton_steps)
    return points, tris, on_plane


def release_touching(points, tris, on_plane, phi_fn, box, newton_steps: int):
    """Move plane nodes that touch their plane without a crossing (`touching_plane_nodes`) off it,
    to their neighbours' mean projected onto phi = 0 (other plane coordinates kept).
    Returns (points, on_plane)."""
    touch = touching_plane_nodes(points, tris, on_plane, box)
    nodes = np.flatnonzero(touch.any(axis=1))
    if not nodes.size:
        return points, on_plane
    points, on_plane = points.copy(), on_plane.copy()
    on_plane[touch] = False
    target = np.where(on_plane[nodes], points[nodes], neighbour_mean(points, tris)[nodes])
    points[nodes], _, _ = project(phi_fn, target, on_plane[nodes], newton_steps)
    return points, on_plane


def _clear_of_others(points: np.ndarray, cand: np.ndarray, q: np.ndarray, radius: float) -> np.ndarray:
    """(k,) bool: snapped positions q of vertices cand that stay radius away from every other vertex
    and from each other (two vertices snapped onto one box-edge point would merge into one node)."""
    others = np.delete(points, cand, axis=0)
    ok = cKDTree(others).query(q)[0] > radius if len(others) else np.ones(len(q), bool)
    for i, j in cKDTree(q).query_pairs(radius):
        ok[max(i, j)] = False
    return ok


def wrap_pieces(points, tris, on_plane, box):
    """Translate every triangle into the box by its cell; a vertex shared by pieces of different
    cells is copied once per cell. Plane coordinates become exactly 0 or L.

    Returns:
        (points (m, 3) in [0, L], tris (t, 3), source (m,) unwrapped vertex of each copy).
    """
    L = np.asarray(box, float)
    cells = triangle_cells(points, tris, box)
    v = tris.reshape(-1)
    c = np.repeat(cells, 3, axis=0)
    key = np.concatenate([v[:, None], c], axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    src, cell = uniq[:, 0], uniq[:, 1:]
    p = points[src] - cell * L
    k = np.round(points[src] / L)
    p = np.where(on_plane[src], (k - cell) * L, p)
    return p, inv.reshape(-1, 3).astype(np.int64), src


class BoxCapped(eqx.Module):
    """An inclusion's level set closed off `cap` beyond the box planes of `axes`: the
    intersection, rounded with radius cap / 2, with the box grown by cap. Equal to phi_fn up to
    cap / 2 beyond the planes, where the box cuts it; the rest is dropped after the cut. A grid
    inclusion cut by the domain boundary continues as an extrusion beyond it, and a percolating
    one as its next periodic copy: neither is closed."""

    phi_fn: Callable
    box: tuple[float, ...] = eqx.field(static=True)
    cap: jax.Array
    axes: tuple[int, ...] = eqx.field(static=True, default=(0, 1, 2))

    def __call__(self, points):
        points = jnp.asarray(points)
        phi = jnp.reshape(self.phi_fn(points), points.shape[:-1])
        r = 0.5 * self.cap
        for a in self.axes:
            L = self.box[a]
            for beyond in (-points[..., a] - self.cap, points[..., a] - L - self.cap):
                u = jnp.maximum(jnp.stack([r + phi, r + beyond], axis=-1), 0.0)
                sq = jnp.sum(u * u, axis=-1)
                # rounded intersection (a safe norm: its gradient is finite where u = 0)
                norm = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
                phi = jnp.minimum(-r, jnp.maximum(phi, beyond)) + norm
        return phi


def inside_pieces(points, tris, on_plane, box):
    """The triangles of a cut surface inside the box (cell 0), the others dropped; plane
    coordinates become exactly 0 or L. Returns (points (m, 3), tris (t, 3), source (m,))."""
    L = np.asarray(box, float)
    tris = tris[(triangle_cells(points, tris, box) == 0).all(axis=1)]
    src, inv = np.unique(tris.reshape(-1), return_inverse=True)
    p = np.where(on_plane[src], np.round(points[src] / L) * L, points[src])
    return p, inv.reshape(-1, 3).astype(np.int64), src


_MC_ATTEMPTS = 3  # marching-cubes grids tried per inclusion, each up to 4x finer
_WINDOW_GROWTH = 4  # marching-cubes windows per grid, each a margin wider where the inside reaches its face
_MIN_CAP_DEPTH = 0.01  # fraction of h: shallower caps beyond a box plane are not meshed


def _walk(phi_fn, q, direction, step: float, newton_steps: int, done, max_steps: int = 40):
    """Move points q (k, 3) along the level set: tangential part of `direction`, then Newton back
    onto phi = 0, until done(q) (k,) holds or the tangential part vanishes (an extreme point)."""
    for _ in range(max_steps):
        live = ~done(q)
        g = level_set_gradient(phi_fn, q)
        n = g / np.linalg.norm(g, axis=1, keepdims=True)
        move = step * (direction - (n @ direction)[:, None] * n) * live[:, None]
        if np.linalg.norm(move, axis=1).max() < 1e-9 * step:
            break
        q, _, _ = project(phi_fn, q + move, np.zeros(q.shape, bool), newton_steps)
    return q


def settle_caps(points, phi_fn, h_fn, box, newton_steps: int, axes=(0, 1, 2)):
    """Make the nodes agree with the level set about which box planes it crosses.

    A cap beyond a plane thinner than the node spacing may hold no node, so the surface would not
    be cut there while the level set is (the volume recovery then projects split points out of the
    box); or its only node makes a cap of slivers. Near each plane (the extreme node within h of
    it) the extreme node walks along the level set to the extreme point: a cap deeper than
    _MIN_CAP_DEPTH * h gets that node (if it moved less than h / 2, so that its triangles do not
    fold), so the cut sees it; a shallower one is left out of the mesh,
    its nodes walking back inside by the cap's depth (meshing it would need elements that thin).
    """
    L = np.asarray(box, float)
    points = points.copy()
    for a in axes:
        for sign in (-1.0, 1.0):
            i = int(np.argmax(sign * points[:, a]))
            plane = points[i, a] - minimum_image(points[i, a], L[a])  # the nearest plane k L
            h = float(evaluate_size(h_fn, points[i][None])[0])
            if not -h < sign * (points[i, a] - plane) < h:
                continue
            up = np.zeros(3)
            up[a] = sign
            q = _walk(phi_fn, points[i][None], up, 0.25 * h, newton_steps, lambda q: np.zeros(len(q), bool))
            depth = sign * (q[0, a] - plane)
            others = np.delete(np.minimum(np.abs(q[0]), np.abs(L - q[0])), a)
            empty = sign * (points[i, a] - plane) <= 0  # no node in the cap yet
            # a short walk (no fold) that ends clear of the other planes (a node on a box edge is cut there)
            if empty and depth > _MIN_CAP_DEPTH * h and np.linalg.norm(q[0] - points[i]) < 0.5 * h \
                    and others.min() > _MIN_CAP_DEPTH * h:
                points[i] = q[0]
            elif 0 < depth <= _MIN_CAP_DEPTH * h and sign * (points[i, a] - plane) > -depth:
                beyond = np.flatnonzero(sign * (points[:, a] - plane) > -depth)
                points[beyond] = _walk(phi_fn, points[beyond], -up, 0.25 * h, newton_steps,
                                       lambda q: sign * (q[:, a] - plane) <= -depth)
    return points


def mesh_inclusion(inclusion, h_fn, box, config: SurfaceConfig = SurfaceConfig(), periodic: bool = True):
    """Closed surface of one inclusion, improved, cut by the box and wrapped into it (periodic), or
    with the pieces outside the box dropped (not periodic).

    Args:
        inclusion: geometry Inclusion (phi_fn, lower, upper unwrapped bounds).
        h_fn: JAX size callable (see :func:`as_size_fn`). box: (3,) lengths.
    Returns:
        dict with points (m, 3) in [0, L], triangles (t, 3) oriented outwards, unwrapped points/triangles,
        folds: the number of kept triangles whose normal opposes the level-set gradient.
    """
    phi_fn = inclusion.phi_fn
    lower, upper = np.asarray(inclusion.lower, float), np.asarray(inclusion.upper, float)
    L = np.asarray(box, float)
    centre = jnp.asarray(((lower + upper) / 2)[None])
    h0 = float(evaluate_size(h_fn, np.asarray(centre))[0])
    step = min(config.mc_step * h0, float(np.min(upper - lower)) / 4)
    # closed off beyond the box: every axis when not periodic; the axes along which a periodic
    # inclusion reaches its own image (it percolates), where no closed surface exists
    capped = tuple(range(3)) if not periodic else capped_axes(lower, upper, box, step, 2.5 * config.mc_step * h0)
    if capped:
        cap = 2.0 * step
        phi_fn = BoxCapped(phi_fn, tuple(float(v) for v in L), jnp.asarray(cap), capped)
        # the surface of an inclusion the box cuts goes on beyond it (a grid one as an extrusion of
        # the border samples, a periodic one as its next copy) up to the cap: the window reaches the cap
        inner = np.isin(np.arange(3), capped)
        lower = np.where(inner & ((lower < cap) | periodic), -cap, lower)
        upper = np.where(inner & ((upper > L - cap) | periodic), L + cap, upper)
        if (upper <= lower).any():
            raise MeshingError("surfaces", "the inclusion lies outside the box", inclusion.id)
    for _ in range(_MC_ATTEMPTS):
        # capped: a piece the box cuts thin (a small step) may still overhang its bounds beyond
        # the box planes, up to the cap (an analytic level set widens there; a grid one is extruded)
        raw, tris = extract(phi_fn, lower, upper, step, box, periodic and not capped, reach=config.mc_step * h0)
        if len(tris) < 4:
            raise MeshingError("surfaces", "marching cubes found no closed surface", inclusion.id)
        edge_use = np.bincount(half_edges(tris, len(raw))[1].reshape(-1))
        if (edge_use != 2).any():
            raise MeshingError("surfaces", f"the marching-cubes surface is not closed ({int((edge_use != 2).sum())} "
                               "edges not in two triangles)", inclusion.id)
        pts, _, _ = project(phi_fn, raw, np.zeros(raw.shape, bool), config.newton_steps)
        # the centre's h can be far coarser than the surface's (a large irregular inclusion): a
        # grid that misses its necks and bumps projects into folds; then sample at the surface's h
        if not folded(pts, tris, phi_fn).any():
            break
        finer = max(config.mc_step * float(np.quantile(evaluate_size(h_fn, raw), 0.05)), step / 4)
        if finer > step / 1.5:
            break
        step = finer
    on_plane = np.zeros(pts.shape, bool)
    pts, tris, on_plane = improve(pts, tris, on_plane, phi_fn, h_fn, box, config, cut=False)
    if (pts.min(0) < lower - 0.25 * L).any() or (pts.max(0) > upper + 0.25 * L).any():
        raise MeshingError("surfaces", "surface nodes left the inclusion's neighbourhood during relaxation "
                           "(a degenerate level set? check the input near this inclusion)", inclusion.id)
    pts = settle_caps(pts, phi_fn, h_fn, box, config.newton_steps,
                      tuple(a for a in range(3) if a not in capped) if periodic else (0, 1, 2))
    crosses = (np.floor(pts.min(0) / L) != np.floor(pts.max(0) / L)).any()
    if crosses:
        for _ in range(3):
            pts, tris, on_plane = cut_by_box(pts, tris, on_plane, phi_fn, box, h_fn, config)
            pts, tris, on_plane = improve(pts, tris, on_plane, phi_fn, h_fn, box, config, cut=True)
            pts, on_plane = release_touching(pts, tris, on_plane, phi_fn, box, config.newton_steps)
            if not straddling(pts, tris, box).any():
                break
        else:  # last resort: cut what still straddles without snapping
            pts, tris, on_plane = cut_by_box(pts, tris, on_plane, phi_fn, box, h_fn,
                                             dataclasses.replace(config, snap_fraction=0.0))
        tris = flip_plane_chords(pts, tris, on_plane, phi_fn)
        pts, tris, on_plane = remove_fold_nodes(pts, tris, on_plane, phi_fn, box)
    if periodic and capped:
        pts, tris, on_plane = _periodic_traces(pts, tris, on_plane, phi_fn, box, capped, inclusion.id, config)
    if periodic:
        wp, wt, src = wrap_pieces(pts, tris, on_plane, box)
    else:
        wp, wt, src = inside_pieces(pts, tris, on_plane, box)
    refuse_nodes_off_the_level_set(pts[np.unique(src)], phi_fn, box, inclusion.id, step)  # the nodes kept
    # a fold the relaxation left beside a trace (seen: a degree-3 node tenting over a chord on the
    # plane) encloses a pocket no Delaunay tetrahedron fills; mesh_surfaces samples such an inclusion again
    folds = int(folded(pts, src[wt], phi_fn).sum())
    return {"points": wp, "triangles": wt, "source": src, "unwrapped_points": pts, "unwrapped_triangles": tris,
            "folds": folds}
