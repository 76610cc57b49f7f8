"""Interface curves of a 2D microstructure, periodic or not (NumPy only, never imports jax).

Paper section 4.4 in 2D: each inclusion's zero contour is extracted ON ITS OWN from its own
level set sampled on a local window (its bounds + a margin, in unwrapped coordinates: the
level set is periodic, so the window may stick out of the box), with
``skimage.measure.find_contours``. A closed contour in unwrapped coordinates is then cut by
the lattice lines x = k Lx and y = m Ly; every piece between two crossings lies in one
lattice cell and is translated into the box. A crossing on x = k Lx is one point on the
master edge x = 0 and its translate on x = Lx: both arcs that meet there share it.
An inclusion that reaches its own periodic image along an axis (a band, a channel) has no closed
contour: its window spans the box plus a cap there (:func:`capped_values`), the loops are cut as
above, only the pieces inside the box are kept, and their crossings of x = 0 and x = Lx, two
copies of one periodic point, are merged (:func:`join_capped_crossings`).

Section 4.5 in 2D: the box edges are meshed once on the master edges (x = 0, y = 0) between
the crossings and corners, at spacing ~h, and copied to the opposite edges. The result is a
:class:`PSLG` whose box segments know their translated partners, so that any later split of a
box segment (:func:`split_segments`) is mirrored and the boundary stays periodic.

Non-periodic boxes (:func:`box_window_axes`, :func:`extract_box_loops`, :func:`clip_loop`,
:func:`assemble_box_pslg`): the window is clipped to the closed box and padded with positive
samples on the box lines, so a contour cut by a side closes along that side; the pieces inside
the box are kept, the rest is dropped. Each of the four sides has its own crossings and nodes,
and no segment has a partner.

The level-set numerics (projection onto phi = 0) arrive as callbacks from the JAX side.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from skimage.measure import find_contours

from ._errors import MeshingError
from ._periodic import wrap


# node kinds of a PSLG
INTERIOR, INTERFACE, BOX_EDGE, FIXED = 0, 1, 2, 3
BOX_SEGMENT = -1  # segment_inclusion of box-edge segments


@dataclass
class PSLG:
    """Constrained nodes and segments of a 2D box (periodic, or with four independent sides).

    Attributes:
        points: (n, 2) node coordinates in [0, Lx] x [0, Ly].
        segments: (s, 2) node ids of the constrained segments.
        segment_inclusion: (s,) inclusion id of interface segments, ``BOX_SEGMENT`` (-1) for box edges.
        segment_partner: (s,) id of the translated box segment on the opposite edge (-1 if none);
            the partner lists its nodes in the same order.
        node_kind: (n,) INTERFACE (on a level set), BOX_EDGE (slides along its edge) or FIXED
            (box corner or interface/box crossing).
        node_axis: (n,) normal axis of the box line a BOX_EDGE/FIXED-crossing node sits on (-1 otherwise).
        node_inclusion: (n,) inclusion id of interface and crossing nodes (0 otherwise).
        periodic_pairs: axis -> (k, 2) (node on x_axis = 0, its translate on x_axis = L); {} when
            not periodic.
        box: (Lx, Ly).
        periodic: opposite box edges are translates (False: every box segment is partnerless).
    """

    points: np.ndarray
    segments: np.ndarray
    segment_inclusion: np.ndarray
    segment_partner: np.ndarray
    node_kind: np.ndarray
    node_axis: np.ndarray
    node_inclusion: np.ndarray
    periodic_pairs: dict[int, np.ndarray] = field(default_factory=dict)
    box: tuple[float, float] = (1.0, 1.0)
    periodic: bool = True

    @property
    def n_points(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Crossing:
    """An interface crossing a box line.

    Attributes:
        axis: normal axis of the line: the point is (0, t) / (Lx, t) for axis 0, (t, 0) / (t, Ly) for axis 1.
        t: coordinate along the line, in (0, L_other).
        inclusion_id: the inclusion whose interface crosses.
    """

    axis: int
    t: float
    inclusion_id: int


@dataclass
class Arc:
    """A piece of an interface inside the box.

    Attributes:
        inclusion_id: owner inclusion.
        points: (k, 2) box coordinates; open arcs include both crossing endpoints, closed loops
            do not repeat their first point.
        closed: a loop that never meets the box boundary.
        start, end: (crossing index, side) of the endpoints of an open arc, side 0 = on the master
            line x_axis = 0, side 1 = on x_axis = L; None for a closed loop.
    """

    inclusion_id: int
    points: np.ndarray
    closed: bool
    start: tuple[int, int] | None = None
    end: tuple[int, int] | None = None


# ----------------------------------------------------------------------------- extraction
def window_grid(lower, upper, step: float, margin: float, box, capped=(), cap: float = 0.0):
    """Sample coordinates of a local window around an inclusion.

    Args:
        lower, upper: (2,) unwrapped bounds of the inclusion. step: sample spacing.
        margin: added on every side. box: (2,) lengths (the window must stay shorter than the box,
            else periodic images of the inclusion would enter it), except along the `capped` axes,
            where it spans [-cap - margin, L + cap + margin] (see :func:`capped_values`).
    Returns:
        (origin (2,), shape (2,) int): samples at origin + i * step.
    """
    L = np.asarray(box, dtype=float)
    inner = np.isin(np.arange(2), capped)
    lower = np.where(inner, -cap, np.asarray(lower, dtype=float)) - margin
    upper = np.where(inner, L + cap, np.asarray(upper, dtype=float)) + margin
    if np.any((upper - lower >= L) & ~inner):
        raise ValueError(
            f"expected an inclusion window shorter than the box {tuple(box)}, got extent {tuple(upper - lower)}; "
            "hint: an inclusion spanning (almost) the whole box cannot be meshed as a closed curve"
        )
    shape = np.ceil((upper - lower) / step).astype(np.int64) + 1
    return lower, shape


def extract_loops(values: np.ndarray, origin, step: float, inclusion_id: int) -> list[np.ndarray]:
    """Closed zero contours of a window sample, in unwrapped coordinates.

    Args:
        values: (nx, ny) samples of the inclusion's level set at origin + (i, j) * step.
        origin: (2,). step: spacing. inclusion_id: for error messages.
    Returns:
        list of (k, 2) loops (first point not repeated). Raises MeshingError when a contour is
        open (the inclusion reaches the window boundary).
    """
    values = np.asarray(values, dtype=float)
    if not np.any(values < 0):
        raise MeshingError("contours", "the level set has no negative sample in its window", inclusion_id)
    loops = []
    for c in find_contours(values, 0.0):
        if not np.allclose(c[0], c[-1]):
            raise MeshingError(
                "contours", "the zero contour reaches the edge of the inclusion window (bounds too small?)",
                inclusion_id,
            )
        c = c[:-1]
        keep = np.ones(len(c), dtype=bool)
        keep[1:] = np.any(np.abs(np.diff(c, axis=0)) > 1e-12, axis=1)
        c = c[keep]
        if len(c) >= 3:
            loops.append(np.asarray(origin, dtype=float) + c * step)
    if not loops:
        raise MeshingError("contours", "no closed zero contour found", inclusion_id)
    return loops


def capped_axes_2d(lower, upper, box, margin: float) -> tuple[int, ...]:
    """Axes along which an inclusion's window with `margin` would reach its next periodic copy (it
    percolates there, or nearly spans the box): its contours are closed off beyond the box there."""
    gap = np.asarray(box, float) - (np.asarray(upper, float) - np.asarray(lower, float))
    return tuple(int(a) for a in np.flatnonzero(gap <= 2 * margin))


def capped_values(values: np.ndarray, origin, step: float, box, capped, cap: float) -> np.ndarray:
    """Window samples closed off beyond x_a = -cap and L + cap along the capped axes: the level set
    of a percolating inclusion (a band, a channel) becomes closed loops whose parts in the box are
    the band's arcs, cut at x_a = 0 and L by :func:`cut_loop` (``keep_axes``)."""
    out = np.asarray(values, dtype=float).copy()
    L = np.asarray(box, float)
    for a in capped:
        x = np.asarray(origin, float)[a] + step * np.arange(out.shape[a])
        beyond = np.maximum(-cap - x, x - L[a] - cap)
        shape = [1, 1]
        shape[a] = -1
        out = np.maximum(out, beyond.reshape(shape))
    return out


