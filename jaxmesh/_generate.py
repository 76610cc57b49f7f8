"""Random RVE inputs: periodic RSA of spheres/ellipsoids with a guaranteed gap, Gaussian excursion sets.

NumPy/SciPy only (no jax at import time); `microstructure_from_specs` / `microstructure_from_npz`
import jaxmesh.geometry lazily to build a JAX Microstructure.

Gap guarantee. Spheres: centre distance >= r_i + r_j + gap (exact). Ellipsoids: the distance of
two convex bodies is max_{|u|=1} u.(c_i - c_j) - h_i(u) - h_j(u) (h: support functions), so a
direction u reaching `gap` is a certificate (growing the semi-axes by gap/2 is not: that ellipsoid
lies inside the gap/2 offset body). Pairs are screened by bounding/inscribed spheres first, then
the direction is found by Newton steps on the sphere; undecided pairs are rejected.
"""

from __future__ import annotations

import itertools
import math
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ._periodic import image_shifts, minimum_image, nearest_centres, wrap

__all__ = [
    "InclusionSpec", "excursion_set", "microstructure_from_npz", "microstructure_from_specs",
    "random_inclusions", "sample_levelset", "write_input",
]


def unit_ball_volume(dim: int) -> float:
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1)


@dataclass(frozen=True, eq=False)
class InclusionSpec:
    """One analytic inclusion: kind "sphere" | "ellipsoid", center (d,), semi-axes (d,), rotation (d, d).

    Rotation columns are the principal directions of axes[0], axes[1], ... (identity for spheres).
    """

    kind: str
    center: np.ndarray
    axes: np.ndarray
    rotation: np.ndarray

    def __post_init__(self):
        if self.kind not in ("sphere", "ellipsoid"):
            raise ValueError(f"InclusionSpec kind: expected 'sphere' or 'ellipsoid', got {self.kind!r}.")
        c = np.asarray(self.center, dtype=np.float64)
        a = np.asarray(self.axes, dtype=np.float64)
        d = c.shape[0] if c.ndim == 1 else -1
        r = np.eye(d) if self.rotation is None else np.asarray(self.rotation, dtype=np.float64)
        if d not in (2, 3) or a.shape != (d,) or r.shape != (d, d):
            raise ValueError(
                f"InclusionSpec: expected center (d,), axes (d,), rotation (d, d) with d in (2, 3), got "
                f"{c.shape}, {a.shape}, {r.shape}."
            )
        if not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise ValueError(f"InclusionSpec axes: expected positive lengths, got {a}.")
        if self.kind == "sphere" and not np.allclose(a, a[0]):
            raise ValueError(f"InclusionSpec: a sphere needs equal axes, got {a}; use kind='ellipsoid'.")
        for name, v in (("center", c), ("axes", a), ("rotation", r)):
            v.setflags(write=False)
            object.__setattr__(self, name, v)

    @property
    def dim(self) -> int:
        return self.center.shape[0]

    @property
    def volume(self) -> float:
        """Volume (3D) or area (2D)."""
        return unit_ball_volume(self.dim) * float(np.prod(self.axes))


# ------------------------------------------------------------------------------------- validation


def _check_box(box) -> np.ndarray:
    b = np.asarray(box, dtype=np.float64) if np.ndim(box) == 1 else None
    if b is None or b.shape[0] not in (2, 3) or not np.all(np.isfinite(b)) or np.any(b <= 0):
        raise ValueError(
            f"box: expected 2 or 3 positive lengths, got {box!r}. Hint: box=(1.0, 1.0, 1.0) for the unit cube."
        )
    return b


def _check_grid(grid_shape, dim: int) -> tuple[int, ...]:
    g = tuple(int(n) for n in np.atleast_1d(grid_shape))
    if len(g) != dim or min(g) < 4 or any(int(n) != n for n in np.atleast_1d(grid_shape)):
        raise ValueError(
            f"grid_shape: expected {dim} integers >= 4 (one per box axis), got {grid_shape!r}. "
            "Hint: e.g. (32,) * dim."
        )
    return g


def checked_seed(seed, name: str = "seed") -> int:
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"{name}: expected an integer >= 0, got {seed!r}.")
    return int(seed)


def _radius_sampler(radius) -> Callable[[np.random.Generator, int], np.ndarray]:
    if callable(radius):

        def call(rng, n):
            r = np.asarray(radius(rng, n), dtype=np.float64)
            if r.shape != (n,):
                raise ValueError(f"radius: expected the callable to return ({n},) radii, got shape {r.shape}.")
            return r

        return call
    if np.ndim(radius) == 0:
        return lambda rng, n: np.full(n, float(radius))
    if np.shape(radius) == (2,):
        mean, std = (float(v) for v in radius)
        if std < 0 or mean <= 0:
            raise ValueError(f"radius: expected (mean > 0, std >= 0), got {radius!r}.")
        lo, hi = max(mean - 2 * std, 0.25 * mean), mean + 2 * std  # truncated normal: no tiny grains

        def draw(rng, n):
            r = rng.normal(mean, std, n)
            while np.any(bad := (r < lo) | (r > hi)):
                r[bad] = rng.normal(mean, std, int(bad.sum()))
            return r

        return draw
    raise ValueError(
        f"radius: expected a float, (mean, std) or a callable (rng, n) -> (n,), got {radius!r}."
    )


def _random_rotation(rng: np.random.Generator, dim: int) -> np.ndarray:
    if dim == 2:
        t = rng.uniform(0, 2 * np.pi)
        return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))  # Haar-uniform after the sign fix
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# ------------------------------------------------------------------------------- overlap engine

_DAMP = np.array([1.0, 0.5, 0.25, 0.125, 0.0625])[:, None, None]


