"""The Microstructure type: inclusions with their own periodic level sets, global DN1 / DN2 (paper 2.2).

A scanned or generated field groups every inclusion in one level set; the paper's DN_k functions
need one signed distance per inclusion (eq. 3: DN1 = min_i DS_i). Each inclusion therefore gets its
own level set here: analytic (from_functions), or rebuilt on a window around it (from_levelset,
from_labels; see _components.py), so that two inclusions one grid step apart stay two.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from .._periodic import image_shifts, minimum_image, nearest_image_shifts, nearest_images_suffice, points_near, wrap
from . import _components as comp
from ._components import check_box, check_field, check_order, check_points, gradient_scale, size_errors
from ._grid import bspline_coefficients, interpolate_cubic, interpolate_linear
from ._shapes import centre_and_spread, with_centre

_CORE_PAD = 3  # steps of accurate own level set around an inclusion's nodes
_SPLINE_PAD = {"cubic": 4, "linear": 1}  # steps more: the window's wrap decays as 0.268^steps
_BUDGET = 2**25  # grid nodes evaluated (over all inclusions) for dn1/dn2 before the reach is capped
_PHI_MARGIN = 8  # steps: Microstructure.phi evaluates an inclusion within this of its bounds


@dataclass(frozen=True, eq=False)
class Inclusion:
    """One inclusion: id (1..N, 0 is the matrix), its own periodic level set phi_fn (JAX, points
    (m, d) -> (m,), negative inside, differentiable), axis-aligned bounds lower/upper (d,) in
    unwrapped coordinates (may stick out of [0, L)), analytic volume (area in 2D) when known."""

    id: int
    phi_fn: Callable
    lower: np.ndarray
    upper: np.ndarray
    volume: float | None = None
    description: dict = field(default_factory=dict)


# Bytes that the windows of one microstructure may take when all are padded to one shape.
_SHARED_SHAPE_BYTES = 256 * 2**20
# Layers along a plain box's planes thinner than this (grid steps) are closed on request: the size
# function sizes no box gap below it (`_sizing.size_sources` clips box gaps at a sixth of a step).
BOX_LAYER_STEPS = 1.0 / 6.0


def _bucket_shape(shape) -> tuple[int, ...]:
    """Window shape rounded up to 8 (16 above 64) per axis."""
    return tuple(-(-n // (8 if n <= 64 else 16)) * (8 if n <= 64 else 16) for n in shape)


def _pad_windows(datas: list) -> list:
    """Pad window data at its far end to one shape for all inclusions (the largest bucket per axis),
    or, when that would take more than _SHARED_SHAPE_BYTES, each to its own bucket (`_bucket_shape`):
    inclusions of one shape share every compilation (a cold run compiles a grid kernel once per shape,
    seconds each). Safe: interpolation only reads the core of the window and its spline neighbours,
    which the padding never reaches."""
    buckets = [_bucket_shape(d.shape) for d in datas]
    shared = tuple(np.max(buckets, axis=0)) if datas else ()
    if datas and len(datas) * np.prod(shared) * datas[0].dtype.itemsize <= _SHARED_SHAPE_BYTES:
        buckets = [shared] * len(datas)
    return [jnp.pad(d, [(0, t - n) for t, n in zip(target, d.shape)]) for d, target in zip(datas, buckets)]


def _window_phi(data, origin, center, half, box, window_box, points, *, cubic, periodic):
    """Level set of one window: the B-spline (or multilinear) interpolant inside the core, and
    outside it the value at the point clamped onto the core plus the distance to the core. Not
    periodic: the window's nodes beyond the grid hold linear continuations of the border samples
    (`_components.extrapolate_beyond_domain`), so the last cell before x = L is interpolated too."""
    points = jnp.asarray(points)
    u = points - center
    if periodic:
        u = minimum_image(u, box)
    uc = jnp.clip(u, -half, half)
    sq = jnp.sum((u - uc) ** 2, axis=-1)
    pos = sq > 0
    excess = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)  # safe sqrt: finite gradient
    interp = interpolate_cubic if cubic else interpolate_linear
    return interp(data, window_box, uc + (center - origin)) + excess


# one object per variant, so that phi_fns (jax.tree_util.Partial) of equal shapes share compilations
_KERNELS = {
    (c, p): functools.partial(_window_phi, cubic=c, periodic=p) for c in (True, False) for p in (True, False)
}
_KERNEL_SET = frozenset(_KERNELS.values())


@functools.partial(jax.jit, static_argnums=0)
def _map_kernel(func, params, box, window_box, batch):
    """Inclusion k of a stack at its own points batch[k] (K, B, d) -> (K, B), one at a time."""
    return jax.lax.map(lambda a: func(*a[0], box, window_box, a[1]), (params, batch))


_GATHER_MAX_PARAMS = 64  # per inclusion: a centre, axes, a rotation; not a grid (copied per point)


def _analytic_key(phi_fn):
    """(func, (box, nearest_images) or None, parameter shapes) of an analytic Partial level set
    (periodized or not) with a few array parameters, None for anything else: inclusions with equal
    keys are evaluated in one compiled call."""
    periodic = (phi_fn.box, phi_fn.nearest_images) if isinstance(phi_fn, _Periodized) else None
    f = phi_fn.fn if isinstance(phi_fn, _Periodized) else phi_fn
    if not isinstance(f, jax.tree_util.Partial) or f.func in _KERNEL_SET or f.keywords:
        return None
    if not f.args or not all(isinstance(a, (jax.Array, np.ndarray)) for a in f.args):
        return None
    if sum(np.size(a) for a in f.args) > _GATHER_MAX_PARAMS:
        return None
    return f.func, periodic, tuple((np.shape(a), jnp.result_type(a)) for a in f.args)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _gather_kernel(func, periodic, params, owner, points):
    """Point k at the level set of inclusion owner[k] of a stack (M, d) -> (M,): one pass over the
    points with each point's own parameters, so many small inclusions cost one dispatch."""
    def one(x, *args):
        f = jax.tree_util.Partial(func, *args)
        return (_Periodized(f, *periodic) if periodic is not None else f)(x[None])[0]

    return jax.vmap(one)(points, *(p[owner] for p in params))