def join_capped_crossings(arcs: list[Arc], crossings: list[Crossing], axes, box, inclusion_id: int):
    """The in-box arcs of capped loops end on the lines x_a = 0 and x_a = L at two crossings of one
    periodic point; merge each such pair into one crossing (and drop the crossings no kept arc uses).

    Returns:
        (arcs, crossings) re-indexed. Raises MeshingError when a crossing on x_a = 0 has no partner
        on x_a = L (a field that is not periodic there).
    """
    used = sorted({e[0] for arc in arcs if not arc.closed for e in (arc.start, arc.end)})
    L = np.asarray(box, float)
    target = {}
    for a in axes:
        ends = {0: [], 1: []}
        for arc in arcs:
            for c, side in (() if arc.closed else (arc.start, arc.end)):
                if crossings[c].axis == a:
                    ends[side].append(c)
        on0, on1 = sorted(set(ends[0])), sorted(set(ends[1]))
        t0 = np.array([crossings[c].t for c in on0])
        t1 = np.array([crossings[c].t for c in on1])
        if len(t0) != len(t1) or (len(t0) and np.abs(np.sort(t0) - np.sort(t1)).max() > 1e-6 * L[1 - a]):
            raise MeshingError("contours", f"the inclusion percolates along axis {a} but its crossings of x_{a} = 0 "
                               f"({np.round(np.sort(t0), 6).tolist()}) and x_{a} = L ({np.round(np.sort(t1), 6).tolist()}) "
                               "are not translates (is the field periodic?)", inclusion_id)
        for i, j in zip(np.array(on0)[np.argsort(t0)], np.array(on1)[np.argsort(t1)]):
            target[int(j)] = int(i)
    keep = [c for c in used if c not in target]
    index = {c: k for k, c in enumerate(keep)}
    index.update({j: index[i] for j, i in target.items()})
    remap = lambda e: (index[e[0]], e[1])  # noqa: E731
    arcs = [arc if arc.closed else replace(arc, start=remap(arc.start), end=remap(arc.end)) for arc in arcs]
    return arcs, [crossings[c] for c in keep]