def _ellipsoid_gap(delta, mi, mj, gap=None, u0=None, max_iter: int = 30):
    """Separating directions of P ellipsoid pairs: f(u) = u.delta - h_i(u) - h_j(u) over unit u.

    delta: (P, d) centre differences c_i - c_j; mi, mj: (P, d, d) = R diag(a^2) R^T, so that
    h(u) = sqrt(u^T M u); u0: optional (P, d) unit start directions (default delta / |delta|).
    max f is the signed distance of the two ellipsoids (minus the penetration depth if they
    overlap). grad f(u) joins two surface points, so |grad f| bounds the distance from above.
    Riemannian Newton on the sphere (curvature term dropped while f <= 0 so the model stays
    concave) with a backtracking search.

    Returns:
        gap given: (ok (P,) bool: f(u) >= gap proven for some u; undecided counts as False, u).
        gap None: (f (P,) best value found, u (P, d) its direction).
    """
    p, d = delta.shape
    ok, best_f, live = np.zeros(p, bool), np.full(p, -np.inf), np.arange(p)
    u = delta / np.linalg.norm(delta, axis=1, keepdims=True) if u0 is None else u0.copy()
    out, eye = u.copy(), np.eye(d)
    for _ in range(max_iter):
        dl, a, b = delta[live], mi[live], mj[live]
        ma, mb = (a @ u[..., None])[..., 0], (b @ u[..., None])[..., 0]
        ha, hb = np.sqrt(np.sum(u * ma, 1)), np.sqrt(np.sum(u * mb, 1))
        f = np.sum(u * dl, 1) - ha - hb
        g = dl - ma / ha[:, None] - mb / hb[:, None]
        out[live], best_f[live] = u, f
        gt = g - f[:, None] * u  # tangential gradient (g.u = f: f is 1-homogeneous)
        if gap is None:
            keep = np.sum(gt * gt, 1) > 1e-24 * np.sum(dl * dl, 1)
        else:
            ok[live[f >= gap]] = True
            keep = (f < gap) & (np.sum(g * g, 1) >= gap * gap)
        if not keep.any():
            break
        live, u, f, gt, dl, a, b = live[keep], u[keep], f[keep], gt[keep], dl[keep], a[keep], b[keep]
        ma, mb, ha, hb = ma[keep, :, None], mb[keep, :, None], ha[keep, None, None], hb[keep, None, None]
        hess = (ma * ma.transpose(0, 2, 1) / ha**3 - a / ha) + (mb * mb.transpose(0, 2, 1) / hb**3 - b / hb)
        uu = u[:, :, None] * u[:, None, :]
        proj = eye - uu
        model = proj @ hess @ proj - np.maximum(f, 0.0)[:, None, None] * proj - uu
        step = np.linalg.solve(model, -gt[..., None])[..., 0]
        w = u[None] + _DAMP * step[None]
        w /= np.linalg.norm(w, axis=2, keepdims=True)
        wa, wb = (a[None] @ w[..., None])[..., 0], (b[None] @ w[..., None])[..., 0]
        val = np.sum(w * dl, 2) - np.sqrt(np.sum(w * wa, 2)) - np.sqrt(np.sum(w * wb, 2))
        k = np.argmax(val, axis=0)
        better = val[k, np.arange(len(live))] > f
        u = np.where(better[:, None], w[k, np.arange(len(live))], u)
    return (ok if gap is not None else best_f), out