class _Periodized(eqx.Module):
    """phi(x) = min over the 3^d image shifts of f(wrap(x) + shift): a periodic level set from an
    SDF defined on R^d (wrap first, so points far outside the box are handled too). With
    nearest_images (`periodized`: a sphere_sdf / ellipsoid_sdf for which
    `_periodic.nearest_images_suffice`), only the 2^d shifts nearest its centre per point: the same
    values, at 8 exact ellipsoid distances per point instead of 27.

    A PyTree: with a Partial f (sphere_sdf, ellipsoid_sdf) inclusions of one kind share their
    compilations; an opaque closure f is a static leaf (one compilation per inclusion)."""

    fn: Callable
    box: tuple[float, ...] = eqx.field(static=True)
    nearest_images: bool = eqx.field(static=True, default=False)

    def __call__(self, points):
        points = jnp.asarray(points)
        d = len(self.box)
        lead, pts = points.shape[:-1], wrap(points.reshape(-1, d), jnp.asarray(self.box))
        if self.nearest_images:
            centre = jax.lax.stop_gradient(centre_and_spread(self.fn)[0]).astype(pts.dtype)
            shifts = nearest_image_shifts(pts - centre, self.box)
        else:
            shifts = jnp.asarray(image_shifts(d, self.box), dtype=pts.dtype)[:, None]
        vals = jnp.reshape(self.fn((pts[None] + shifts).reshape(-1, d)), (len(shifts), -1))
        return jnp.min(vals, axis=0).reshape(lead)


def periodized(fn: Callable, box) -> _Periodized:
    """The periodic level set of fn (`_Periodized`), over the nearest images only where that is exact."""
    shape = centre_and_spread(fn)
    exact = shape is not None and nearest_images_suffice(np.asarray(shape[0]), float(shape[1]), box)
    return _Periodized(fn, tuple(box), exact)


_apply = eqx.filter_jit(lambda fn, pts: fn(pts))  # fn a PyTree: one compilation per kernel and shape


def _traceable(fn) -> bool:
    """A PyTree level set whose arrays are traced (not an opaque closure compiled per object)."""
    if isinstance(fn, _Periodized):
        return _traceable(fn.fn)
    return isinstance(fn, (jax.tree_util.Partial, eqx.Module))


def diagonal_gaps(ms: Microstructure, values: np.ndarray, labels: np.ndarray):
    """Gaps between inclusions that come closest across a grid square or cube (`comp.diagonal_cells`),
    where no matrix sample lies between them: min of phi_a + phi_b (a distance's triangle bound,
    negative where they overlap) over a 9^d lattice of a step around each such cell's centre. Returns
    (k, 2) ids, (k,) gaps and (k, d) places (index units), one row per pair, smallest first."""
    ids, centres = comp.diagonal_cells(values, labels, ms.periodic)
    d, h = values.ndim, np.asarray(ms.spacing)
    offsets = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 9)] * d, indexing="ij"), -1).reshape(-1, d)
    rows = {}
    for pair in {tuple(p) for p in ids.tolist()}:
        at = np.flatnonzero((ids == pair).all(axis=1))
        pts = ((centres[at][:, None, :] + offsets) * h).reshape(-1, d)
        pts = pts if ms.periodic else np.clip(pts, 0.0, np.asarray(ms.box))  # a plain box ends at its planes
        total = (ms.inclusion_phi(pair[0], pts) + ms.inclusion_phi(pair[1], pts)).reshape(len(at), -1)
        best = np.unravel_index(np.argmin(total), total.shape)
        rows[pair] = (float(total[best]), centres[at[best[0]]] + offsets[best[1]])
    order = sorted(rows, key=lambda p: rows[p][0])
    return (np.array(order, np.int64).reshape(-1, 2), np.array([rows[p][0] for p in order]),
            np.array([rows[p][1] for p in order]).reshape(-1, d))


def evaluate(phi_fn: Callable, points: np.ndarray, name: str | None = None, chunk: int = 2**15) -> np.ndarray:
    """phi_fn at NumPy points (m, d) -> (m,) float64, in chunks padded to powers of two (few
    compilations). With a name (user functions), failures and non-finite output raise ValueError."""
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p = points[start : start + chunk]
        k = len(p)
        size = max(64, 1 << (k - 1).bit_length())
        p = np.concatenate([p, np.repeat(p[-1:], size - k, axis=0)]) if size > k else p
        try:
            v = _apply(phi_fn, p) if _traceable(phi_fn) else phi_fn(jnp.asarray(p))
            v = np.asarray(v, dtype=float)
        except Exception as err:
            if name is None:
                raise
            raise ValueError(f"from_functions: {name} failed on points of shape {p.shape}: {err}. Hint: each "
                             "phi_fn maps points (m, d) to values (m,), e.g. jaxmesh sphere_sdf.") from err
        if name is not None and (v.shape != (size,) or not np.isfinite(v).all()):
            raise ValueError(f"from_functions expected {name} to return {size} finite values for points "
                             f"({size}, d), got shape {v.shape} with {np.size(v) - np.isfinite(v).sum()} "
                             "NaN/inf. "
                             "Hint: return one finite signed distance per point.")
        out[start : start + k] = v[:k]
    return out


def _grid_points(axes, spacing) -> np.ndarray:
    mesh = np.meshgrid(*[a * h for a, h in zip(axes, spacing)], indexing="ij")
    return np.stack(mesh, axis=-1).reshape(-1, len(axes))


_LATTICE_MARGIN = 0.6  # of a lattice cell's diagonal (0.5 is exact for a signed distance)