# ----------------------------------------------------------------------------- cutting
def cut_loop(
    loop: np.ndarray, box, refine_fn: Callable, inclusion_id: int, keep_axes=()
) -> tuple[list[Arc], list[Crossing]]:
    """Cut a closed unwrapped loop by the lattice lines and translate the pieces into the box.
    Along `keep_axes` only the pieces in the cell [0, L] are kept (a capped loop's pieces beyond
    the box are copies of pieces inside it).

    Args:
        loop: (n, 2) closed polyline (unwrapped, first point not repeated), ideally on phi = 0.
        box: (2,) lengths.
        refine_fn: ``(points (k, 2), axis (k,)) -> (k, 2)``: moves each approximate crossing along
            its line (coordinate ``axis`` untouched) onto phi = 0.
        inclusion_id: owner.
    Returns:
        (arcs, crossings): arcs' start/end refer to indices into ``crossings``.
    """
    L = np.asarray(box, dtype=float)
    V = np.asarray(loop, dtype=float)
    W = np.roll(V, -1, axis=0)
    n = len(V)
    cv = np.floor(V / L).astype(np.int64)
    cw = np.roll(cv, -1, axis=0)
    js, ts, axes, ks, dirs = [], [], [], [], []
    for a in (0, 1):
        j = np.nonzero(cv[:, a] != cw[:, a])[0]
        if np.any(np.abs(cv[j, a] - cw[j, a]) > 1):
            raise MeshingError("contours", "a contour segment is longer than the box", inclusion_id)
        k = np.maximum(cv[j, a], cw[j, a])
        js.append(j)
        ts.append((k * L[a] - V[j, a]) / (W[j, a] - V[j, a]))
        axes.append(np.full(j.size, a))
        ks.append(k)
        dirs.append(cw[j, a] - cv[j, a])
    j, t, ax, k, dr = (np.concatenate(x) for x in (js, ts, axes, ks, dirs))
    keep = list(keep_axes)
    if j.size == 0:
        return ([Arc(inclusion_id, V - cv[0] * L, closed=True)] if not cv[0, keep].any() else []), []
    order = np.lexsort((t, j))
    j, t, ax, k, dr = j[order], t[order], ax[order], k[order], dr[order]
    approx = V[j] + t[:, None] * (W[j] - V[j])
    rows = np.arange(j.size)
    approx[rows, ax] = k * L[ax]
    # along keep_axes a crossing beyond [0, L] only ends dropped pieces (it may lie on a cap, off phi = 0)
    used = ((approx[:, keep] >= -1e-9 * L[keep]) & (approx[:, keep] <= L[keep] * (1 + 1e-9))).all(axis=1)
    pts = approx.copy()
    if used.any():
        pts[used] = np.asarray(refine_fn(approx[used], ax[used]), dtype=float)
    pts[rows, ax] = k * L[ax]  # exactly on the line
    other = 1 - ax
    tcan = wrap(pts[rows, other], L[other])
    # a crossing at (or within rounding of) a box corner has no well defined edge
    gap = np.minimum(tcan, L[other] - tcan)
    if np.any(used & (gap < 1e-9 * L[other])):
        raise MeshingError("contours", "the interface passes through a box corner; shift the geometry slightly",
                           inclusion_id)
    crossings = [Crossing(int(a), float(tc), inclusion_id) for a, tc in zip(ax, tcan)]

    arcs = []
    cur = cv[j[0]].copy()
    m = j.size
    for e in range(m):
        cur[ax[e]] += dr[e]
        nxt = (e + 1) % m
        count = (j[nxt] - j[e]) % n
        vid = (j[e] + 1 + np.arange(count)) % n
        if cur[keep].any():
            continue
        inner = V[vid] - cur * L
        start, sside = _local_crossing(pts[e], ax[e], k[e], tcan[e], cur, L, inclusion_id)
        end, eside = _local_crossing(pts[nxt], ax[nxt], k[nxt], tcan[nxt], cur, L, inclusion_id)
        arcs.append(Arc(inclusion_id, np.vstack([start, inner, end]), False, (e, sside), (nxt, eside)))
    return arcs, crossings


def _local_crossing(p, a, k, tcan, cell, L, inclusion_id):
    """Box coordinates of a crossing seen from the arc in lattice cell ``cell``, and its side."""
    a = int(a)
    b = 1 - a
    side = int(k - cell[a])
    if side not in (0, 1) or abs(p[b] - cell[b] * L[b] - tcan) > 1e-6 * L[b]:
        raise MeshingError("contours", "inconsistent crossing bookkeeping (interface near a box corner?)",
                           inclusion_id)
    q = np.empty(2)
    q[a] = side * L[a]
    q[b] = tcan
    return q, side