def _box_clearance(x: np.ndarray, mats: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distances from the box planes to the ends of the inclusions' extents in every box section.

    For centres x (K, d) and shape matrices mats (K, d, d) = R diag(a^2) R^T: along each axis c, the
    extent of the inclusion itself and of its sections with the box planes / box edges it meets
    (x_S = 0 or L_S for axis sets S without c) ends somewhere; an end within the gap of a plane
    x_c = 0 or L is a cap, a trace or an edge crossing thinner than the gap. The section of
    {y^T mats^-1 y <= 1} at y_S = t spans mean +- w along c, with (N = mats restricted to S + c)
    mean = N_cS N_SS^-1 t and w^2 = (N_cc - N_cS N_SS^-1 N_Sc)(1 - t N_SS^-1 t).

    Returns:
        dist (K, m): distance of every end to its plane (inf where the section does not exist),
        axis (m,): the axis c of each column, away (K, m): +-1, the direction along c that moves
        the end away from its plane.
    """
    k, d = x.shape
    dists, axes, signs = [], [], []
    for c in range(d):
        others = [a for a in range(d) if a != c]
        for s in range(len(others) + 1):
            for sub in itertools.combinations(others, s):
                S = list(sub)
                nss = mats[:, S][:, :, S]
                ncs = mats[:, c, S]
                gain = np.linalg.solve(nss, ncs[..., None])[..., 0] if S else np.zeros((k, 0))
                var = np.maximum(mats[:, c, c] - np.sum(gain * ncs, axis=1), 0.0)
                for planes in itertools.product((0.0, 1.0), repeat=len(S)):
                    t = np.asarray(planes) * box[S] - x[:, S]  # the plane, seen from the centre
                    sol = np.linalg.solve(nss, t[..., None])[..., 0] if S else t
                    inside = np.sum(t * sol, axis=1)
                    w = np.sqrt(var * np.maximum(1.0 - inside, 0.0))
                    mid = x[:, c] + np.sum(gain * t, axis=1)
                    for end in (mid - w, mid + w):
                        for q in (0.0, box[c]):
                            off = end - q
                            dists.append(np.where(inside < 1.0, np.abs(off), np.inf))
                            axes.append(c)
                            signs.append(np.where(off >= 0, 1.0, -1.0))
    return np.stack(dists, 1), np.asarray(axes), np.stack(signs, 1)


def _shape_matrices(axes, rots):
    return np.einsum("...ij,...j,...kj->...ik", rots, axes * axes, rots)


class _Packing:
    """Placed inclusions with a periodic cell list (spatial hash) and the exact gap test."""

    def __init__(self, box, axes, rots, gap, is_sphere: bool, box_gap: float = 0.0):
        self.box, self.gap, self.box_gap, self.dim = box, gap, box_gap, box.shape[0]
        self.axes, self.rots, self.is_sphere = axes, rots, is_sphere
        self.mats = _shape_matrices(axes, rots)
        self.amax, self.amin = axes.max(1), axes.min(1)
        self.centers = np.zeros((len(axes), self.dim))
        self.placed = np.zeros(len(axes), bool)
        reach = 2 * self.amax.max() + gap  # largest centre distance at which two can interact
        self.nc = np.maximum(1, np.floor(box / reach)).astype(int)
        self.strides = np.cumprod(np.r_[self.nc[1:], 1][::-1])[::-1]
        # an inclusion wider than half the box can meet several images of a neighbour
        self.shifts = image_shifts(self.dim, box) if reach > 0.5 * box.min() else np.zeros((1, self.dim))
        ranges = [np.arange(-1, 2) if n >= 3 else np.arange(n) for n in self.nc]
        self.offsets = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, self.dim)
        self.members = -np.ones((int(np.prod(self.nc)), 8), int)
        self.cache: dict[int, np.ndarray] = {}  # last separating direction of each ellipsoid pair

    def _cells(self, x):
        return (np.floor(wrap(x, self.box) * (self.nc / self.box)).astype(int) % self.nc) @ self.strides

    def insert(self, i, x):
        self.centers[i], self.placed[i] = wrap(x, self.box), True
        row = self.members[self._cells(self.centers[i])]
        free = np.flatnonzero(row < 0)
        if free.size == 0:
            self.members = np.concatenate([self.members, -np.ones_like(self.members)], axis=1)
            row, free = self.members[self._cells(self.centers[i])], [row.size]
        row[free[0]] = i

    def feasible(self, i, x) -> np.ndarray:
        """Whether inclusion i centred at each of x (K, d) keeps the gap to all placed others and
        box_gap to the box planes, edges and corners."""
        k = x.shape[0]
        ok = np.ones(k, bool)
        if self.box_gap > 0:
            dist, _, _ = _box_clearance(wrap(x, self.box), np.broadcast_to(self.mats[i], (k, self.dim, self.dim)),
                                        self.box)
            ok = dist.min(axis=1) >= self.box_gap
        idx = np.floor(wrap(x, self.box) * (self.nc / self.box)).astype(int) % self.nc
        nb = self.members[((idx[:, None, :] + self.offsets[None]) % self.nc) @ self.strides].reshape(k, -1)
        kk, jj = np.nonzero((nb >= 0) & (nb != i))
        if kk.size == 0:
            return ok
        j = nb[kk, jj]
        ns = self.shifts.shape[0]
        base = minimum_image(x[kk] - self.centers[j], self.box)
        kk, j = np.repeat(kk, ns), np.repeat(j, ns)
        delta = (base[:, None, :] + self.shifts[None]).reshape(-1, self.dim)
        dist = np.sqrt(np.einsum("pi,pi->p", delta, delta))
        far = dist >= self.amax[i] + self.amax[j] + self.gap
        if self.is_sphere:  # exact
            np.logical_and.at(ok, kk[~far], False)
            return ok
        sure = dist < self.amin[i] + self.amin[j] + self.gap  # inscribed balls already too close
        np.logical_and.at(ok, kk[sure], False)
        amb = ~far & ~sure & ok[kk]
        if np.any(amb):
            jm, da = j[amb], delta[amb]
            key = np.minimum(i, jm) * len(self.axes) + np.maximum(i, jm)
            sign = np.where(i < jm, 1.0, -1.0)[:, None]  # the cache holds u for c_min - c_max
            u0 = da / np.linalg.norm(da, axis=1, keepdims=True)
            got = [self.cache.get(q) for q in key.tolist()]
            has = np.array([q is not None for q in got])
            if has.any():  # warm start from the pair's last separating direction
                cu = np.stack([q for q in got if q is not None]) * sign[has]
                fits = np.sum(cu * da[has], 1) > 0
                u0[np.flatnonzero(has)[fits]] = cu[fits]
            sep, u = _ellipsoid_gap(da, np.broadcast_to(self.mats[i], (len(jm), self.dim, self.dim)),
                                    self.mats[jm], self.gap, u0)
            self.cache.update(zip(key[sep].tolist(), sign[sep] * u[sep]))
            np.logical_and.at(ok, kk[amb][~sep], False)
        return ok


def _relax(box, axes, mats, x, gap, is_sphere, max_iter, box_gap=0.0):
    """Force-biased overlap removal: every pair closer than the gap (plus a small slack) is pushed
    apart along its separating direction, shared by volume (small ones move more), all pairs at
    once; an inclusion whose cap, trace or edge crossing ends within box_gap of a box plane moves
    along that plane's axis, to the nearer side. Returns the wrapped centres (N, d), or None if
    pairs still overlap after max_iter."""
    from scipy.spatial import cKDTree

    n, d = x.shape
    amax, weight = axes.max(1), np.prod(axes, axis=1)
    slack = 1e-3 * axes.min()  # pairs must clear gap + slack (the exact check must pass), pushed to + 2 slack
    target = gap + 2 * slack
    cutoff = 2 * amax.max() + target
    shifts = image_shifts(d, box) if cutoff > 0.5 * box.min() else np.zeros((1, d))  # as in _Packing
    prev_key, prev_u, top = np.zeros(0, int), np.zeros((0, d)), np.nextafter(box, 0)
    for _ in range(max_iter):
        x = np.minimum(wrap(x, box), top)
        i, j = cKDTree(x, boxsize=box).query_pairs(cutoff, output_type="ndarray").T
        delta = (minimum_image(x[i] - x[j], box)[:, None] + shifts[None]).reshape(-1, d)
        i, j, im = np.repeat(i, len(shifts)), np.repeat(j, len(shifts)), np.tile(np.arange(len(shifts)), len(i))
        dist = np.maximum(np.linalg.norm(delta, axis=1), 1e-300)
        near = dist < amax[i] + amax[j] + target
        i, j, im, delta, dist = i[near], j[near], im[near], delta[near], dist[near]
        u = delta / dist[:, None]
        if is_sphere:
            f = dist - amax[i] - amax[j]
        else:  # warm start from the previous iteration's directions
            key = (i * n + j) * len(shifts) + im
            pos = np.minimum(np.searchsorted(prev_key, key), max(len(prev_key) - 1, 0))
            hit = (pos < len(prev_key)) & (prev_key[pos] == key) if len(prev_key) else np.zeros(len(key), bool)
            u[hit] = prev_u[pos[hit]]
            mi, mj = mats[i], mats[j]
            f = np.sum(u * delta, 1) - np.sqrt(np.einsum("pi,pij,pj->p", u, mi, u)) - np.sqrt(
                np.einsum("pi,pij,pj->p", u, mj, u))  # lower bound: pairs above gap + slack are done
            low = f < gap + slack
            f[low], u[low] = _ellipsoid_gap(delta[low], mi[low], mj[low], None, u[low], max_iter=8)
            order = np.argsort(key)
            prev_key, prev_u = key[order], u[order]
        push = target - f
        bad = push > slack
        disp = np.zeros_like(x)
        if box_gap > 0:
            end_dist, end_axis, away = _box_clearance(x, mats, box)
            move = np.where(end_dist < box_gap + slack, (box_gap + 2 * slack - end_dist) * away, 0.0)
            for c in range(d):
                disp[:, c] += move[:, end_axis == c].sum(axis=1)
        if not bad.any() and not disp.any():
            return x
        share = weight[j] / (weight[i] + weight[j])
        np.add.at(disp, i[bad], (push * share)[bad, None] * u[bad])
        np.add.at(disp, j[bad], -(push * (1 - share))[bad, None] * u[bad])
        x = x + disp
    return None


# ------------------------------------------------------------------------------ random inclusions


def _draw_axes(rng, sampler, shape, aspect, dim, m) -> np.ndarray:
    """Semi-axes (m, d) of m inclusions: radius = largest semi-axis, prolate for ellipsoids."""
    r = sampler(rng, m)
    if np.any(~np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"radius: expected positive radii, the distribution gave {r[~(r > 0)][:3]}.")
    k = rng.uniform(aspect[0], aspect[1], m) if shape == "ellipsoid" else np.ones(m)
    return np.concatenate([r[:, None], np.repeat((r / k)[:, None], dim - 1, axis=1)], axis=1)


def _draw_pool(rng, draw, n, target, box_volume, tol, dim, scale_to_fraction=False) -> np.ndarray:
    """Semi-axes (m, d), largest first, of n inclusions or of inclusions whose volumes sum to `target`
    (scale_to_fraction: n inclusions, all scaled by one factor so that their volumes sum to `target`)."""
    if n is not None:
        axes = draw(n)
        if scale_to_fraction:
            axes *= (target / (unit_ball_volume(dim) * float(np.sum(np.prod(axes, axis=1))))) ** (1 / dim)
    else:
        chunks, total = [], 0.0
        while total < target:
            chunks.append(draw(64))
            total += unit_ball_volume(dim) * float(np.sum(np.prod(chunks[-1], axis=1)))
            if len(chunks) > 10_000:
                raise ValueError("radius: the distribution draws radii too small for the target fraction.")
        axes = np.concatenate(chunks)
        cum = np.cumsum(unit_ball_volume(dim) * np.prod(axes, axis=1))
        m = int(np.searchsorted(cum, target))  # first index reaching the target
        axes = axes[: m + 1].copy()
        before = cum[m - 1] if m > 0 else 0.0
        shrink = ((target - before) / (cum[m] - before)) ** (1 / dim)
        axes[m] *= shrink  # the last one hits the target exactly, unless it becomes a speck
        if shrink < 0.5 and target - before < 0.5 * tol * box_volume and m > 0:
            axes = axes[:m]
    return axes[np.argsort(-np.prod(axes, axis=1), kind="stable")]


def random_inclusions(
    box: Sequence[float],
    *,
    n: int | None = None,
    volume_fraction: float | None = None,
    shape: str = "sphere",
    radius=(0.08, 0.02),
    aspect=(1.0, 2.0),
    min_gap: float = 0.0,
    box_gap: float | None = None,
    seed: int = 0,
    max_attempts: int = 500,
    tol: float = 0.005,
    max_relax_iter: int = 3000,
    scale_to_fraction: bool = False,
) -> list[InclusionSpec]:
    """Periodic random sequential addition (RSA) of spheres or ellipsoids (2D: circles/ellipses) with a gap.

    Sizes are drawn from `radius`, sorted largest first, and each inclusion is dropped at up to
    `max_attempts` uniform random positions until it keeps `min_gap` (periodic minimum image, exact
    test) from all placed ones. Inclusions that find no room are dropped anywhere and the whole set
    is densified by force-biased overlap removal, then every inclusion is checked again exactly.

    Args:
        box: (d,) box lengths, d in {2, 3}.
        n: number of inclusions; volume_fraction: target inclusion fraction in (0, 1). Give either
            or both (then it stops at whichever is reached first; of the n drawn, one that would
            overshoot the fraction by more than tol is left out; with scale_to_fraction, all n).
        shape: "sphere" or "ellipsoid" (prolate spheroid, uniformly random orientation).
        radius: radius / largest semi-axis: a float, (mean, std) of a normal truncated to
            [max(mean - 2 std, mean / 4), mean + 2 std], or a callable (rng, n) -> (n,) radii.
        aspect: largest / smallest semi-axis of ellipsoids, uniform in [aspect[0], aspect[1]] (or a float).
        min_gap: guaranteed minimum distance between inclusion surfaces, also across periodic faces.
        box_gap: guaranteed clearance from the box (None: min_gap): every cap cut off by a box plane,
            every trace on a box face and every crossing of a box edge either extends at least box_gap
            past the plane, edge or corner it approaches or stays box_gap away from it, so the mesh
            never needs elements thinner than box_gap there. 0 places inclusions anywhere.
        seed: random seed (same seed, same result).
        max_attempts: random positions tried per inclusion before it is left to densification.
        tol: accepted |reached - target| volume fraction (the pool is drawn to hit the target).
        max_relax_iter: iterations allowed for densification.
        scale_to_fraction: with n and volume_fraction both given, scale the n drawn sizes by one common
            factor so that n inclusions fill volume_fraction exactly; `radius` then sets the spread of
            the sizes relative to their mean, not their scale.

    Returns:
        list of InclusionSpec, centres in [0, L).

    Raises:
        ValueError: bad arguments. MeshingError: jammed (says which fraction could be reached).

    Example:
        >>> specs = random_inclusions((1.0, 1.0, 1.0), n=20, radius=0.1, min_gap=0.02)
    """
    from ._errors import MeshingError

    box = _check_box(box)
    dim = box.shape[0]
    if shape not in ("sphere", "ellipsoid"):
        raise ValueError(f"shape: expected 'sphere' or 'ellipsoid', got {shape!r}.")
    if n is None and volume_fraction is None:
        raise ValueError("random_inclusions: expected n or volume_fraction (or both), got neither.")
    if scale_to_fraction and (n is None or volume_fraction is None):
        raise ValueError("scale_to_fraction: expected both n and volume_fraction, got "
                         f"n={n!r}, volume_fraction={volume_fraction!r}.")
    if n is not None and (isinstance(n, bool) or int(n) != n or n < 1):
        raise ValueError(f"n: expected a positive integer, got {n!r}.")
    if volume_fraction is not None and not 0 < volume_fraction < 1:
        raise ValueError(
            f"volume_fraction: expected a value in (0, 1), got {volume_fraction!r}. "
            "Hint: random packings reach about 0.5 with a broad size distribution."
        )
    if not np.isfinite(min_gap) or min_gap < 0:
        raise ValueError(f"min_gap: expected a finite value >= 0, got {min_gap!r}. Hint: 0 allows touching.")
    box_gap = float(min_gap) if box_gap is None else box_gap
    if not np.isfinite(box_gap) or box_gap < 0:
        raise ValueError(f"box_gap: expected a finite value >= 0 (or None: min_gap), got {box_gap!r}.")
    if not tol > 0 or max_attempts < 1:
        raise ValueError(f"tol > 0 and max_attempts >= 1 expected, got {tol!r}, {max_attempts!r}.")
    lo_k, hi_k = (float(aspect),) * 2 if np.ndim(aspect) == 0 else (float(aspect[0]), float(aspect[1]))
    if shape == "ellipsoid" and not 1.0 <= lo_k <= hi_k:
        raise ValueError(f"aspect: expected 1 <= aspect[0] <= aspect[1], got {aspect!r}.")

    rng = np.random.default_rng(checked_seed(seed))
    box_volume = float(np.prod(box))
    target = volume_fraction * box_volume if volume_fraction is not None else np.inf
    sampler = _radius_sampler(radius)
    axes = _draw_pool(
        rng, lambda m: _draw_axes(rng, sampler, shape, (lo_k, hi_k), dim, m), n, target, box_volume, tol, dim,
        scale_to_fraction,
    )
    if axes[:, 0].max() + min_gap / 2 > box.min() / 2:
        raise ValueError(
            f"radius: an inclusion of radius {axes[:, 0].max():.4g} (+ half the gap {min_gap / 2:.4g}) is larger "
            f"than half the box {box.min():.4g}: it would touch its own periodic image. Hint: smaller radii or "
            + ("more inclusions or a lower fraction (the sizes are scaled to fill it)" if scale_to_fraction else
               "a larger box") + "."
        )
    rots = np.stack([_random_rotation(rng, dim) if shape == "ellipsoid" else np.eye(dim) for _ in axes])
    vols = unit_ball_volume(dim) * np.prod(axes, axis=1)

    pack = _Packing(box, axes, rots, float(min_gap), shape == "sphere", box_gap)
    committed, deferred, batch = 0.0, [], 32
    # a fraction-only or scaled pool sums to target: place all of it
    enough = target - (0.5 * tol if n is not None and not scale_to_fraction else 1e-12) * box_volume
    for i in range(len(axes)):
        if committed >= enough:
            break
        if n is not None and committed + vols[i] > target + tol * box_volume:
            continue  # it would overshoot the fraction: a smaller one (they come largest first) may fit
        committed += vols[i]
        for _ in range(-(-max_attempts // batch)):
            x = rng.uniform(0, 1, (batch, dim)) * box
            ok = pack.feasible(i, x)
            if ok.any():
                pack.insert(i, x[np.argmax(ok)])
                break
        else:
            deferred.append(i)
    used = np.array(sorted(np.flatnonzero(pack.placed).tolist() + deferred))
    fraction = vols[used].sum() / box_volume
    if deferred:  # densify: drop the rest anywhere, push overlaps apart, check everything again
        x = pack.centers.copy()
        x[deferred] = rng.uniform(0, 1, (len(deferred), dim)) * box
        relaxed = _relax(box, axes[used], pack.mats[used], x[used], float(min_gap), shape == "sphere",
                         max_relax_iter, box_gap)
        if relaxed is None:
            raise MeshingError(
                "random_inclusions",
                f"jammed: RSA placed volume fraction {vols[pack.placed].sum() / box_volume:.4f} "
                f"({int(pack.placed.sum())} inclusions); {len(deferred)} more (up to {fraction:.4f}) could not be "
                f"separated by {min_gap} (box clearance {box_gap}) within {max_relax_iter} relaxation iterations. "
                "Hint: broaden the size distribution, lower the fraction or the gap, or raise max_relax_iter.",
            )
        pack = _Packing(box, axes, rots, float(min_gap), shape == "sphere", box_gap)
        for q, i in enumerate(used):
            pack.insert(i, relaxed[q])
        bad = [int(i) for i in used if not pack.feasible(i, pack.centers[i][None])[0]]
        if bad:
            raise MeshingError("random_inclusions", f"densified packing failed the exact gap check at {bad[:5]}.")
    if volume_fraction is not None and (n is None or len(used) < n) and abs(fraction - volume_fraction) > tol:
        share = vols / box_volume
        if share.min() > tol:  # the ones left out would overshoot the target
            hint = (f"each of these inclusions fills {share.min():.1%} to {share.max():.1%} of the box, so the "
                    f"fraction moves in steps coarser than +- {tol}: smaller radii (more of them)")
        else:
            hint = f"n={n} is too small for this fraction with these radii"
        raise MeshingError(
            "random_inclusions",
            f"reached volume fraction {fraction:.4f} with {len(used)} inclusions, target {volume_fraction} "
            f"+- {tol}. Hint: {hint}.",
        )
    kind = "sphere" if shape == "sphere" else "ellipsoid"
    return [InclusionSpec(kind, pack.centers[i].copy(), axes[i], rots[i]) for i in used]


# ------------------------------------------------------------------------------------ level sets


def _ellipsoid_sdf_np(y: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Exact signed distance of local points y (m, d) to the axis-aligned ellipsoid with semi-axes a (d,).

    Same scheme as geometry._shapes.ellipsoid_sdf: Newton on the shifted Lagrange multiplier
    s = t + a_min^2 from a start left of the root, closed form on the medial plane.
    """
    scale = a.max()
    y, a = y / scale, a / scale
    a2 = a * a
    a2min = a2.min()
    is_min = a2 <= a2min * (1 + 1e-12)
    off = np.where(is_min, 0.0, a2 - a2min)
    off_safe = np.where(is_min, 1.0, off)
    q = np.where(is_min, 0.0, a * y / off_safe)
    deg = np.all(np.where(is_min, y == 0, True), axis=1) & (np.sum(q * q, 1) < 1)
    out = np.empty(len(y))
    gd = np.where(is_min, 0.0, y[deg] * a2min / off_safe)
    out[deg] = -np.sqrt(np.sum(gd * gd, 1) + a2min * (1 - np.sum(q[deg] ** 2, 1)))
    yr = y[~deg]
    ay = a * yr
    s = np.maximum(np.max(a * np.abs(yr) - off, axis=1), 1e-150)
    for _ in range(100):
        den = off + s[:, None]
        r = ay / den
        step = (np.sum(r * r, 1) - 1) / (2 * np.sum(r * r / den, 1))
        s = np.maximum(s + step, s)  # convex, decreasing residual: iterates rise to the root
        if np.all(np.abs(step) <= 1e-14 * s):
            break
    out[~deg] = (s - a2min) * np.linalg.norm(yr / (off + s[:, None]), axis=1)
    return out * scale


def _spec_sdf_np(spec: InclusionSpec, points: np.ndarray) -> np.ndarray:
    local = points - spec.center
    if spec.kind == "sphere":
        return np.linalg.norm(local, axis=-1) - spec.axes[0]
    return _ellipsoid_sdf_np(local @ spec.rotation, spec.axes)


def sample_levelset(specs: Sequence[InclusionSpec], box, grid_shape) -> np.ndarray:
    """Global periodic DN1 field (min over inclusions and their images of the exact SDF) on the grid.

    Args:
        specs: inclusions (centres anywhere; the field is periodic).
        box: (d,) lengths; grid_shape: (d,) nodes per axis, node i at x = i L / n.

    Returns:
        phi (grid_shape), float64, negative inside inclusions.
    """
    box = _check_box(box)
    shape = _check_grid(grid_shape, box.shape[0])
    if len(specs) == 0 or any(not isinstance(s, InclusionSpec) or s.dim != box.shape[0] for s in specs):
        raise ValueError(
            f"specs: expected a non-empty list of {box.shape[0]}D InclusionSpec, got {len(specs)} entries. "
            "Hint: use random_inclusions(...) or InclusionSpec(kind, center, axes, rotation)."
        )
    h = box / np.asarray(shape)
    coords = [np.arange(n) * hk for n, hk in zip(shape, h)]
    pts = np.stack(np.meshgrid(*coords, indexing="ij"), axis=-1)
    # upper bound everywhere: each inclusion holds the ball of radius a_min about its centre, and the
    # minimum over a few nearest centres bounds the minimum over all (a k-d tree, not N grid passes)
    dist, near = nearest_centres(pts.reshape(-1, len(shape)), np.stack([s.center for s in specs]), box, k=8)
    ub = np.min(dist - np.array([s.axes.min() for s in specs])[near], axis=1).reshape(shape)
    reach = max(float(ub.max()), 0.0)
    phi = ub.copy()
    for s in specs:
        rad = s.axes.max() + reach  # beyond this the copy cannot be the nearest
        for shift in image_shifts(box.shape[0], box):  # copies of the wrapped centre: enough
            c = wrap(s.center, box) + shift
            lo = np.maximum(np.ceil((c - rad) / h), 0).astype(int)
            hi = np.minimum(np.floor((c + rad) / h), np.asarray(shape) - 1).astype(int)
            if np.any(hi < lo):
                continue
            block = tuple(slice(a, b + 1) for a, b in zip(lo, hi))
            sub = pts[block]
            lower = np.linalg.norm(sub - c, axis=-1) - s.axes.max()
            todo = lower < phi[block]
            if todo.any():
                vals = _spec_sdf_np(s, sub[todo] - (c - s.center))
                view = phi[block]  # a view: writes go to phi
                view[todo] = np.minimum(view[todo], vals)
    return phi


def gaussian_random_field(box, grid_shape, correlation_length: float, seed: int = 0) -> np.ndarray:
    """Periodic Gaussian random field on the node grid (node i at x = i L / n): zero mean, unit
    variance, covariance exp(-r^2 / (2 l^2)), made by filtering white noise with the square root of
    its spectral density in Fourier space. No checks: `excursion_set` validates its arguments."""
    shape = tuple(int(n) for n in grid_shape)
    h = np.asarray(box, float) / np.asarray(shape)
    rng = np.random.default_rng(seed)
    k2 = sum(np.meshgrid(*[(2 * np.pi * np.fft.fftfreq(n, d=hk)) ** 2 for n, hk in zip(shape, h)], indexing="ij"))
    field = np.fft.ifftn(np.fft.fftn(rng.normal(size=shape)) * np.exp(-0.25 * correlation_length**2 * k2)).real
    return (field - field.mean()) / field.std()


def excursion_set(box, grid_shape, *, correlation_length: float, volume_fraction: float, seed: int = 0) -> np.ndarray:
    """Excursion set of a periodic Gaussian random field, as a signed-distance-like level set.

    The field has covariance exp(-r^2 / (2 l^2)) (l = correlation_length), made by filtering white
    noise with the square root of its spectral density in Fourier space, so it is exactly periodic.
    Inclusions are {field < u}, made admissible for the mesher at the grid's resolution: specks it does
    not resolve (fewer than 8 nodes or under 1.5 steps thick) are dropped, necks narrower than a grid
    step are cut (their thin nodes become matrix), and of two components less than a quarter step
    apart, also across a grid cell, the smaller is dropped (the mesher refuses 0.02 steps as touching,
    and would refine such gaps far). The level u is then moved until the node fraction is
    `volume_fraction` to within 0.005 (5 % of fractions under 0.1), or the nearest of six tries (a
    drop makes it jump). phi is the field divided by its gradient norm at nodes next to the interface
    (a first-order distance), extended elsewhere by the periodic Euclidean distance transform to those
    nodes.

    Args:
        box: (d,) lengths; grid_shape: (d,) nodes per axis (node i at x = i L / n).
        correlation_length: l > 0 (a few grid steps at least). volume_fraction: in (0, 1).
        seed: random seed.

    Returns:
        phi (grid_shape), float64, negative inside.
    """
    box = _check_box(box)
    shape = _check_grid(grid_shape, box.shape[0])
    h = box / np.asarray(shape)
    if not (np.isfinite(correlation_length) and correlation_length > 0):
        raise ValueError(f"correlation_length: expected a positive length, got {correlation_length!r}.")
    if not 0 < volume_fraction < 1:
        raise ValueError(f"volume_fraction: expected a value in (0, 1), got {volume_fraction!r}.")
    if correlation_length < h.max() or correlation_length > box.min():
        raise ValueError(
            f"correlation_length: expected between one grid step {h.max():.4g} and the box {box.min():.4g}, got "
            f"{correlation_length!r}. Hint: refine the grid or choose l of a few percent of the box."
        )
    field = gaussian_random_field(box, shape, correlation_length, checked_seed(seed))
    target, best = volume_fraction, None
    tol = min(_FRACTION_TOL, _FRACTION_RTOL * target)
    lo, hi, level, bracketed = 0.0, 1.0, target, False
    for _ in range(_LEVEL_ROUNDS):
        try:
            phi = _admissible_excursion(field - np.quantile(field, level), box, correlation_length)
        except _NothingAdmissible as error:  # try a higher level
            phi, fraction, failure = None, 0.0, error
        else:
            fraction = float((phi < 0).mean())
        if phi is not None and (best is None or abs(fraction - target) < abs(best[1] - target)):
            best = (phi, fraction)
        if phi is not None and abs(fraction - target) <= tol:
            break
        # repairs only remove nodes, so the fraction is at most the level; it jumps where a drop comes
        # or goes, so bracket the level and bisect once it is bracketed
        if fraction < target:
            lo = level
        else:
            hi, bracketed = level, True
        secant = level + target - fraction
        level = secant if lo < secant < hi and not bracketed else 0.5 * (lo + hi)
    if best is None:
        raise failure
    return best[0]


_LEVEL_ROUNDS = 6
_FRACTION_TOL, _FRACTION_RTOL = 0.005, 0.05  # node fraction (random_inclusions' default tol), 5 % of small ones
_MAX_DROP_ROUNDS = 8
_SEPARATION_STEPS = 0.25  # closest components kept, in grid steps


class _NothingAdmissible(ValueError):
    """No admissible excursion set at one level: `excursion_set` tries another before it gives up."""


def _admissible_excursion(g: np.ndarray, box: np.ndarray, correlation_length: float) -> np.ndarray:
    """phi of {g < 0} less what Microstructure.from_levelset would refuse (see `excursion_set`)."""
    from .geometry._components import first_order_distance  # lazy: the geometry package imports jax

    h = box / np.asarray(g.shape)
    inside, cut = g < 0, np.zeros(g.shape, bool)
    for _ in range(_MAX_DROP_ROUNDS):
        if not inside.any():
            break
        phi = first_order_distance(g, inside, h, periodic=True)
        phi[cut] = np.maximum(phi[cut], h.max())  # a cut node is a step outside: the pieces stay a step apart
        dropped, necks = _refused_components(phi, box)
        if not (dropped.any() or necks.any()):
            return phi
        inside &= ~(dropped | necks)
        cut |= necks
    raise _NothingAdmissible(
        f"excursion_set: no admissible excursion set at this resolution (correlation_length "
        f"{correlation_length:g}, grid step {h.max():.4g}): "
        + ("every component was too small, too thin or too close to another" if not inside.any() else
           f"components still too thin or too close after {_MAX_DROP_ROUNDS} rounds of repairs")
        + ". Hint: a correlation length of at least 4 grid steps, or a finer grid."
    )


def _refused_components(phi: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """(grid) bool masks by Microstructure.from_levelset's own verdicts: the nodes to drop (components
    the grid does not resolve; then the smaller of each pair closer than _SEPARATION_STEPS, and any
    necked component whose neck the periodic grid does not show) and the neck nodes to cut (necks
    below one grid step)."""
    from .geometry._components import _NECK_STEPS, _unresolved, label_components, neck_nodes
    from .geometry._microstructure import Microstructure

    ms = Microstructure.from_levelset(phi, tuple(box), check_sizes=False, check_gaps=False, check_necks=False)
    labels, n = label_components(phi < 0, True)  # the same ids as ms.inclusions
    specks = np.zeros(n + 1, bool)
    specks[[inc.id for inc in ms.inclusions
            if _unresolved(inc.description["n_samples"], inc.description["thickness"])]] = True
    if specks.any():  # first: the other verdicts may change without them
        return specks[labels], np.zeros(phi.shape, bool)
    necked = _necked_ids(ms, n)
    cut = neck_nodes(phi, labels, _NECK_STEPS) & necked[labels] if necked.any() else np.zeros(phi.shape, bool)
    uncut = necked & ~np.isin(np.arange(n + 1), labels[cut])
    return (_touching_ids(ms, phi, labels, n) | uncut)[labels], cut


def _touching_ids(ms, phi: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n + 1,) bool: the smaller of each pair of components closer than _SEPARATION_STEPS, by the
    loader's estimates (`close_pairs`, and `diagonal_gaps` across a grid cell)."""
    from .geometry._components import close_pairs
    from .geometry._microstructure import diagonal_gaps

    spacing = np.asarray(ms.box) / np.asarray(labels.shape)
    ids, _, _ = close_pairs(ms.dn1, ms.dn2, ms.nearest_id, labels, spacing, _SEPARATION_STEPS * spacing.min(),
                            True, limit=n)
    pairs, gaps, _ = diagonal_gaps(ms, phi, labels)
    ids = np.concatenate([ids, pairs[gaps < _SEPARATION_STEPS * spacing.min()]])
    counts = np.bincount(labels.ravel(), minlength=n + 1)
    drop = np.zeros(n + 1, bool)
    for a, b in ids:
        drop[a if b == 0 or counts[a] <= counts[b] else b] = True
    return drop


def _necked_ids(ms, n: int) -> np.ndarray:
    """(n + 1,) bool: the components with a neck below one grid step (found by the loader)."""
    drop = np.zeros(n + 1, bool)
    drop[[inc.id for inc in ms.inclusions if "neck_steps" in inc.description]] = True
    return drop


def spanning_components(phi: np.ndarray) -> list[int]:
    """Ids (as Microstructure.from_levelset numbers them) of the periodic components of phi < 0 whose
    nodes cover a whole axis: they reach their own periodic image (percolate)."""
    from .geometry._components import component_arcs, label_components

    labels, n = label_components(phi < 0, True)
    _, lengths = component_arcs(labels, n, True)
    return [int(i) + 1 for i in np.flatnonzero((lengths >= np.asarray(phi.shape)).any(axis=1))]


# ------------------------------------------------------------------------------ files, structures


def microstructure_from_specs(specs: Sequence[InclusionSpec], box, grid_shape, periodic: bool = True):
    """Microstructure of exact analytic inclusions (geometry._shapes SDFs) via Microstructure.from_functions."""
    from .geometry._microstructure import Microstructure
    from .geometry._shapes import ellipsoid_sdf, sphere_sdf

    box = _check_box(box)
    if len(specs) == 0 or any(not isinstance(s, InclusionSpec) or s.dim != box.shape[0] for s in specs):
        raise ValueError(f"specs: expected a non-empty list of {box.shape[0]}D InclusionSpec.")
    fns = [sphere_sdf(s.center, float(s.axes[0])) if s.kind == "sphere" else ellipsoid_sdf(s.center, s.axes, s.rotation)
           for s in specs]
    desc = [{"kind": s.kind, "center": s.center.tolist(), "axes": s.axes.tolist()} for s in specs]
    return Microstructure.from_functions(fns, tuple(box.tolist()), _check_grid(grid_shape, box.shape[0]),
                                         periodic=periodic, volumes=[s.volume for s in specs], descriptions=desc)


def write_input(path, specs_or_none, box, grid_shape, *, phi=None, periodic: bool = True) -> None:
    """Write an RVE input .npz atomically (temporary file in the same folder, then os.replace).

    Keys: phi (grid_shape float64 global field), box, periodic, and for analytic specs kind (N,) str,
    centers (N, d), axes (N, d), rotations (N, d, d). phi defaults to sample_levelset(specs, ...).
    """
    box = _check_box(box)
    shape = _check_grid(grid_shape, box.shape[0])
    if phi is None:
        if not specs_or_none:
            raise ValueError("write_input: expected specs or phi, got neither. Hint: phi=excursion_set(...).")
        phi = sample_levelset(specs_or_none, box, shape)
    phi = np.asarray(phi, dtype=np.float64)
    if phi.shape != shape or not np.all(np.isfinite(phi)):
        raise ValueError(f"phi: expected finite values of shape {shape}, got shape {phi.shape}.")
    data = {"phi": phi, "box": box, "periodic": np.asarray(bool(periodic))}
    if specs_or_none:
        data.update(
            kind=np.array([s.kind for s in specs_or_none]),
            centers=np.stack([s.center for s in specs_or_none]),
            axes=np.stack([s.axes for s in specs_or_none]),
            rotations=np.stack([s.rotation for s in specs_or_none]),
        )
    path = os.fspath(path)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=os.path.dirname(os.path.abspath(path)))
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def microstructure_from_npz(data: Mapping):
    """Rebuild the exact analytic Microstructure from a mapping written by write_input; None if it has no specs."""
    if not all(k in data for k in ("kind", "centers", "axes", "rotations", "box", "phi")):
        return None
    specs = [InclusionSpec(str(k), c, a, r)
             for k, c, a, r in zip(data["kind"], data["centers"], data["axes"], data["rotations"])]
    periodic = bool(np.asarray(data.get("periodic", True)).item())
    return microstructure_from_specs(specs, np.asarray(data["box"], float), np.shape(data["phi"]), periodic)