def function_bounds(f: Callable, i: int, shape, spacing):
    """Bounds of {f < 0} sampled on the grid nodes of [-L, 2L)^d, searched coarse to fine: on a
    lattice of stride ~n/4, then of stride ~n/16 around its candidates, then every node around
    those. A node where f < 0 is within half a lattice cell's diagonal of a lattice node, where f is
    then below that half diagonal (f a signed distance: 1-Lipschitz); candidates are the lattice
    nodes below 0.6 diagonal (a margin for near-distances), so no negative node is missed.

    Returns:
        lower, upper (d,) unwrapped, the number of negative nodes and the thickness in steps.
    """
    n = np.asarray(shape)
    spacing = np.asarray(spacing, float)
    ranges = [(-nk, 2 * nk) for nk in n]  # node index ranges [start, stop) searched per axis
    strides = [np.maximum(1, n // 4), np.maximum(1, n // 16), np.ones_like(n)]
    for s, s_next in zip(strides[:-1], strides[1:]):
        axes = [np.arange(a - (a % sk), b, sk) for (a, b), sk in zip(ranges, s)]  # nodes of stride s
        vals = evaluate(f, _grid_points(axes, spacing), name=f"phi_fns[{i}]").reshape([len(a) for a in axes])
        cand = vals < (0.0 if (s == 1).all() else _LATTICE_MARGIN * float(np.linalg.norm(s * spacing)))
        if not cand.any():
            raise ValueError(
                f"from_functions expected phi_fns[{i}] to be negative somewhere on the grid, got min "
                f"{vals.min():.4g} on the nodes of [-L, 2L)^d. Hint: negative inside; an inclusion must span "
                "grid nodes (refine grid_shape)."
            )
        # a negative node lies within s / 2 of a candidate; the next lattice brackets it, one node beyond
        reach = s // 2 + s_next + 1
        ranges = []
        for k in range(len(n)):
            hit = np.flatnonzero(cand.any(axis=tuple(j for j in range(len(n)) if j != k)))
            ranges.append((axes[k][hit[0]] - reach[k], axes[k][hit[-1]] + reach[k] + 1))
    fine = [np.arange(a, b) for a, b in ranges]
    vals = evaluate(f, _grid_points(fine, spacing), name=f"phi_fns[{i}]").reshape([len(a) for a in fine])
    own = vals < 0
    if not own.any():
        raise ValueError(f"from_functions expected phi_fns[{i}] to be negative on some grid node, got none "
                         f"(min {vals.min():.4g}). Hint: it is smaller than a grid step: refine grid_shape.")
    lo, hi = comp.crossing_bounds(vals, own, [False] * len(n))
    origin = np.array([a[0] for a in fine])
    return (origin + lo) * spacing, (origin + hi) * spacing, int(own.sum()), comp.chord_thickness(vals, own)


class Microstructure:
    """A periodic (or not) box holding a matrix (id 0) and inclusions 1..N, each with its own level set.

    Attributes:
        box: (d,) cell lengths; periodic: bool; inclusions: tuple of Inclusion (ids 1..N);
        grid_shape: nodes per axis of the node-centred grid (node i at x = i * L / n).
        dn1: (grid_shape) DN1 = min_i phi_i (eq. 3), signed, negative inside inclusions.
        dn2: (grid_shape) distance to the second nearest inclusion, positive where inclusions are
            separated. Exact up to `reach` from every inclusion, min(DN2, reach) beyond; with a
            single inclusion it is half the box diagonal.
        nearest_id: (grid_shape) int, id of the nearest inclusion.
        reach: physical distance up to which dn1/dn2 are exact (inf: everywhere).

    Example:
        >>> ms = Microstructure.from_levelset(phi)                 # (n, n[, n]) samples, unit box
        >>> ms.label(np.array([[0.5, 0.5, 0.5]])), ms.volume_fraction()
    """

    def __init__(self, box, periodic, inclusions, grid_shape, dn1, dn2, nearest_id, reach=np.inf):
        self.box = tuple(float(b) for b in box)
        self.periodic = bool(periodic)
        self.inclusions = tuple(inclusions)
        self.grid_shape = tuple(int(n) for n in grid_shape)
        self.dn1, self.dn2, self.nearest_id = dn1, dn2, nearest_id
        self.reach = float(reach)
        if [inc.id for inc in self.inclusions] != list(range(1, len(self.inclusions) + 1)):
            raise ValueError("Microstructure expected inclusion ids 1..N in order.")
        for name, a in (("dn1", dn1), ("dn2", dn2), ("nearest_id", nearest_id)):
            if np.shape(a) != self.grid_shape:
                raise ValueError(f"Microstructure expected {name} of shape {self.grid_shape}, "
                                 f"got {np.shape(a)}.")
        self._stacked = None
        self._rebuild = None  # periodic: samples -> the same Microstructure in the rolled frame
        self._redistance = None  # from_levelset as given: () -> the same field made a first-order distance
        self._close_box_layers = None  # plain-box from_levelset: () -> the same with its box layers closed

    def rolled(self, samples) -> Microstructure:
        """The same periodic microstructure in the frame whose origin is sample samples[a] along each axis a
        (the box faces move to x_a = samples[a] L_a / n_a of this frame), as `load_input(...,
        roll=samples)` reads a file: from_levelset / from_labels rebuild from their grid rolled,
        from_functions from its functions shifted (phi_rolled(x) = phi(x + samples h)).

        Example:
            >>> moved = ms.rolled((8, 0, 0))  # sample 8 along x now at x = 0; the grid is kept for this
        """
        if self._rebuild is None:
            raise ValueError("Microstructure.rolled needs a periodic microstructure (a plain box's faces are "
                             "the domain's); hint: build it with periodic=True")
        if len(samples) != self.dim or not all(isinstance(k, (int, np.integer)) for k in samples):
            raise ValueError(f"Microstructure.rolled expected {self.dim} integers (grid samples per axis), "
                             f"got {samples!r}")
        return self._rebuild(tuple(int(k) % n for k, n in zip(samples, self.grid_shape)))

    @property
    def can_roll(self) -> bool:
        """Whether `rolled` can rebuild this microstructure in another frame."""
        return self._rebuild is not None

    def redistanced(self) -> Microstructure:
        """This from_levelset microstructure rebuilt from its samples made a first-order signed distance to
        their zero set (`from_levelset(..., redistance=True)`, the other arguments the same).

        Example:
            >>> ms = Microstructure.from_levelset(phi).redistanced()
        """
        if self._redistance is None:
            raise ValueError("Microstructure.redistanced needs a level set built by from_levelset without "
                             "redistance (labelled images and analytic inclusions are distances already)")
        return self._redistance()

    @property
    def can_redistance(self) -> bool:
        """Whether `redistanced` applies: a from_levelset field not redistanced yet."""
        return self._redistance is not None

    def with_box_layers_closed(self) -> Microstructure:
        """This plain-box from_levelset microstructure rebuilt with the layers along its box planes that
        are thinner than BOX_LAYER_STEPS of a grid step closed (`from_levelset(..., close_box_layers=True)`,
        the other arguments the same): the interface moves by at most that much, at those places only.

        Example:
            >>> ms = Microstructure.from_levelset(phi, periodic=False).with_box_layers_closed()
        """
        if self._close_box_layers is None:
            raise ValueError("Microstructure.with_box_layers_closed needs a plain-box level set built by "
                             "from_levelset(periodic=False) without close_box_layers")
        return self._close_box_layers()

    @property
    def can_close_box_layers(self) -> bool:
        """Whether `with_box_layers_closed` applies: a plain-box from_levelset field not closed yet."""
        return self._close_box_layers is not None

    def __repr__(self):
        return (f"Microstructure(dim={self.dim}, box={self.box}, periodic={self.periodic}, "
                f"inclusions={len(self.inclusions)}, grid_shape={self.grid_shape})")

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        return len(self.box)

    @property
    def spacing(self) -> tuple[float, ...]:
        """Grid step per axis L_i / n_i."""
        return tuple(L / n for L, n in zip(self.box, self.grid_shape))

    def coordinates(self) -> np.ndarray:
        """Grid node positions, (*grid_shape, d); node i sits at i * L / n."""
        axes = [np.arange(n) * (L / n) for n, L in zip(self.grid_shape, self.box)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def _bbox_distance(self, inc: Inclusion, pts: np.ndarray) -> np.ndarray:
        """(m,) Euclidean (minimum-image) distance from points to the inclusion's bounds."""
        centre, half = (inc.upper + inc.lower) / 2, (inc.upper - inc.lower) / 2
        u = pts - centre
        if self.periodic:
            u = minimum_image(u, np.asarray(self.box))
        return np.linalg.norm(np.maximum(np.abs(u) - half, 0.0), axis=-1)

    def _near_bounds(self, pts: np.ndarray, margin: float) -> list[np.ndarray]:
        """Per inclusion, the indices of points within margin of its bounds: the points in the ball
        around the bounds (a k-d tree query), then the exact box distance on those."""
        if not self.inclusions:
            return []
        lower = np.array([inc.lower for inc in self.inclusions], dtype=float)
        upper = np.array([inc.upper for inc in self.inclusions], dtype=float)
        radii = np.linalg.norm(upper - lower, axis=1) / 2 + margin
        balls = points_near(pts, (lower + upper) / 2, radii * (1 + 1e-9), self.box, self.periodic)
        return [ball[self._bbox_distance(inc, pts[ball]) <= margin] for inc, ball in zip(self.inclusions, balls)]

    def _inclusion(self, inclusion_id) -> Inclusion:
        if not (isinstance(inclusion_id, (int, np.integer)) and 1 <= inclusion_id <= len(self.inclusions)):
            raise ValueError(
                f"expected an inclusion id in 1..{len(self.inclusions)}, got {inclusion_id!r}. "
                "Hint: 0 is the matrix, which has no level set of its own."
            )
        return self.inclusions[int(inclusion_id) - 1]

    def phi(self, points) -> np.ndarray:
        """DN1 at points (m, d) -> (m,), NumPy: the min of the inclusions' phi_fn, each evaluated
        where its (periodic) bounds + 8 grid steps reach. Exact (to the interpolation) within ~3
        steps of the interfaces; farther, where phi_fn only continues distance-like, the dn1 grid
        (multilinear, accurate to about half a step) is used when smaller."""
        pts = check_points(points, self.dim, "Microstructure.phi")
        h = max(self.spacing)
        out = np.full(len(pts), np.inf)
        for _, sel, vals in self.evaluate_near(pts, _PHI_MARGIN * h):
            out[sel] = np.minimum(out[sel], vals)
        # window-based phi_fn only continue distance-like beyond their core: take the grid if smaller
        far = out > _CORE_PAD * h if self._groups()[0] else ~np.isfinite(out)
        if far.any():
            coords = (pts[far] / np.asarray(self.spacing)).T
            mode = "grid-wrap" if self.periodic else "nearest"
            out[far] = np.minimum(out[far], ndimage.map_coordinates(self.dn1, coords, order=1, mode=mode))
        return out

    def inclusion_phi(self, inclusion_id: int, points) -> np.ndarray:
        """Level set of one inclusion at points (m, d) -> (m,), NumPy."""
        inc = self._inclusion(inclusion_id)
        return evaluate(inc.phi_fn, check_points(points, self.dim, "Microstructure.inclusion_phi"))

    def label(self, points) -> np.ndarray:
        """Inclusion id containing each point (m, d) -> (m,) int64; 0 = matrix."""
        pts = check_points(points, self.dim, "Microstructure.label")
        ids, best = np.zeros(len(pts), np.int64), np.zeros(len(pts))
        for i, sel, vals in self.evaluate_near(pts, max(self.spacing)):
            win = vals < best[sel]
            ids[sel[win]], best[sel[win]] = i + 1, vals[win]
        return ids

    def _groups(self):
        """Inclusions stacked for evaluation (cached): window-based ones by (kernel, window shape)
        as [(kernel, params, box, window_box, member indices)], analytic Partial ones by (function,
        box, parameter shapes) as [(function, box, params, member indices)], and the others' indices."""
        if self._stacked is None:
            windows, analytic, others = {}, {}, []
            for i, inc in enumerate(self.inclusions):
                f = inc.phi_fn
                if isinstance(f, jax.tree_util.Partial) and f.func in _KERNEL_SET:
                    windows.setdefault((f.func, f.args[0].shape), []).append(i)
                elif (key := _analytic_key(f)) is not None:
                    analytic.setdefault(key, []).append(i)
                else:
                    others.append(i)
            stacks = []
            for (func, _), members in windows.items():
                fs = [self.inclusions[i].phi_fn for i in members]
                params = tuple(jnp.stack([f.args[k] for f in fs]) for k in range(4))
                stacks.append((func, params, fs[0].args[4], fs[0].args[5], np.array(members)))
            gathers = []
            for (func, box, _), members in analytic.items():
                fs = [self.inclusions[i].phi_fn for i in members]
                fs = [f.fn if isinstance(f, _Periodized) else f for f in fs]
                params = tuple(jnp.stack([jnp.asarray(f.args[k]) for f in fs]) for k in range(len(fs[0].args)))
                gathers.append((func, box, params, np.array(members)))
            self._stacked = (stacks, gathers, others)
        return self._stacked

    def evaluate_near(self, pts, margin: float, chunk: int = 2**16):
        """Yield (inclusion index, selected point indices, phi values) for every inclusion at the
        points (m, d) within margin of its (periodic) bounds: each inclusion's own level set where it
        is meaningful; equal windows, and analytic inclusions of one kind, are evaluated in one
        compiled call."""
        pts = check_points(pts, self.dim, "Microstructure.evaluate_near")
        near = self._near_bounds(pts, margin)
        stacks, gathers, others = self._groups()
        for func, params, box, wbox, members in stacks:
            counts = [len(near[i]) for i in members]
            if max(counts) == 0:
                continue
            size = max(64, 1 << (max(counts) - 1).bit_length())
            batch = np.zeros((len(members), size, self.dim))
            for j, i in enumerate(members):
                batch[j, : counts[j]] = pts[near[i]]
            vals = np.asarray(_map_kernel(func, params, box, wbox, batch))
            for j, i in enumerate(members):
                yield i, near[i], vals[j, : counts[j]]
        for func, box, params, members in gathers:
            counts = np.array([len(near[i]) for i in members])
            if counts.sum() == 0:
                continue
            sel = np.concatenate([near[i] for i in members])
            owner = np.repeat(np.arange(len(members)), counts)
            vals = np.empty(len(sel))
            for start in range(0, len(sel), chunk):
                k = min(chunk, len(sel) - start)
                size = max(64, 1 << (k - 1).bit_length())
                p, o = np.zeros((size, self.dim)), np.zeros(size, np.int64)
                p[:k], o[:k] = pts[sel[start : start + k]], owner[start : start + k]
                p[k:] = p[0]  # padding: any point inside the box
                vals[start : start + k] = np.asarray(_gather_kernel(func, box, params, o, p))[:k]
            ends = np.cumsum(counts)
            for j, i in enumerate(members):
                yield i, near[i], vals[ends[j] - counts[j] : ends[j]]
        for i in others:
            if len(near[i]):
                yield i, near[i], evaluate(self.inclusions[i].phi_fn, pts[near[i]])

    def global_phi_fn(self) -> Callable:
        """JAX DN1 callable points (m, d) -> (m,): the min over every inclusion's phi_fn.

        Window-based inclusions of equal window shape are stacked and folded with lax.scan, so the
        cost is N interpolations per point at the memory of one. Jit-able, differentiable.
        """
        stacks, gathers, others = self._groups()
        unstacked = sorted(others + [int(i) for *_, members in gathers for i in members])
        other_fns = [self.inclusions[i].phi_fn for i in unstacked]

        def dn1_fn(points):
            points = jnp.asarray(points)
            out = jnp.full(points.shape[:-1], jnp.inf, dtype=jnp.result_type(points.dtype, float))
            for func, params, box, wbox, _ in stacks:
                def body(carry, p, func=func, box=box, wbox=wbox):
                    return jnp.minimum(carry, func(*p, box, wbox, points)), None

                out, _ = jax.lax.scan(body, out, params)
            for f in other_fns:
                out = jnp.minimum(out, f(points))
            return out

        return dn1_fn

    def volume_fraction(self) -> float:
        """Inclusion volume fraction: analytic when every inclusion's volume is known, else from the
        dn1 grid with a linear smoothed Heaviside clip(1/2 - dn1/h, 0, 1) (unbiased for a plane)."""
        if self.inclusions and all(inc.volume is not None for inc in self.inclusions):
            return float(sum(inc.volume for inc in self.inclusions) / np.prod(self.box))
        h = float(np.mean(self.spacing))
        return float(np.clip(0.5 - self.dn1 / h, 0.0, 1.0).mean())

    @classmethod
    def from_levelset(cls, values, box=None, periodic=True, order="cubic", *, reach=None,
                      check_sizes: bool = True, check_gaps: bool = True, check_necks: bool = True,
                      redistance: bool = False, close_box_layers: bool = False) -> Microstructure:
        """Inclusions = periodic connected components of {phi < 0} of one global field (on a plain
        box, parts that join in the last cell before a far face x = L are one component).

        Args:
            values: (nx, ny[, nz]) real samples on the node-centred grid, negative inside. Fields
                that are not distance-like (|grad| far from 1, e.g. scan intensities) are rescaled
                by their median gradient near the interface (zero set unchanged).
            box: (d,) cell lengths, equal spacing L_i / n_i; None: unit cube.
            periodic: the field is periodic (checked: a wrap-around jump of many steps is an error).
            order: "cubic" (C2 B-spline) or "linear" interpolation of each inclusion's window.
            reach: distance up to which dn1/dn2 are exact; None: everywhere if affordable.
            check_sizes: refuse inclusions the grid does not resolve (fewer than 8 negative samples
                or thinner than 1.5 steps).
            check_gaps: refuse inclusions less than 0.02 grid step apart (touching at the grid's
                resolution: the size function would refine the gap down to its floor), also across one
                grid square or cube (two diagonal samples in different inclusions, no matrix sample
                between them, where their interpolated level sets meet: their surfaces would cross).
            check_necks: refuse inclusions that narrow below one grid step between two resolved
                parts (a filament in 3D, a strip in 2D: the surfaces cannot follow it).
            redistance: replace the field by a first-order signed distance to its zero set first
                (phi / |grad phi| at the nodes next to the interface, the distance to those nodes
                elsewhere): the same signs at every node, the interface moved within its grid cells.
                For fields far from a distance, such as a thresholded random field whose saddles lie
                close to zero: their nearly flat zero sets fold the surfaces.
            close_box_layers: plain boxes only: close the layers along the box planes thinner than
                BOX_LAYER_STEPS of a grid step (`_components.close_box_layers`: an interface that
                grazes a plane from inside reaches it, a sheet of inclusion along it is dropped),
                after redistancing. The mesher fills such a layer with tets as thin as it is, or its
                volume recovery stops there.

        Returns:
            The Microstructure; each inclusion's description holds n_samples and thickness (steps),
            neck_steps (the narrowest neck's width) when it has a neck below one step, and the field's
            scale and slope_spread (`gradient_scale`: how far the field is from a distance).
        """
        if close_box_layers and periodic:
            raise ValueError("from_levelset: close_box_layers applies to a plain box (periodic=False); a "
                             "periodic field's box planes are no boundary (roll moves them instead)")
        v = check_field(values, "from_levelset")
        shape = v.shape
        box = check_box(box, shape, "from_levelset")
        check_order(order)
        spacing = tuple(L / n for L, n in zip(box, shape))
        mask = v < 0
        if not mask.any():
            raise ValueError(
                f"from_levelset expected an inclusion (phi < 0 somewhere), got no negative values "
                f"(min {v.min():.4g}). Hint: the convention is negative inside; pass -phi if reversed."
            )
        if mask.all():
            raise ValueError(
                f"from_levelset expected some matrix (phi >= 0 somewhere), got phi < 0 at every node "
                f"(max {v.max():.4g}). Hint: the convention is negative inside; pass -phi if reversed."
            )
        if periodic:
            repeated = comp.repeated_end_axes(v)
            if repeated:
                raise ValueError(
                    f"from_levelset expected a node-centred periodic grid (x = i * L / n, i < n), but along "
                    f"axes {repeated} the last slice repeats the first. Hint: drop it, e.g. values[:-1] "
                    "along those axes (the periodic grid has no node at x = L)."
                )
            for k, (jump, typical) in enumerate(comp.periodicity_ratios(v)):
                if jump > 3.0 * typical + 1e-12 * (np.abs(v).max() + 1):
                    raise ValueError(
                        f"from_levelset expected a periodic field (periodic=True), but along axis {k} the "
                        f"wrap-around jump |phi[0] - phi[n-1]| averages {jump:.4g}, "
                        f"{jump / max(typical, 1e-300):.1f} times the largest jump between neighbouring "
                        f"slices ({typical:.4g}). Hint: pass periodic=False, or sample a periodic field at "
                        "x = i * L / n, i < n (no repeated last node)."
                    )
        if redistance:
            v = comp.first_order_distance(v, mask, spacing, periodic)
        closed = 0
        if close_box_layers:
            v, closed = comp.close_box_layers(v, BOX_LAYER_STEPS)
            mask = v < 0
            if not mask.any():
                raise ValueError("from_levelset: with the layers along the box planes closed no inclusion is left "
                                 "(every part was a sheet thinner than the grid resolves); hint: sample finer")
        scale, spread = gradient_scale(v, mask, spacing, periodic)
        scale = scale if abs(scale - 1.0) > 0.25 else 1.0  # distance-like fields are kept as they are
        v = v / scale
        labels, n = comp.label_components(mask, True) if periodic else comp.label_components_to_far_planes(v)
        starts, lengths = comp.component_arcs(labels, n, periodic)
        pad = _CORE_PAD + _SPLINE_PAD[order]
        r = _reach_steps(reach, lengths, shape, spacing, pad)
        _, near = comp.nearest_component(labels, spacing, periodic, pad=int(min(max(shape), 2 * pad + 8)))
        windows, fields = [], []
        for c in range(1, n + 1):
            win = comp.make_window(starts[c - 1], lengths[c - 1], shape, periodic, _CORE_PAD,
                                   _SPLINE_PAD[order])
            idx = comp.frame_indices(win.origin, win.shape, shape, periodic)
            own = comp.take(labels, idx) == c
            near_w = comp.take(near, idx)
            other = (comp.take(labels, idx) > 0) & ~own
            fields.append(comp.levelset_window_field(comp.take(v, idx), own, near_w, c, spacing, win.full, other))
            windows.append(win)
        descriptions = [{"kind": "levelset", "scale": float(scale), "slope_spread": spread,
                         **({"redistanced": True} if redistance else {}),
                         **({"box_layers_closed": closed} if close_box_layers else {})} for _ in range(n)]
        ms = cls._from_windows(box, periodic, order, labels, (starts, lengths), windows, fields, r,
                               descriptions, "from_levelset", check_sizes, check_gaps, check_necks)
        if check_gaps:
            ids, gaps, centres = diagonal_gaps(ms, v, labels)
            min_gap = comp._MIN_GAP_STEPS * min(spacing)
            close = gaps < min_gap
            if close.any():
                raise ValueError(comp.close_pairs_message(
                    ids[close], gaps[close], centres[close], spacing, min_gap, "from_levelset", across_cell=True,
                    hint="move them apart (raise the field at the cell's other samples), merge them (a negative "
                         "sample there joins them into one inclusion), or sample the field on a finer grid"))
        grid = np.array(values, copy=True)
        build = functools.partial(cls.from_levelset, box=box, periodic=periodic, order=order, reach=reach,
                                  check_sizes=check_sizes, check_gaps=check_gaps, check_necks=check_necks)
        if periodic:
            ms._rebuild = functools.partial(_from_rolled_grid, functools.partial(build, redistance=redistance), grid)
        if not redistance:
            ms._redistance = functools.partial(build, grid, redistance=True, close_box_layers=close_box_layers)
        if not periodic and not close_box_layers:
            ms._close_box_layers = functools.partial(build, grid, redistance=redistance, close_box_layers=True)
        return ms

    @classmethod
    def from_labels(cls, labels, box=None, periodic=True, *, reach=None) -> Microstructure:
        """Inclusions from a labelled image: 0 matrix, k > 0 inclusion (bool: each component one).

        Each connected region of one label (face-connected, across the periodic faces when periodic)
        is one inclusion: a label in several parts (a phase image such as 0 matrix, 1 aggregate,
        2 pore; or a crop whose box cuts a region) gives one inclusion per part (description["part"]
        1, 2, ...). Inclusions are numbered 1..N by increasing label, parts in scan order (the
        original is kept in description["label"]). Regions of different labels must not share a
        grid face. The
        level set of each is the signed distance to its voxels with the interface half a step
        from the nodes, lightly smoothed.

        Args:
            labels: (nx, ny[, nz]) int >= 0 or bool. box, periodic, reach: as in from_levelset.
        """
        lab = check_field(labels, "from_labels", labels=True)
        shape = lab.shape
        box = check_box(box, shape, "from_labels")
        spacing = tuple(L / n for L, n in zip(box, shape))
        if not lab.any():
            raise ValueError("from_labels expected at least one inclusion (label > 0), got only zeros. "
                             "Hint: 0 is the matrix, inclusions are labelled 1, 2, ...")
        comps, n = comp.label_components(lab > 0, periodic)
        if lab.dtype == bool:
            values = np.arange(1, n + 1)
        else:
            pairs = comp.touching_label_pairs(lab, periodic)
            if len(pairs):
                listed = ", ".join(f"{a}-{b}" for a, b in pairs[:8])
                raise ValueError(
                    f"from_labels expected separated inclusions, got {len(pairs)} pairs of different labels "
                    f"sharing a grid face ({listed}). Hint: leave at least one matrix (0) voxel between "
                    "inclusions; a region that crosses the periodic box must carry one label on both sides "
                    "(scipy.ndimage.label does not wrap: pass labels > 0, a bool image, to have it labelled "
                    "periodically)."
                )
            first = np.zeros(n + 1, dtype=lab.dtype)
            first[comps.ravel()] = lab.ravel()
            values = first[1:]
            # a label in several parts (a phase image, or a crop the box cuts): one inclusion per part
            order = np.argsort(values, kind="stable")  # ids 1..N by increasing label, parts in scan order
            relabel = np.zeros(n + 1, np.int32)
            relabel[order + 1] = np.arange(1, n + 1)
            comps, values = relabel[comps], values[order]
        starts, lengths = comp.component_arcs(comps, n, periodic)
        r = _reach_steps(reach, lengths, shape, spacing, _CORE_PAD + _SPLINE_PAD["cubic"])
        windows, fields = [], []
        for c in range(1, n + 1):
            win = comp.make_window(starts[c - 1], lengths[c - 1], shape, periodic, _CORE_PAD,
                                   _SPLINE_PAD["cubic"])
            own = comp.take(comps, comp.frame_indices(win.origin, win.shape, shape, periodic)) == c
            fields.append(comp.labels_window_field(own, spacing, win.full))
            windows.append(win)
        descriptions = [{"kind": "labels", "label": int(val)} for val in values]
        if len(np.unique(values)) < len(values):
            for k, val in enumerate(values):
                descriptions[k]["part"] = int((values[:k] == val).sum()) + 1
        ms = cls._from_windows(box, periodic, "cubic", comps, (starts, lengths), windows, fields, r,
                               descriptions, "from_labels")
        if periodic:
            ms._rebuild = functools.partial(_from_rolled_grid, functools.partial(
                cls.from_labels, box=box, periodic=True, reach=reach), np.array(labels, copy=True))
        return ms

    @classmethod
    def _from_windows(cls, box, periodic, order, labels, arcs, windows, fields, r, descriptions, where: str,
                      check_sizes: bool = True, check_gaps: bool = True, check_necks: bool = True):
        """Shared tail of from_levelset / from_labels: size and gap checks, dn1/dn2, bounds, JAX phi_fns.
        labels: (grid) component ids; arcs: (starts, lengths) (N, d); fields: window level sets."""
        shape, (starts, lengths) = labels.shape, arcs
        spacing = np.array([L / n for L, n in zip(box, shape)])
        owns = [f < 0 for f in fields]
        stats = [(int(o.sum()), comp.chord_thickness(f, o)) for f, o in zip(fields, owns)]
        errors = size_errors(stats, descriptions) if check_sizes else ""
        if errors:
            cut = comp.box_cut_small(stats, labels) if not periodic else []
            if cut:
                which = f"inclusion {cut[0]} touches" if len(cut) == 1 else f"inclusions {cut[:10]} touch"
                errors += (f" Here {which} the box: where the box cuts an inclusion, the part inside can be "
                           "thinner than the whole; on a periodic field mesh it periodic (the inclusion stays "
                           "whole), or move the box plane by a grid layer.")
            raise ValueError(errors)
        found = []
        for c, (win, W, own) in enumerate(zip(windows, fields, owns), start=1):
            for _, node, chord in comp.necks(W, own.astype(np.int32), comp._NECK_STEPS):
                label = descriptions[c - 1].get("label")
                name = f"inclusion {c}" + (f" (label {label})" if label is not None else "")
                found.append((name, ((win.origin + node) % shape) * spacing, chord))
                descriptions[c - 1] = dict(descriptions[c - 1], neck_steps=chord)
        if check_necks and found:
            raise ValueError(comp.neck_errors(found, where))
        dn1, dn2, nearest = _new_dn(shape)
        for c, (win, W) in enumerate(zip(windows, fields), start=1):
            fo, fs = comp.reach_frame(starts[c - 1], lengths[c - 1], shape, periodic, r)
            idx = comp.frame_indices(fo, fs, shape, periodic)
            own = comp.take(labels, idx) == c
            tree = comp.surface_tree(W, W < 0, spacing, win.full)
            vals = comp.frame_values(W, win, own, fo, spacing, tree)
            comp.accumulate(dn1, dn2, nearest, c, idx, vals)
        reach = _finish_dn(dn1, dn2, nearest, labels, spacing, box, periodic, r)
        if check_gaps:
            min_gap = comp._MIN_GAP_STEPS * min(spacing)
            ids, gaps, nodes = comp.close_pairs(dn1, dn2, nearest, labels, spacing, min_gap, periodic)
            if len(ids):
                raise ValueError(comp.close_pairs_message(ids, gaps, comp.node_places(nodes, shape), spacing,
                                                          min_gap, where))
        inclusions, datas, pending = [], [], []  # pending: what each inclusion gets once its data are padded
        for c, (win, W, own, desc, stat) in enumerate(zip(windows, fields, owns, descriptions, stats), 1):
            if not periodic:  # the level set goes on beyond the box as it meets it, no crease
                W = comp.extrapolate_beyond_domain(W, win.origin, shape)
                # its zero set in the last cell (up to the node at x = L) belongs to the bounds too
                own = (W < 0) & comp.within_nodes(win.origin, W.shape, np.zeros(len(shape)), np.asarray(shape))
            lo, hi = comp.crossing_bounds(W, own, win.full)
            lower, upper = (win.origin + lo) * spacing, (win.origin + hi) * spacing
            if not periodic:  # cut by the domain boundary: the bounds reach the box
                lower = np.where(starts[c - 1] == 0, 0.0, lower)
                upper = np.where(starts[c - 1] + lengths[c - 1] == shape, np.asarray(box, float), upper)
            else:  # samples in every grid plane along an axis: it meets its own image (the mesher refuses it)
                upper = np.where(lengths[c - 1] == shape, lower + np.asarray(box, float), upper)
            centre, half = zip(*(comp.core_geometry(win, k, spacing, W.shape) for k in range(len(shape))))
            datas.append(bspline_coefficients(W) if order == "cubic" else jnp.asarray(W))
            pending.append((c, lower, upper, dict(desc, n_samples=stat[0], thickness=stat[1]),
                            (win.origin * spacing, centre, half)))
        for (c, lower, upper, desc, frame), data in zip(pending, _pad_windows(datas)):
            args = [jnp.asarray(a, dtype=data.dtype) for a in (*frame, box, np.asarray(data.shape) * spacing)]
            phi_fn = jax.tree_util.Partial(_KERNELS[(order == "cubic", bool(periodic))], data, *args)
            inclusions.append(Inclusion(c, phi_fn, lower, upper, None, desc))
        return cls(box, periodic, inclusions, shape, dn1, dn2, nearest, reach)

    @classmethod
    def from_functions(cls, phi_fns, box, grid_shape, periodic=True, volumes=None, descriptions=None,
                       *, reach=None) -> Microstructure:
        """Inclusions from analytic JAX SDFs, one per inclusion, each defined on R^d.

        Periodic: phi_i(x) = min over the 3^d image shifts of f_i(wrap(x) + shift). Bounds come from
        sampling f_i on the grid (coarse, then fine near its negative set); dn1/dn2 on the grid.

        Args:
            phi_fns: sequence of callables points (m, d) -> (m,), negative inside.
            box: (d,) cell lengths; grid_shape: (d,) nodes per axis (equal spacing).
            periodic: make each inclusion periodic. volumes: optional analytic volumes (or None
                entries). descriptions: optional dicts (e.g. kind, center, radius).
            reach: as in from_levelset.

        Raises:
            ValueError: bad arguments, an inclusion with no or too few negative grid samples, or
                two inclusions closer than one grid step (touching / overlapping).
        """
        fns, box, shape, volumes, descriptions = comp.check_function_args(phi_fns, box, grid_shape, volumes,
                                                                      descriptions)
        spacing = np.array([L / n for L, n in zip(box, shape)])
        found = [function_bounds(f, i, shape, spacing) for i, f in enumerate(fns)]
        errors = size_errors([(cnt, th) for _, _, cnt, th in found], descriptions)
        if errors:
            raise ValueError(errors)
        L = np.asarray(box)
        starts, lengths, bounds, shifts = [], [], [], []
        for lower, upper, _, _ in found:
            full = upper - lower >= L * (1 - 1e-9)
            shift = np.where(full, 0.0, np.floor((lower + upper) / 2 / L) * L) if periodic else 0.0
            lower, upper = np.where(full, 0.0, lower - shift), np.where(full, L, upper - shift)
            s = np.floor(lower / spacing + 1e-9).astype(np.int64)
            starts.append(s)
            lengths.append(np.minimum(np.ceil(upper / spacing - 1e-9).astype(np.int64) - s + 1, shape))
            bounds.append((lower, upper))
            shifts.append(np.broadcast_to(shift, L.shape))
        lengths = np.array(lengths)
        r = _reach_steps(reach, lengths, shape, spacing, _CORE_PAD + _SPLINE_PAD["cubic"])
        phis = [periodized(f, box) if periodic else f for f in fns]
        dn1, dn2, nearest = _new_dn(shape)
        for c, (f, phi, s, m, shift) in enumerate(zip(fns, phis, starts, lengths, shifts), start=1):
            fo, fs = comp.reach_frame(s, m, shape, periodic, r)
            axes = [(o + np.arange(w)) * h for o, w, h in zip(fo, fs, spacing)]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(shape))
            big = periodic and np.any(m * spacing > L / 2)  # nearest image by centre may not be nearest
            # frame points live in the wrapped frame of the bounds: f itself is defined around lower + shift
            vals = (evaluate(phi, pts, name=f"phi_fns[{c - 1}]") if big
                    else evaluate(f, pts + shift, name=f"phi_fns[{c - 1}]")).reshape(fs)
            comp.accumulate(dn1, dn2, nearest, c, comp.frame_indices(fo, fs, shape, periodic), vals)
        labels = np.where(dn1 < 0, nearest, 0)
        reach_len = _finish_dn(dn1, dn2, nearest, labels, spacing, box, periodic, r)
        _check_gaps(dn1, dn2, nearest, labels, spacing, len(fns), periodic)
        inclusions = [
            Inclusion(c, phi, lo, hi, vol, desc)
            for c, (phi, (lo, hi), vol, desc) in enumerate(zip(phis, bounds, volumes, descriptions), start=1)
        ]
        ms = cls(box, periodic, inclusions, shape, dn1, dn2, nearest, reach_len)
        if periodic:
            ms._rebuild = functools.partial(_from_shifted_functions, functools.partial(
                cls.from_functions, box=box, grid_shape=shape, periodic=True, volumes=volumes, reach=reach),
                fns, descriptions, spacing)
        return ms


def _reach_steps(reach, lengths, shape, spacing, r_min) -> float:
    """Reach in grid steps: from the user's length, or the largest the node budget allows."""
    if reach is None:
        return comp.choose_reach(np.asarray(lengths), shape, _BUDGET, r_min)
    if not (isinstance(reach, (int, float)) and reach > 0):
        raise ValueError(f"expected reach as a positive length (or None, or inf), got {reach!r}.")
    return np.inf if not np.isfinite(reach) else float(max(r_min, int(np.ceil(reach / min(spacing)))))


def _new_dn(shape):
    return np.full(shape, np.inf), np.full(shape, np.inf), np.zeros(shape, np.int64)


def _finish_dn(dn1, dn2, nearest, labels, spacing, box, periodic, r) -> float:
    """Fill nodes no inclusion reached (finite reach only) and cap dn2; returns the reach length."""
    h = min(spacing)
    far = ~np.isfinite(dn1)
    if far.any():
        dist, near = comp.nearest_component(labels, spacing, periodic, pad=int(min(max(dn1.shape), r + 2)))
        dn1[far], nearest[far] = dist[far] - 0.5 * h, near[far]
    cap = r * h if np.isfinite(r) else 0.5 * float(np.linalg.norm(box))
    np.minimum(dn2, cap, out=dn2)
    return r * h if np.isfinite(r) else np.inf


def _check_gaps(dn1, dn2, nearest, labels, spacing, n: int, periodic: bool):
    """Functions: every inclusion present on the grid, none closer than one grid step to another
    (gap estimated at nodes within a step of an interface as dn1 + dn2)."""
    h = min(spacing)
    missing = sorted(set(range(1, n + 1)) - set(np.unique(labels[labels > 0]).tolist()))
    ids, gaps, nodes = comp.close_pairs(dn1, dn2, nearest, labels, spacing, h * (1 - 1e-9), periodic)
    if len(ids):
        raise ValueError(comp.close_pairs_message(ids, gaps, comp.node_places(nodes, labels.shape), spacing, h,
                                                  "from_functions", hint="move them apart (e.g. random_inclusions("
                                                  "..., min_gap=...)) or refine grid_shape"))
    if missing:
        raise ValueError(f"from_functions expected every inclusion to own grid nodes, got {missing} hidden "
                         "inside others. Hint: remove nested or duplicated inclusions.")


def _shifted(fn: Callable, offset: np.ndarray, points):
    return fn(points + offset)


def _from_shifted_functions(build: Callable, fns, descriptions, spacing: np.ndarray,
                            samples: tuple[int, ...]) -> Microstructure:
    """build(each function shifted so that x = 0 is sample `samples` of this frame); a description's
    "center" moves with it. Spheres and ellipsoids move their centres (into the box), so they stay
    analytic kernels evaluated together."""
    offset = np.asarray(samples) * spacing
    box = np.asarray(build.keywords["box"], float)
    moved = [dict(d, center=wrap(np.asarray(d["center"], float) - offset, box).tolist()) if "center" in d else d
             for d in descriptions]
    shifted = []
    for f in fns:
        shape = centre_and_spread(f)
        g = None if shape is None else with_centre(f, wrap(np.asarray(shape[0], float) - offset, box))
        shifted.append(g if g is not None else functools.partial(_shifted, f, offset))
    return build(shifted, descriptions=moved)


def _from_rolled_grid(build: Callable, grid: np.ndarray, samples: tuple[int, ...]) -> Microstructure:
    """build(grid rolled so that sample samples[a] comes first along each axis a)."""
    return build(np.roll(grid, [-k for k in samples], axis=tuple(range(grid.ndim))))