# ----------------------------------------------------------------------------- non-periodic box
def box_window_axes(lower, upper, step: float, margin: float, box) -> list[np.ndarray]:
    """Sample coordinates per axis of a window around an inclusion, clipped to the closed box.

    Samples at lower - margin + i * step that lie inside the box, none closer than step / 4 to a
    box line (no sliver cells); where the window reaches a box line, the line itself (exactly 0
    or L) is a sample, so contours meet it at their true crossings.

    Args:
        lower, upper: (2,) bounds of the inclusion (may stick out of the box). step: spacing.
        margin: added on every side. box: (2,) lengths.
    Returns:
        [xs, ys]: increasing coordinates, the window samples are their outer product.
    """
    axes = []
    for lo, hi, L in zip(np.asarray(lower, float) - margin, np.asarray(upper, float) + margin, np.asarray(box, float)):
        x = lo + step * np.arange(int(np.ceil((hi - lo) / step)) + 1)
        inner = x[(x > 0.25 * step) & (x < L - 0.25 * step)]
        axes.append(np.concatenate([[0.0] if x[0] <= 0.25 * step else [], inner,
                                    [L] if x[-1] >= L - 0.25 * step else []]))
    return axes


def extract_box_loops(values: np.ndarray, axes, box, inclusion_id: int) -> list[np.ndarray]:
    """Closed zero contours of a window sample of a non-periodic box, in box coordinates.

    Where the window lies on a box line, one more row of positive samples at the same coordinate
    is added: a contour cut by that line then closes along it (its vertices there exactly on the
    line, see :func:`clip_loop`) instead of running out of the window.

    Args:
        values: (nx, ny) samples of the inclusion's level set at the outer product of ``axes``.
        axes: [xs, ys] from :func:`box_window_axes`. box: (2,) lengths. inclusion_id: for errors.
    Returns:
        list of (k, 2) loops (first point not repeated). Raises MeshingError when a contour
        reaches a window edge inside the box (bounds too small).
    """
    values = np.asarray(values, dtype=float)
    if not np.any(values < 0):
        raise MeshingError("contours", "the level set has no negative sample in its window", inclusion_id)
    L = np.asarray(box, dtype=float)
    positive = float(np.abs(values).max()) + 1.0
    coords = []
    for k, x in enumerate(axes):
        before, after = int(x[0] == 0.0), int(x[-1] == L[k])
        widths = [(0, 0), (0, 0)]
        widths[k] = (before, after)
        values = np.pad(values, widths, constant_values=positive)
        coords.append(np.concatenate([x[:1]] * before + [x] + [x[-1:]] * after))
    loops = []
    scale = 1e-12 * float(L.max())
    for c in find_contours(values, 0.0):
        if not np.allclose(c[0], c[-1]):
            raise MeshingError(
                "contours", "the zero contour reaches the edge of the inclusion window (bounds too small?)",
                inclusion_id,
            )
        p = np.stack([np.interp(c[:-1, k], np.arange(len(x)), x) for k, x in enumerate(coords)], axis=1)
        keep = np.ones(len(p), dtype=bool)
        keep[1:] = np.any(np.abs(np.diff(p, axis=0)) > scale, axis=1)
        p = p[keep]
        if len(p) >= 3:
            loops.append(p)
    if not loops:
        raise MeshingError("contours", "no closed zero contour found", inclusion_id)
    return loops


def clip_loop(loop: np.ndarray, box, refine_fn: Callable, inclusion_id: int) -> tuple[list[Arc], list[Crossing]]:
    """The pieces of a closed loop inside a non-periodic box; what runs along the box lines goes.

    Vertices exactly on a box line (as :func:`extract_box_loops` leaves them where the box cuts
    the inclusion) are outside; every run of inside vertices is an arc whose two end vertices,
    on a box line, are crossings. Nothing is translated: a crossing is on one side only.

    Args:
        loop: (n, 2) closed polyline in the closed box (first point not repeated).
        box: (2,) lengths.
        refine_fn: ``(points (k, 2), axis (k,)) -> (k, 2)``: moves each approximate crossing along
            its line (coordinate ``axis`` untouched) onto phi = 0.
        inclusion_id: owner.
    Returns:
        (arcs, crossings) as :func:`cut_loop`: an arc's start/end is (crossing index, side), side 0
        on x_axis = 0 and 1 on x_axis = L.
    """
    L = np.asarray(box, dtype=float)
    V = np.asarray(loop, dtype=float)
    on_line = (V == 0.0) | (V == L)
    on = on_line.any(axis=1)
    if not on.any():
        return [Arc(inclusion_id, V.copy(), closed=True)], []
    n = len(V)
    leave = np.nonzero(on & ~np.roll(on, -1))[0]  # last boundary vertex before a run of inside ones
    if leave.size == 0:
        return [], []  # the loop runs along the box lines only: nothing of it is inside
    runs = []
    for i in leave:
        j = i + 1
        while not on[j % n]:
            j += 1
        runs.append((i, j % n))
    ends = np.array([e for run in runs for e in run])
    if np.any(on_line[ends].all(axis=1)):
        raise MeshingError("contours", "the interface passes through a box corner; shift the geometry slightly",
                           inclusion_id)
    ax = np.argmax(on_line[ends], axis=1)
    rows = np.arange(ends.size)
    side = (V[ends, ax] == L[ax]).astype(np.int64)
    pts = np.asarray(refine_fn(V[ends], ax), dtype=float).copy()
    pts[rows, ax] = side * L[ax]  # exactly on the line
    other = 1 - ax
    t = pts[rows, other]
    if np.any(np.minimum(t, L[other] - t) < 1e-9 * L[other]):
        raise MeshingError("contours", "an interface crossing is at (or beyond) a box corner; shift the geometry "
                           "slightly", inclusion_id)
    crossings = [Crossing(int(a), float(tc), inclusion_id) for a, tc in zip(ax, t)]
    arcs = []
    for k, (i, j) in enumerate(runs):
        inner = V[(i + 1 + np.arange((j - i - 1) % n)) % n]
        arcs.append(Arc(inclusion_id, np.vstack([pts[2 * k], inner, pts[2 * k + 1]]), False,
                        (2 * k, int(side[2 * k])), (2 * k + 1, int(side[2 * k + 1]))))
    return arcs, crossings


# ----------------------------------------------------------------------------- resampling
def resample_polyline(points: np.ndarray, closed: bool, h_fn: Callable, min_segments: int = 1) -> np.ndarray:
    """Nodes equidistributed in h-weighted arclength (integral of ds / h) along a polyline.

    Args:
        points: (k, 2) polyline (closed: first point not repeated).
        closed: loop or open arc (open arcs keep both endpoints exactly).
        h_fn: NumPy size function (m, 2) -> (m,).
        min_segments: lower bound on the number of segments.
    Returns:
        (n, 2) nodes; open arcs: n = segments + 1, closed loops: n = segments.
    """
    P = np.vstack([points, points[:1]]) if closed else np.asarray(points, dtype=float)
    seg = np.diff(P, axis=0)
    ds = np.linalg.norm(seg, axis=1)
    w = ds / np.asarray(h_fn(0.5 * (P[:-1] + P[1:])), dtype=float)
    S = np.concatenate([[0.0], np.cumsum(w)])
    nseg = max(int(min_segments), int(np.round(S[-1])))
    targets = np.linspace(0.0, S[-1], nseg + 1)
    if closed:
        targets = targets[:-1]
    idx = np.clip(np.searchsorted(S, targets, side="right") - 1, 0, len(ds) - 1)
    frac = np.where(w[idx] > 0, (targets - S[idx]) / np.where(w[idx] > 0, w[idx], 1.0), 0.0)
    nodes = P[idx] + np.clip(frac, 0.0, 1.0)[:, None] * seg[idx]
    if not closed:
        nodes[0], nodes[-1] = P[0], P[-1]
    return nodes


def edge_parameters(breaks: np.ndarray, line_point: Callable, h_fn: Callable) -> np.ndarray:
    """Node parameters along a straight box edge, ~h apart between fixed break points.

    Args:
        breaks: sorted (b,) parameters that must be nodes (corners, crossings).
        line_point: t (m,) -> points (m, 2) on the edge.
        h_fn: NumPy size function (m, 2) -> (m,).
    Returns:
        sorted parameters including every break.
    """
    out = [np.asarray(breaks[:1], dtype=float)]
    for t0, t1 in zip(breaks[:-1], breaks[1:]):
        length = t1 - t0
        h_ends = np.asarray(h_fn(line_point(np.array([t0, t1]))), dtype=float)
        fine = np.linspace(t0, t1, max(8, int(np.ceil(8 * length / h_ends.min()))) + 1)
        w = np.diff(fine) / np.asarray(h_fn(line_point(0.5 * (fine[:-1] + fine[1:]))), dtype=float)
        S = np.concatenate([[0.0], np.cumsum(w)])
        nseg = max(1, int(np.round(S[-1])))
        inner = np.interp(np.linspace(0.0, S[-1], nseg + 1)[1:-1], S, fine)
        out.extend([inner, np.array([t1], dtype=float)])
    return np.concatenate(out)


# ----------------------------------------------------------------------------- splitting
def split_segments(pslg: PSLG, which: np.ndarray, project_fn: Callable) -> PSLG:
    """Split the flagged segments at their midpoints.

    Interface midpoints go through ``project_fn(points (k, 2), inclusion_ids (k,)) -> (k, 2)``
    (back onto the level set). A box segment is split on its master edge (x_axis = 0) and the
    same point, translated, splits its partner, and the new pair joins ``periodic_pairs``; a
    segment without partner (every box segment of a non-periodic box) is split alone.

    Args:
        pslg: the graph. which: (s,) bool or index array of segments to split.
        project_fn: the level-set projection callback.
    Returns:
        A new PSLG (old node ids unchanged, new nodes appended).
    """
    which = np.unique(np.nonzero(which)[0] if np.asarray(which).dtype == bool else np.asarray(which, np.int64))
    box = np.asarray(pslg.box, dtype=float)
    seg = pslg.segments.copy()
    inc = pslg.segment_inclusion.copy()
    partner = pslg.segment_partner.copy()
    new_pts, kind, axis, ninc = [], [], [], []
    new_seg, new_inc, new_partner = [], [], []
    pairs = {a: [p for p in np.asarray(pslg.periodic_pairs.get(a, np.zeros((0, 2), np.int64)))] for a in (0, 1)}
    n0 = pslg.n_points

    def add_node(p, k, ax, i):
        new_pts.append(p)
        kind.append(k)
        axis.append(ax)
        ninc.append(i)
        return n0 + len(new_pts) - 1

    # interface segments: batch projection
    iface = which[inc[which] != BOX_SEGMENT]
    if iface.size:
        a, b = seg[iface, 0], seg[iface, 1]
        mid = 0.5 * (pslg.points[a] + pslg.points[b])
        mid = np.asarray(project_fn(mid, inc[iface]), dtype=float)
        for s, p in zip(iface, mid):
            m = add_node(p, INTERFACE, -1, inc[s])
            new_seg.append((m, seg[s, 1]))
            new_inc.append(inc[s])
            new_partner.append(-1)
            seg[s, 1] = m
    # box segments: split each master once (normal coordinate exactly 0), mirror onto its partner
    s0 = len(seg)
    done = set()
    for s in which[inc[which] == BOX_SEGMENT]:
        t = partner[s]
        a, b = pslg.segments[s]  # original ids: seg[] may already hold a split half
        ax = int(np.argmin(np.abs(pslg.points[a] - pslg.points[b])))  # axis-aligned: normal coords equal
        master, slave = (s, t) if pslg.points[a][ax] == 0.0 or t < 0 else (t, s)
        if master in done:
            continue
        done.add(master)
        a, b = seg[master]
        pm = 0.5 * (pslg.points[a] + pslg.points[b])
        pm[ax] = pslg.points[a][ax]
        m = add_node(pm, BOX_EDGE, ax, 0)
        i_m = s0 + len(new_seg)
        new_seg.append((m, b))
        new_inc.append(BOX_SEGMENT)
        seg[master, 1] = m
        if slave < 0:
            new_partner.append(-1)
            continue
        ps = pm.copy()
        ps[ax] = box[ax]
        ms = add_node(ps, BOX_EDGE, ax, 0)
        i_s = s0 + len(new_seg)
        new_seg.append((ms, seg[slave, 1]))
        new_inc.append(BOX_SEGMENT)
        seg[slave, 1] = ms
        new_partner.extend([i_s, i_m])
        pairs[ax].append(np.array([m, ms]))
    new_seg = np.asarray(new_seg, dtype=np.int64).reshape(-1, 2)
    new_partner = np.asarray(new_partner, dtype=np.int64)
    pts = np.vstack([pslg.points, np.asarray(new_pts, dtype=float).reshape(-1, 2)])
    return replace(
        pslg,
        points=pts,
        segments=np.vstack([seg, new_seg]),
        segment_inclusion=np.concatenate([inc, np.asarray(new_inc, np.int64)]),
        segment_partner=np.concatenate([partner, new_partner]),
        node_kind=np.concatenate([pslg.node_kind, np.asarray(kind, pslg.node_kind.dtype)]),
        node_axis=np.concatenate([pslg.node_axis, np.asarray(axis, pslg.node_axis.dtype)]),
        node_inclusion=np.concatenate([pslg.node_inclusion, np.asarray(ninc, pslg.node_inclusion.dtype)]),
        periodic_pairs={a: np.asarray(pairs[a], np.int64).reshape(-1, 2) for a in (0, 1)} if pslg.periodic else {},
    )


# ----------------------------------------------------------------------------- assembly
def _line_parameters(crossings: list[Crossing], cid: np.ndarray, a: int, level: float, L, h_fn: Callable):
    """Node parameters along the box line x_a = level: corners, the crossings cid, ~h between.

    Returns:
        (cid sorted along the line, parameters (p,), index of each crossing in the parameters).
    """
    b = 1 - a
    tc = np.array([crossings[i].t for i in cid], dtype=float)
    order = np.argsort(tc)
    cid, tc = cid[order], tc[order]
    if tc.size > 1 and np.any(np.diff(tc) <= 1e-12 * L[b]):
        raise MeshingError("box edges", f"two interfaces cross the box line x_{a} = {level:g} at the same point")

    def line_point(t):
        p = np.zeros((len(t), 2))
        p[:, a] = level
        p[:, b] = t
        return p

    params = edge_parameters(np.concatenate([[0.0], tc, [L[b]]]), line_point, h_fn)
    where = np.searchsorted(params, tc)
    assert np.all(params[where] == tc)
    return cid, params, where


def assemble_pslg(arcs: list[Arc], crossings: list[Crossing], box, h_fn: Callable) -> PSLG:
    """Constrained graph of the box: corners, box-edge nodes (master edges copied), interface arcs.

    Args:
        arcs: resampled arcs/loops (open arcs end exactly at their crossings).
        crossings: every crossing the arcs refer to.
        box: (Lx, Ly). h_fn: NumPy size function for the box-edge spacing.
    Returns:
        :class:`PSLG` with periodic pairs for both axes (corners included).
    """
    L = np.asarray(box, dtype=float)
    g = _PslgLists(L)
    add, seg, seg_inc, seg_partner = g.add, g.seg, g.seg_inc, g.seg_partner
    BL, BR, TL, TR = 0, 1, 2, 3
    pairs = {0: [(BL, BR), (TL, TR)], 1: [(BL, TL), (BR, TR)]}
    corner_chain = {0: ((BL, TL), (BR, TR)), 1: ((BL, BR), (TL, TR))}
    node_of = {}  # (crossing index, side) -> node id

    for a in (0, 1):
        b = 1 - a
        cid = np.array([i for i, c in enumerate(crossings) if c.axis == a], dtype=np.int64)
        cid, params, where = _line_parameters(crossings, cid, a, 0.0, L, h_fn)
        is_crossing = np.zeros(len(params), dtype=bool)
        is_crossing[where] = True
        owner = np.zeros(len(params), dtype=np.int64)
        owner[where] = [crossings[i].inclusion_id for i in cid]
        (lo_m, hi_m), (lo_s, hi_s) = corner_chain[a]
        chain_m, chain_s = [lo_m], [lo_s]
        for i in range(1, len(params) - 1):
            pm = np.zeros(2)
            pm[b] = params[i]
            ps = pm.copy()
            ps[a] = L[a]
            k = FIXED if is_crossing[i] else BOX_EDGE
            chain_m.append(add(pm, k, a, owner[i]))
            chain_s.append(add(ps, k, a, owner[i]))
            pairs[a].append((chain_m[-1], chain_s[-1]))
        chain_m.append(hi_m)
        chain_s.append(hi_s)
        for c, w in zip(cid, where):
            node_of[(int(c), 0)] = chain_m[w]
            node_of[(int(c), 1)] = chain_s[w]
        s0 = len(seg)
        nb = len(chain_m) - 1
        for i in range(nb):
            seg.append((chain_m[i], chain_m[i + 1]))
            seg.append((chain_s[i], chain_s[i + 1]))
            seg_inc.extend([BOX_SEGMENT, BOX_SEGMENT])
            seg_partner.extend([s0 + 2 * i + 1, s0 + 2 * i])

    _append_arcs(arcs, node_of, add, seg, seg_inc, seg_partner)
    return g.pslg(pairs, periodic=True)


class _PslgLists:
    """The lists a PSLG assembly collects, starting from the four box corners (BL, BR, TL, TR)."""

    def __init__(self, L: np.ndarray):
        self.L = L
        self.pts = [np.array([0.0, 0.0]), np.array([L[0], 0.0]), np.array([0.0, L[1]]), np.array([L[0], L[1]])]
        self.kind, self.axis, self.ninc = [FIXED] * 4, [-1] * 4, [0] * 4
        self.seg, self.seg_inc, self.seg_partner = [], [], []

    def add(self, p, k, a, i) -> int:
        """A node at p of kind k on box axis a (-1: none) on inclusion i; returns its id."""
        self.pts.append(np.asarray(p, dtype=float))
        self.kind.append(k)
        self.axis.append(a)
        self.ninc.append(i)
        return len(self.pts) - 1

    def pslg(self, pairs: dict, periodic: bool) -> PSLG:
        return PSLG(
            points=np.asarray(self.pts, dtype=float),
            segments=np.asarray(self.seg, dtype=np.int64).reshape(-1, 2),
            segment_inclusion=np.asarray(self.seg_inc, dtype=np.int64),
            segment_partner=np.asarray(self.seg_partner, dtype=np.int64),
            node_kind=np.asarray(self.kind, dtype=np.int8),
            node_axis=np.asarray(self.axis, dtype=np.int8),
            node_inclusion=np.asarray(self.ninc, dtype=np.int64),
            periodic_pairs={a: np.asarray(p, dtype=np.int64) for a, p in pairs.items()},
            box=(float(self.L[0]), float(self.L[1])),
            periodic=periodic,
        )


def _append_arcs(arcs: list[Arc], node_of: dict, add: Callable, seg: list, seg_inc: list, seg_partner: list):
    """Interface nodes and segments of the arcs; open arcs end on their crossing nodes node_of[(c, side)]."""
    for arc in arcs:
        nodes = np.asarray(arc.points, dtype=float)
        if arc.closed:
            ids = [add(p, INTERFACE, -1, arc.inclusion_id) for p in nodes]
            ring = ids + ids[:1]
        else:
            ids = [add(p, INTERFACE, -1, arc.inclusion_id) for p in nodes[1:-1]]
            ring = [node_of[arc.start]] + ids + [node_of[arc.end]]
        for u, v in zip(ring[:-1], ring[1:]):
            seg.append((u, v))
            seg_inc.append(arc.inclusion_id)
            seg_partner.append(-1)


# the four sides of a non-periodic box: (normal axis, side) -> (corner at t = 0, corner at t = L)
_SIDES = {(0, 0): (0, 2), (0, 1): (1, 3), (1, 0): (0, 1), (1, 1): (2, 3)}  # corners BL, BR, TL, TR


def assemble_box_pslg(arcs: list[Arc], crossings: list[Crossing], box, h_fn: Callable) -> PSLG:
    """Constrained graph of a non-periodic box: corners, each side meshed on its own, interface arcs.

    Args:
        arcs: resampled arcs/loops from :func:`clip_loop` (open arcs end exactly at their crossings).
        crossings: every crossing the arcs refer to; each lies on the side its arc end names.
        box: (Lx, Ly). h_fn: NumPy size function for the box-edge spacing.
    Returns:
        :class:`PSLG` with ``periodic=False``, no periodic pairs and no segment partners.
    """
    L = np.asarray(box, dtype=float)
    g = _PslgLists(L)
    add, seg, seg_inc, seg_partner = g.add, g.seg, g.seg_inc, g.seg_partner
    side_of = {end[0]: end[1] for arc in arcs if not arc.closed for end in (arc.start, arc.end)}
    node_of = {}  # (crossing index, side) -> node id

    for (a, side), (lo, hi) in _SIDES.items():
        b = 1 - a
        cid = np.array([i for i, c in enumerate(crossings) if c.axis == a and side_of.get(i) == side],
                       dtype=np.int64)
        cid, params, where = _line_parameters(crossings, cid, a, side * L[a], L, h_fn)
        is_crossing = np.zeros(len(params), dtype=bool)
        is_crossing[where] = True
        owner = np.zeros(len(params), dtype=np.int64)
        owner[where] = [crossings[i].inclusion_id for i in cid]
        chain = [lo]
        for i in range(1, len(params) - 1):
            p = np.zeros(2)
            p[a], p[b] = side * L[a], params[i]
            chain.append(add(p, FIXED if is_crossing[i] else BOX_EDGE, a, owner[i]))
        chain.append(hi)
        for c, w in zip(cid, where):
            node_of[(int(c), side)] = chain[w]
        seg.extend(zip(chain[:-1], chain[1:]))
        seg_inc.extend([BOX_SEGMENT] * (len(chain) - 1))
        seg_partner.extend([-1] * (len(chain) - 1))
    _append_arcs(arcs, node_of, add, seg, seg_inc, seg_partner)
    return g.pslg({}, periodic=False)


def rebuild_box_segments(pslg: PSLG) -> PSLG:
    """Box segments re-derived from the node order along each edge (box nodes slide in the truss
    relaxation and may pass one another or a crossing); master and slave edges stay partners.
    Non-periodic: each side on its own, from its nodes (exactly on the side) between its corners."""
    L = np.asarray(pslg.box, dtype=float)
    pts = pslg.points
    seg, inc, partner = [], [], []
    keep = pslg.segment_inclusion != BOX_SEGMENT
    if not pslg.periodic:
        corner = (pslg.node_kind == FIXED) & (pslg.node_axis == -1)
        for a, side in _SIDES:
            on_side = ((pslg.node_axis == a) | corner) & (pts[:, a] == side * L[a])
            chain = np.nonzero(on_side)[0]
            chain = chain[np.argsort(pts[chain, 1 - a], kind="stable")]
            seg.extend(zip(chain[:-1], chain[1:]))
        return replace(
            pslg,
            segments=np.vstack([pslg.segments[keep], np.asarray(seg, np.int64).reshape(-1, 2)]),
            segment_inclusion=np.concatenate([pslg.segment_inclusion[keep], np.full(len(seg), BOX_SEGMENT, np.int64)]),
            segment_partner=np.full(int(keep.sum()) + len(seg), -1, np.int64),
        )
    for a in (0, 1):
        b = 1 - a
        pairs = np.asarray(pslg.periodic_pairs[a])
        order = np.argsort(pts[pairs[:, 0], b], kind="stable")
        master, slave = pairs[order, 0], pairs[order, 1]
        s0 = int(keep.sum()) + len(seg)
        for i in range(len(master) - 1):
            seg.extend([(master[i], master[i + 1]), (slave[i], slave[i + 1])])
            inc.extend([BOX_SEGMENT, BOX_SEGMENT])
            partner.extend([s0 + 2 * i + 1, s0 + 2 * i])
    return PSLG(
        points=pts,
        segments=np.vstack([pslg.segments[keep], np.asarray(seg, np.int64).reshape(-1, 2)]),
        segment_inclusion=np.concatenate([pslg.segment_inclusion[keep], np.asarray(inc, np.int64)]),
        segment_partner=np.concatenate([np.full(int(keep.sum()), -1, np.int64), np.asarray(partner, np.int64)]),
        node_kind=pslg.node_kind,
        node_axis=pslg.node_axis,
        node_inclusion=pslg.node_inclusion,
        periodic_pairs=pslg.periodic_pairs,
        box=pslg.box,
    )
