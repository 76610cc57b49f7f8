"""Periodic connected components and per-inclusion windows of a grid (NumPy/SciPy only, no jax).

A *window* is a box of grid nodes around one inclusion, in unwrapped index coordinates (node u of
the window is grid node u mod n when periodic). It holds the inclusion's own level set: accurate
inside its *core* (the inclusion's index arc plus a few steps), padded by a few more steps so that
the periodic B-spline prefilter of the window does not feel the window's own wrap-around. An axis
whose window would reach the grid size becomes a *full* axis: the whole periodic axis, centred on
the inclusion. The validation of raw inputs (fields, labels, boxes, points) lives here too.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Window:
    """Node box of one inclusion: window node u (unwrapped) is grid node u mod n.

    origin: (d,) int, unwrapped index of window node 0; shape: nodes per axis; core_lo/core_hi: (d,)
    local indices of the first/last core node; full: (d,) bool, the axis spans the periodic axis.
    """

    origin: np.ndarray
    shape: tuple[int, ...]
    core_lo: np.ndarray
    core_hi: np.ndarray
    full: np.ndarray


def label_components(mask: np.ndarray, periodic: bool) -> tuple[np.ndarray, int]:
    """Face-connected components of a boolean grid, merged across opposite faces when periodic.

    A component crossing a face, edge or corner of the periodic cell is counted once.

    Args:
        mask: (*shape) bool.
        periodic: merge labels that touch through opposite faces.

    Returns:
        labels (*shape) int32 (0 = background, 1..n in raster order of first node) and n.
    """
    labels, n = ndimage.label(mask)
    labels = labels.astype(np.int32)
    if n == 0 or not periodic:
        return labels, int(n)
    pairs = []
    for axis in range(mask.ndim):
        a = np.take(labels, 0, axis=axis).ravel()
        b = np.take(labels, -1, axis=axis).ravel()
        both = (a > 0) & (b > 0)
        pairs.append(np.stack([a[both], b[both]]))
    pairs = np.concatenate(pairs, axis=1) - 1
    graph = coo_matrix((np.ones(pairs.shape[1]), (pairs[0], pairs[1])), shape=(n, n))
    n_merged, comp = connected_components(graph, directed=False)
    first = np.full(n_merged, n)
    np.minimum.at(first, comp, np.arange(n))  # keep raster order of first appearance
    rank = np.argsort(np.argsort(first))
    lut = np.concatenate([[0], rank[comp] + 1]).astype(np.int32)
    return lut[labels], int(n_merged)


def label_components_to_far_planes(values: np.ndarray) -> tuple[np.ndarray, int]:
    """label_components of {values < 0} on a non-periodic grid, where parts that join in the last
    cell, at the far box planes x = L (a step beyond the last sample, the field continued linearly
    as `extrapolate_beyond_domain` does), are one component: the surface there is the field's one
    zero set, not two level sets separated within less than a cell. Same raster-order ids."""
    d = values.ndim
    grid = tuple(slice(0, n) for n in values.shape)
    extended = extrapolate_beyond_domain(np.pad(values, [(0, 1)] * d), np.zeros(d, int), values.shape)
    labels, _ = label_components(extended < 0, periodic=False)
    labels = labels[grid]
    ids, first = np.unique(labels.ravel(), return_index=True)
    ids, first = ids[ids > 0], first[ids > 0]  # parts only beyond the last sample are not inclusions
    lut = np.zeros(int(labels.max()) + 1, np.int32)
    lut[ids[np.argsort(first)]] = np.arange(1, len(ids) + 1)
    return lut[labels], len(ids)


def _arc(occupied: np.ndarray, periodic: bool) -> tuple[int, int]:
    """(start, length) of the smallest (circular if periodic) index interval covering occupied."""
    n = occupied.size
    pos = np.flatnonzero(occupied)
    if not periodic:
        return int(pos[0]), int(pos[-1] - pos[0] + 1)
    if pos.size == n:
        return 0, n
    gaps = np.diff(np.concatenate([pos, [pos[0] + n]]))  # gap after each occupied index
    g = int(np.argmax(gaps))
    start = int(pos[(g + 1) % pos.size])
    length = n - int(gaps[g]) + 1
    if start + (length - 1) / 2 >= n:  # arc centre in [0, n)
        start -= n
    return start, length


def component_arcs(labels: np.ndarray, n: int, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per component and axis the covered index arc (unwrapped start, arc centre in [0, n_axis)).

    Returns:
        starts (n, d) int and lengths (n, d) int; length == n_axis means the component spans
        (percolates through) that periodic axis.
    """
    shape = labels.shape
    flat = labels.ravel()
    where = np.flatnonzero(flat)
    ids = flat[where] - 1
    coords = np.unravel_index(where, shape)
    starts = np.zeros((n, len(shape)), np.int64)
    lengths = np.zeros((n, len(shape)), np.int64)
    for k, size in enumerate(shape):
        occupied = np.zeros((n, size), bool)
        occupied[ids, coords[k]] = True
        for c in range(n):
            starts[c, k], lengths[c, k] = _arc(occupied[c], periodic)
    return starts, lengths


def _bucket(w: int) -> int:
    """Round a window length up to 2^k or 3*2^(k-1) (few distinct shapes -> few compilations)."""
    b = 8
    while b < w:
        b = b * 3 // 2 if (b & (b - 1)) == 0 else b * 4 // 3
    return b


def make_window(start, length, grid_shape, periodic: bool, core_pad: int, spline_pad: int) -> Window:
    """Window around the index arc [start, start + length) of one inclusion (per axis arrays)."""
    origin, shape, lo, hi, full = [], [], [], [], []
    for s, m, n in zip(start, length, grid_shape):
        need = int(m) + 2 * (core_pad + spline_pad)
        w = _bucket(need)
        if periodic and w >= n:
            origin.append(int(s) - (n - int(m)) // 2)
            shape.append(n)
            lo.append(0)
            hi.append(n - 1)
            full.append(True)
            continue
        extra = w - need
        origin.append(int(s) - core_pad - spline_pad - extra // 2)
        shape.append(w)
        lo.append(spline_pad)
        hi.append(w - 1 - spline_pad)
        full.append(False)
    return Window(np.array(origin), tuple(shape), np.array(lo), np.array(hi), np.array(full))


def frame_indices(origin, shape, grid_shape, periodic: bool) -> list[np.ndarray]:
    """Grid node indices of a box of nodes: wrapped when periodic, else clamped (edge replicate)."""
    idx = []
    for o, w, n in zip(origin, shape, grid_shape):
        u = int(o) + np.arange(w)
        idx.append(u % n if periodic else np.clip(u, 0, n - 1))
    return idx


def extrapolate_beyond_domain(field: np.ndarray, origin, grid_shape) -> np.ndarray:
    """A window field whose nodes beyond a non-periodic grid are linear continuations from the
    nearest grid node: ghost = border + sum over the axes it lies beyond of k (border - next inner).

    Windows take replicated border nodes there (`frame_indices`); a B-spline through them bends
    the level set to meet the box plane at a right angle within the last cell (a crease: curvature
    radii below a grid step, and surfaces that fold where a trace passes near a box edge). A linear
    field is reproduced exactly up to the plane and beyond it. Beyond an edge or corner the slopes are
    the border node's own, with no product term k_x k_z (a continuation axis after axis has one,
    and it can turn a positive field negative again far beyond the edge: a phantom lobe).
    """
    out = np.asarray(field, dtype=float)  # read only
    nearest, steps, inward = [], [], []
    for a, (o, n) in enumerate(zip(origin, grid_shape)):
        w = out.shape[a]
        u = int(o) + np.arange(w)  # global node index along the axis
        first, last = -int(o), int(n) - 1 - int(o)  # window indices of grid nodes 0 and n - 1
        c, k, c_in = np.arange(w), np.zeros(w), np.arange(w)
        for ghosts, border, inner in ((u < 0, first, first + 1), (u >= n, last, last - 1)):
            if n >= 2 and ghosts.any() and 0 <= border < w and 0 <= inner < w:
                c[ghosts], k[ghosts], c_in[ghosts] = border, np.abs(np.flatnonzero(ghosts) - border), inner
        nearest.append(c)
        steps.append(k)
        inward.append(c_in)
    border_values = out[np.ix_(*nearest)]
    result = border_values.copy()
    for a, k in enumerate(steps):
        if k.any():
            inner_values = out[np.ix_(*(inward[a] if b == a else c for b, c in enumerate(nearest)))]
            result += k.reshape((-1,) + (1,) * (out.ndim - 1 - a)) * (border_values - inner_values)
    return result


def within_nodes(origin, shape, first, last) -> np.ndarray:
    """(shape) bool: window nodes whose global index lies in [first, last] on every axis."""
    out = np.ones(tuple(shape), bool)
    for k, (o, w, f, t) in enumerate(zip(origin, shape, first, last)):
        u = int(o) + np.arange(w)
        out &= ((u >= f) & (u <= t)).reshape((-1,) + (1,) * (len(shape) - 1 - k))
    return out


def take(array: np.ndarray, indices: list[np.ndarray]) -> np.ndarray:
    """array at the outer product of per-axis node indices."""
    return array[np.ix_(*indices)]


def edt(mask: np.ndarray, spacing, full=None) -> np.ndarray:
    """Distance from every node to the nearest True node (scipy EDT), periodic along `full` axes."""
    full = [False] * mask.ndim if full is None else full
    pad = [(w // 2, w // 2) if f else (0, 0) for w, f in zip(mask.shape, full)]
    padded = np.pad(~mask, pad, mode="wrap") if any(p[0] for p in pad) else ~mask
    dist = ndimage.distance_transform_edt(padded, sampling=spacing)
    return dist[tuple(slice(p[0], p[0] + w) for p, w in zip(pad, mask.shape))]


def close_box_layers(v: np.ndarray, fraction: float, min_patch: int = 4) -> tuple[np.ndarray, int]:
    """A plain box's samples with the layers along its planes thinner than `fraction` of a grid step
    closed: where the level set crosses zero between a box plane and the first sample inside, within
    that fraction of a step of the plane, the value on the plane takes the inner sample's sign (a
    matrix layer: the inclusion then reaches the plane; a sheet of inclusion: it is dropped), its new
    value `fraction` times the inner sample's (the zero crossing then lies beyond the plane). The plane
    x = 0 holds sample 0; the plane x = L holds the linear continuation 2 v[n-1] - v[n-2]
    (`extrapolate_beyond_domain`), set by raising |v[n-1]| (its sign stays). A change that would leave
    a patch of one sign on the plane smaller than min_patch samples (a new speck of trace, or a pinhole
    in one) is not made. The mesher follows no layer thinner than the size function's floor; closing
    them moves the interface by at most that much, at those places only. Returns (new values, number
    of box-plane samples changed)."""
    out = np.array(v, dtype=float, copy=True)
    changed = 0
    for a in range(out.ndim):
        w = np.moveaxis(out, a, 0)  # a view: writes go to out
        for far in (False, True):
            inner = w[-1] if far else w[1]
            plane = 2.0 * w[-1] - w[-2] if far else w[0]
            crossing = np.abs(plane) / np.maximum(np.abs(plane) + np.abs(inner), np.finfo(float).tiny)
            close = (np.sign(plane) != np.sign(inner)) & (inner != 0) & (crossing < fraction)
            if close.any():
                negative = np.where(close, inner < 0, plane < 0)
                for side in (negative, ~negative):
                    patches, _ = ndimage.label(side)
                    size = np.bincount(patches.ravel())
                    close &= ~(side & (size[patches] < min_patch))
            target = np.sign(inner) * fraction * np.abs(inner)  # the new value on the plane
            if far:
                w[-1] = np.where(close, 0.5 * (target + w[-2]), w[-1])
            else:
                w[0] = np.where(close, target, w[0])
            changed += int(close.sum())
    return out, changed


def first_order_distance(g: np.ndarray, inside: np.ndarray, spacing, periodic: bool) -> np.ndarray:
    """Signed distance-like level set of `inside` (negative there): g over its gradient norm at the
    nodes next to the interface (a first-order distance, clipped to one step), plus the Euclidean
    distance to those nodes elsewhere (periodic: across the faces). The signs are those of `inside`."""
    h = np.asarray(spacing, float)
    grad = np.sqrt(sum(g_k**2 for g_k in _gradient(g, h, periodic)))
    band = np.zeros(g.shape, bool)
    for k in range(g.ndim):
        if periodic:
            for step in (1, -1):
                band |= inside != np.roll(inside, step, k)
        else:
            lo, hi = [slice(None)] * g.ndim, [slice(None)] * g.ndim
            lo[k], hi[k] = slice(None, -1), slice(1, None)
            differs = inside[tuple(lo)] != inside[tuple(hi)]
            band[tuple(lo)] |= differs
            band[tuple(hi)] |= differs
    near = np.clip(g / np.maximum(grad, 1e-12), -h.max(), h.max())
    if periodic:  # distance transform on a wrapped copy
        pad = [(n // 2 + 1,) * 2 for n in g.shape]
        dist, idx = ndimage.distance_transform_edt(~np.pad(band, pad, mode="wrap"), sampling=h, return_indices=True)
        core = tuple(slice(p[0], p[0] + n) for p, n in zip(pad, g.shape))
        dist, src = dist[core], tuple((ix[core] - p[0]) % n for ix, p, n in zip(idx, pad, g.shape))
    else:
        dist, idx = ndimage.distance_transform_edt(~band, sampling=h, return_indices=True)
        src = tuple(idx)
    return np.where(inside, -1.0, 1.0) * (dist + np.abs(near[src]))


def _gradient(g: np.ndarray, h: np.ndarray, periodic: bool) -> list[np.ndarray]:
    """Central differences per axis (periodic: wrapped; else one-sided at the borders)."""
    if periodic:
        return [(np.roll(g, -1, k) - np.roll(g, 1, k)) / (2 * h[k]) for k in range(g.ndim)]
    return [np.gradient(g, h[k], axis=k) for k in range(g.ndim)]


def nearest_component(labels: np.ndarray, spacing, periodic: bool, pad: int):
    """Distance to, and label of, the nearest component node of every grid node (periodic via a wrap
    pad of `pad` nodes: exact wherever the nearest component is within `pad` steps)."""
    widths = [(min(pad, n // 2),) * 2 if periodic else (0, 0) for n in labels.shape]
    lab = np.pad(labels, widths, mode="wrap") if periodic else labels
    dist, idx = ndimage.distance_transform_edt(lab == 0, sampling=spacing, return_indices=True)
    near = lab[tuple(idx)]
    crop = tuple(slice(w[0], w[0] + n) for w, n in zip(widths, labels.shape))
    return dist[crop], near[crop]


_EXACT_STEPS = 10  # nodes this close to an inclusion get their distance from its surface points


def surface_tree(field: np.ndarray, own: np.ndarray, spacing, full) -> cKDTree:
    """KD-tree of the linear zero crossings on the grid edges leaving own (window coordinates,
    index * spacing), with copies shifted by one window along full (periodic) axes."""
    pts = []
    for k in range(own.ndim):
        for step in (1, -1):
            nb_own, nb_val = np.roll(own, -step, axis=k), np.roll(field, -step, axis=k)
            edge = own & ~nb_own
            v, vn = field[edge], nb_val[edge]
            t = np.clip(v / np.minimum(v - vn, -1e-300), 0.0, 1.0)
            where = np.stack(np.nonzero(edge), axis=-1).astype(float)
            where[:, k] += step * t
            pts.append(where)
    pts = np.concatenate(pts) * np.asarray(spacing)
    for k in np.flatnonzero(full):
        shift = np.zeros(own.ndim)
        shift[k] = own.shape[k] * spacing[k]
        pts = np.concatenate([pts - shift, pts, pts + shift])
    return cKDTree(pts)


def outside_distance(tree: cKDTree, coords: np.ndarray, d_nodes: np.ndarray, spacing) -> np.ndarray:
    """Distance outside an inclusion: to its surface points where the node distance d_nodes (EDT to
    its nodes) is within _EXACT_STEPS steps, else d_nodes - h/2 (a staircase estimate, +-h/2)."""
    h = min(spacing)
    out = d_nodes - 0.5 * h
    close = d_nodes <= _EXACT_STEPS * max(spacing)
    if close.any():
        out[close] = tree.query(coords[close])[0]
    return np.maximum(out, 1e-3 * h)  # outside: strictly positive


def levelset_window_field(values, own, nearest, cid: int, spacing, full, other=None) -> np.ndarray:
    """Own level set of component cid on its window, rebuilt from the global field.

    The input values are kept inside the component, at its outside face neighbours, and at the
    non-negative nodes closer to it than to any other component where they agree with the distance
    to its surface (within half a step, that estimate's error), so the zero set near the inclusion
    is the input's; elsewhere (other inclusions included) that distance, so the field is positive
    on every other inclusion and |grad| ~ 1. Where the input is not a distance away from its zero
    set (a thresholded random field, scan intensities), kept values would jump against the
    distances and the cubic spline would ring below zero beside the jump.

    A face neighbour shared with another component (`other`, window bool) holds one value, the
    distance to the nearer of the two; for this component it is at least that, and is taken as the
    linear extrapolation of its own values towards the node (kept as a value, two spheres one step
    apart had the farther one's spline ring half a step towards the nearer one).
    """
    rim = ndimage.binary_dilation(own) & ~own  # outside face neighbours: non-negative by construction
    away = ~(own | rim)
    out = values.copy()
    if other is not None:
        shared = rim & ndimage.binary_dilation(other)
        if shared.any():
            out[shared] = np.maximum(values[shared], _extrapolated(values, own, spacing)[shared])
    if away.any():
        tree = surface_tree(np.where(own | rim, out, 1.0), own, spacing, full)
        coords = np.stack(np.nonzero(away), axis=-1) * np.asarray(spacing)
        dist = outside_distance(tree, coords, edt(own, spacing, full)[away], spacing)
        v = values[away]
        agree = (v >= 0) & (nearest[away] == cid) & (np.abs(v - dist) <= 0.5 * min(spacing))
        out[away] = np.where(agree, v, dist)
    return out


def _extrapolated(values, own, spacing) -> np.ndarray:
    """Per node: the smallest linear extrapolation of own values from a face neighbour in own (from
    that neighbour and the next node on the line when it is own too, else neighbour + step)."""
    est = np.full(values.shape, np.inf)
    for k in range(values.ndim):
        for s in (1, -1):
            v1, o1 = np.roll(values, s, axis=k), np.roll(own, s, axis=k)
            v2, o2 = np.roll(values, 2 * s, axis=k), np.roll(own, 2 * s, axis=k)
            est = np.where(o1, np.minimum(est, np.where(o2, 2 * v1 - v2, v1 + spacing[k])), est)
    return est


def labels_window_field(own, spacing, full, sigma: float = 0.75) -> np.ndarray:
    """Signed distance of a voxel set with the interface half a step from its nodes, Gaussian-smoothed
    (sigma in steps) so the cubic interpolant does not ring on the staircase, then shifted by a
    constant so that its volume (smoothed Heaviside clip(1/2 - phi/h, 0, 1)) is the voxel count
    (smoothing alone shrinks convex shapes); node signs are kept (own < 0 < others)."""
    h = min(spacing)
    inside = edt(~own, spacing, full)  # own node -> nearest non-own node
    outside = edt(own, spacing, full)  # non-own node -> nearest own node
    phi = np.where(own, 0.5 * h - inside, outside - 0.5 * h)
    phi = ndimage.gaussian_filter(phi, sigma=sigma, mode=["wrap" if f else "nearest" for f in full])
    target, lo, hi = own.sum(), -2.0 * h, 2.0 * h
    near = phi[np.abs(phi) < 4 * h]  # only these change the volume for |shift| < 2h
    for _ in range(50):  # bisection: the volume decreases monotonically with the shift
        mid = 0.5 * (lo + hi)
        vol = np.clip(0.5 - (near + mid) / h, 0.0, 1.0).sum() + (phi <= -4 * h).sum()
        lo, hi = (mid, hi) if vol > target else (lo, mid)
    phi = phi + 0.5 * (lo + hi)
    eps = 0.05 * h
    return np.where(own, np.minimum(phi, -eps), np.maximum(phi, eps))


def crossing_bounds(field: np.ndarray, own: np.ndarray, full) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of own's zero set in local fractional indices, from the linear crossings
    between own nodes (negative) and their outside neighbours along each axis."""
    lo, hi = np.zeros(field.ndim), np.zeros(field.ndim)
    for k in range(field.ndim):
        lo[k], hi[k] = np.inf, -np.inf
        for step, sign in ((1, -1.0), (-1, 1.0)):
            nb_own = np.roll(own, step, axis=k)
            nb_val = np.roll(field, step, axis=k)
            edge = own & ~nb_own
            if not full[k]:  # no wrap-around neighbour at the window ends
                first = [slice(None)] * field.ndim
                first[k] = 0 if step == 1 else -1
                edge[tuple(first)] = False
            v, vn = field[edge], nb_val[edge]
            frac = np.where(vn > v, v / np.minimum(v - vn, -1e-300), 0.0)
            pos = np.nonzero(edge)[k] + sign * np.clip(frac, 0.0, 1.0)
            if pos.size:
                lo[k], hi[k] = min(lo[k], pos.min()), max(hi[k], pos.max())
        if not np.isfinite(lo[k]):  # own fills every line along k (percolating)
            lo[k], hi[k] = -0.5, field.shape[k] - 0.5
    return lo, hi


def axis_chords(field: np.ndarray, own: np.ndarray) -> np.ndarray:
    """(d, *shape) length in grid steps of the axis-parallel chord of `own` through each node along
    each axis (chord ends at the linear zero crossings of `field`); inf where the line has no outside
    node. Axes are treated as periodic (a window has an outside layer along its other axes)."""
    out = []
    for k in range(own.ndim):
        m = np.moveaxis(own, k, -1)
        v = np.moveaxis(field, k, -1)
        w = m.shape[-1]
        m2 = np.concatenate([m, m], axis=-1)
        pos = np.arange(2 * w)
        last_out = np.maximum.accumulate(np.where(~m2, pos, -1), axis=-1)[..., w:] - w
        rev = np.where(~m2, pos, 4 * w)[..., ::-1]
        next_out = np.minimum.accumulate(rev, axis=-1)[..., ::-1][..., :w]
        closed = last_out >= -w  # the line has an outside node
        pn = np.where(closed, last_out, 0)
        en = np.where(closed, next_out, 1)

        def at(i):
            return np.take_along_axis(v, i % w, axis=-1)

        vp, v1, v2, ve = at(pn), at(pn + 1), at(en - 1), at(en)
        lo = pn + 1 - np.clip(v1 / np.minimum(v1 - vp, -1e-300), 0.0, 1.0)
        hi = en - 1 + np.clip(v2 / np.minimum(v2 - ve, -1e-300), 0.0, 1.0)
        out.append(np.moveaxis(np.where(closed, hi - lo, np.inf), -1, k))
    return np.stack(out)


def chord_thickness(field: np.ndarray, own: np.ndarray) -> float:
    """Thickness of a component in grid steps: the largest, over its nodes, of the shortest of the
    axis-parallel chords through the node (:func:`axis_chords`). Window axes are treated as periodic;
    a chord with no outside node is infinite."""
    if not own.any():
        return 0.0
    crop = []  # the component's bounding box plus one outside layer: the same chords, fewer nodes
    for k in range(own.ndim):
        hit = np.flatnonzero(own.any(axis=tuple(j for j in range(own.ndim) if j != k)))
        inner = hit[0] >= 1 and hit[-1] <= own.shape[k] - 2
        crop.append(slice(hit[0] - 1, hit[-1] + 2) if inner else slice(None))
    field, own = field[tuple(crop)], own[tuple(crop)]
    return float(axis_chords(field, own).min(axis=0)[own].max())


def necks(field: np.ndarray, labels: np.ndarray, max_chord: float) -> list[tuple[int, tuple, float]]:
    """Necks thinner than max_chord grid steps, which no mesh at the grid's resolution can follow.

    A node is thin when its chords (:func:`axis_chords`) are below max_chord across d - 1 axes (a
    filament in 3D, a strip in 2D). A cluster of thin nodes is a neck when it joins two pieces of its
    component that stay apart without the thin nodes, each of at least _MIN_SAMPLES nodes (a thin
    tip or ridge joins nothing). Arrays are treated as periodic along every axis.

    Args:
        field: (*shape) level set, negative inside. labels: (*shape) component ids, 0 outside.
    Returns:
        per necked component (ascending id): (id, index of its neck's thinnest node, that chord).
    """
    clusters, joining, chords = _neck_clusters(field, labels, max_chord)
    found = {}
    for c in joining:
        nodes = np.flatnonzero((clusters == c).ravel())
        best = nodes[np.argmin(chords.ravel()[nodes])]
        cid = int(labels.ravel()[best])
        if cid not in found or chords.ravel()[best] < found[cid][2]:
            found[cid] = (cid, np.unravel_index(best, field.shape), float(chords.ravel()[best]))
    return [found[c] for c in sorted(found)]


def neck_nodes(field: np.ndarray, labels: np.ndarray, max_chord: float) -> np.ndarray:
    """(*shape) bool: the nodes of the necks that :func:`necks` finds (removing them cuts each neck)."""
    clusters, joining, _ = _neck_clusters(field, labels, max_chord)
    return np.isin(clusters, joining) & (clusters > 0)


def _neck_clusters(field: np.ndarray, labels: np.ndarray, max_chord: float):
    """(clusters of thin nodes (*shape) int, ids of those that join two resolved pieces, chords)."""
    own = labels > 0
    chords = np.sort(axis_chords(field, own), axis=0)[field.ndim - 2]
    thin = own & (chords < max_chord)
    if not thin.any():
        return np.zeros(field.shape, np.int32), np.zeros(0, int), chords
    rest, m = label_components(own & ~thin, True)
    resolved = np.bincount(rest.ravel(), minlength=m + 1) >= _MIN_SAMPLES
    resolved[0] = False
    piece = np.where(resolved[rest], rest, 0)
    clusters, _ = label_components(thin, True)
    touch = []  # (thin cluster, resolved piece) face neighbours
    for k in range(field.ndim):
        for step in (1, -1):
            other = np.roll(piece, step, k)
            at = thin & (other > 0)
            touch.append(np.stack([clusters[at], other[at]], axis=1))
    touch = np.unique(np.concatenate(touch), axis=0)
    cl, n_pieces = np.unique(touch[:, 0], return_counts=True)
    return clusters, cl[n_pieces >= 2], chords


def repeated_end_axes(values: np.ndarray) -> list[int]:
    """Axes whose last slice repeats the first exactly (a field sampled at x = i L / (n - 1))."""
    return [k for k in range(values.ndim)
            if np.array_equal(np.take(values, 0, axis=k), np.take(values, -1, axis=k))
            and not np.array_equal(np.take(values, 0, axis=k), np.take(values, 1, axis=k))]


def periodicity_ratios(values: np.ndarray) -> list[tuple[float, float]]:
    """Per axis: (mean wrap-around jump |phi[0] - phi[n-1]|, largest mean jump between neighbouring
    interior slices). A periodic field's wrap slice is like any other slice."""
    out = []
    for k in range(values.ndim):
        axes = tuple(a for a in range(values.ndim) if a != k)
        interior = np.abs(np.diff(values, axis=k)).mean(axis=axes)
        wrap = np.abs(np.take(values, 0, axis=k) - np.take(values, -1, axis=k)).mean()
        out.append((float(wrap), float(interior.max())))
    return out


def touching_label_pairs(labels: np.ndarray, periodic: bool) -> np.ndarray:
    """(p, 2) sorted unique pairs of different positive labels that share a grid face."""
    pairs = []
    for k in range(labels.ndim):
        if periodic:
            a, b = labels, np.roll(labels, -1, axis=k)
        else:
            a, b = np.delete(labels, -1, axis=k), np.delete(labels, 0, axis=k)
        t = (a > 0) & (b > 0) & (a != b)
        pairs.append(np.sort(np.stack([a[t], b[t]], axis=-1), axis=-1))
    pairs = np.concatenate(pairs)
    return np.unique(pairs, axis=0) if pairs.size else pairs.reshape(0, 2)


def frame_values(W: np.ndarray, win: Window, own: np.ndarray, frame_origin, spacing, tree) -> np.ndarray:
    """An inclusion's level set on a frame (unwrapped node box): its window values inside the core
    (= its phi_fn at those nodes), outside_distance beyond (more accurate than the phi_fn's clamped
    extension, which only needs to stay positive). tree: surface_tree of the window."""
    dst, src, local = [], [], []
    for k in range(W.ndim):
        u = int(frame_origin[k]) + np.arange(own.shape[k]) - int(win.origin[k])
        local.append((u % W.shape[k] if win.full[k] else u) * spacing[k])
        if win.full[k]:
            dst.append(np.arange(own.shape[k]))
            src.append(u % W.shape[k])
        else:
            inside = (u >= win.core_lo[k]) & (u <= win.core_hi[k])
            dst.append(np.flatnonzero(inside))
            src.append(u[inside])
    vals = np.empty(own.shape)
    core = np.zeros(own.shape, bool)
    core[np.ix_(*dst)] = True
    vals[np.ix_(*dst)] = W[np.ix_(*src)]
    rest = np.nonzero(~core)
    if rest[0].size:
        coords = np.stack([loc[i] for loc, i in zip(local, rest)], axis=-1)
        vals[rest] = outside_distance(tree, coords, edt(own, spacing)[rest], spacing)
    return vals


def core_geometry(win: Window, k: int, spacing, shape) -> tuple[float, float]:
    """Physical centre and half-width of the core along axis k (half = inf on a full axis)."""
    h = spacing[k]
    if win.full[k]:
        return (win.origin[k] + shape[k] / 2) * h, np.inf
    centre = (win.origin[k] + (win.core_lo[k] + win.core_hi[k]) / 2) * h
    return centre, (win.core_hi[k] - win.core_lo[k]) / 2 * h


def reach_frame(start, length, grid_shape, periodic: bool, r: float):
    """Unwrapped node box within r steps of an index arc: (origin, shape); a periodic axis it would
    cover becomes the whole axis centred on the arc, plus 2 nodes per end (fold duplicates)."""
    origin, shape = [], []
    for s, m, n in zip(start, length, grid_shape):
        s, m = int(s), int(m)
        if periodic and (not np.isfinite(r) or m + 2 * r >= n):
            # the whole axis centred on the arc, 2 nodes more at each end so that nodes near the
            # antipodal plane see both images (fold() keeps the smaller value)
            origin.append(int(np.floor(s + (m - 1) / 2 - n / 2)) - 2)
            shape.append(n + 4)
        elif periodic:
            origin.append(s - int(r))
            shape.append(m + 2 * int(r))
        else:
            lo = max(0, s - int(min(r, n))) if np.isfinite(r) else 0
            hi = min(n - 1, s + m - 1 + int(min(r, n))) if np.isfinite(r) else n - 1
            origin.append(lo)
            shape.append(hi - lo + 1)
    return np.array(origin), tuple(shape)


def choose_reach(lengths: np.ndarray, grid_shape, budget: int, r_min: int) -> float:
    """Largest reach r (steps) with sum over inclusions of the reach-frame sizes <= budget; inf when
    every inclusion can cover the whole grid."""
    n = np.asarray(grid_shape)

    def cost(r):
        return np.prod(np.minimum(n, lengths + 2 * r), axis=1).sum()

    if cost(int(n.max())) <= budget:
        return np.inf
    lo, hi = 0, int(n.max())
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if cost(mid) <= budget else (lo, mid - 1)
    return float(max(lo, r_min))


def accumulate(dn1, dn2, nearest, cid: int, indices, values) -> None:
    """Fold one inclusion's values on a node box into the running first/second minima (in place).
    A node present twice (frame longer than the axis) keeps its smaller value."""
    indices = list(indices)
    for k, (idx, n) in enumerate(zip(indices, dn1.shape)):
        if len(idx) > n:
            moved = np.moveaxis(values, k, 0)
            folded = np.full((n,) + moved.shape[1:], np.inf)
            np.minimum.at(folded, idx, moved)
            values, indices[k] = np.moveaxis(folded, 0, k), np.arange(n)
    sub = np.ix_(*indices)
    a, b = dn1[sub], dn2[sub]
    closer = values < a
    dn2[sub] = np.where(closer, a, np.minimum(b, values))
    dn1[sub] = np.where(closer, values, a)
    nearest[sub] = np.where(closer, cid, nearest[sub])


# ---- validation of raw inputs (NumPy only: runs before anything is traced) ----

_MIN_SAMPLES, _MIN_THICKNESS = 8, 1.5  # a resolved feature: >= 8 nodes and >= 1.5 steps thick
_NECK_STEPS = 1.0  # a neck narrower than a grid step across d - 1 axes is below the grid's resolution
# grid inputs: inclusions closer than this (in steps) touch at the grid's resolution (the estimate
# below is itself good to a fraction of a step only; the size function would refine such a gap far)
_MIN_GAP_STEPS = 0.02


def close_pairs(dn1, dn2, nearest, labels, spacing, min_gap: float, periodic: bool, limit: int = 64):
    """Pairs of inclusions whose gap, estimated at nodes within a step of an interface as dn1 + dn2,
    is below min_gap: (k, 2) ids (ascending; the second 0 when no other inclusion is within two steps
    of the node), (k,) gaps and (k,) flat node indices, worst first, one row per pair, at most `limit`."""
    h = float(min(spacing))
    gap = np.where(np.abs(dn1) <= h, dn1 + dn2, np.inf).ravel()
    nodes = np.flatnonzero(gap < min_gap)
    nodes = nodes[np.argsort(gap[nodes], kind="stable")]
    shape = np.asarray(labels.shape)
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * labels.ndim, indexing="ij"), -1).reshape(-1, labels.ndim)
    radius = np.linalg.norm(offsets * np.asarray(spacing), axis=1)
    rows, seen = [], set()
    for node in nodes:
        a = int(nearest.flat[node])
        idx = np.asarray(np.unravel_index(node, labels.shape)) + offsets
        inside = np.ones(len(idx), bool) if periodic else ((idx >= 0) & (idx < shape)).all(axis=1)
        around = labels[tuple((idx[inside] % shape).T)]
        other = (around > 0) & (around != a)
        b = int(around[other][np.argmin(radius[inside][other])]) if other.any() else 0
        pair = (min(a, b), max(a, b)) if b else (a, 0)
        if pair not in seen:
            seen.add(pair)
            rows.append((*pair, gap[node], node))
            if len(rows) == limit:
                break
    ids = np.array([r[:2] for r in rows], np.int64).reshape(-1, 2)
    return ids, np.array([r[2] for r in rows], float), np.array([r[3] for r in rows], np.int64)


def diagonal_cells(values: np.ndarray, labels: np.ndarray, periodic: bool, per_pair: int = 4):
    """Grid squares (and cubes in 3D) whose two opposite corners lie in different components, the
    other corners >= 0: where two inclusions come closest without a matrix sample between them,
    which `close_pairs` (gaps estimated at nodes) does not see. Per pair, the `per_pair` cells with
    the lowest mean of their corners (the multilinear interpolant at the centre).

    Returns (k, 2) ids (ascending) and (k, d) cell centres in index units.
    """
    d, found = values.ndim, {}
    for axes in [a for r in range(2, d + 1) for a in itertools.combinations(range(d), r)]:
        def corner(a, offset):  # the cell's corner at `offset` (0/1 along `axes`) for every cell
            if periodic:
                return np.roll(a, tuple(-o for o in offset), axis=axes)
            cut = [slice(None)] * d
            for k, o in zip(axes, offset):
                cut[k] = slice(o, a.shape[k] - 1 + o)
            return a[tuple(cut)]
        offsets = list(itertools.product((0, 1), repeat=len(axes)))
        f = {o: corner(values, o) for o in offsets}
        lab = {o: corner(labels, o) for o in offsets}
        mean = sum(f.values()) / len(offsets)
        for o in offsets[: len(offsets) // 2]:  # each diagonal once
            q = tuple(1 - k for k in o)
            hit = (lab[o] > 0) & (lab[q] > 0) & (lab[o] != lab[q])
            for r in offsets:
                if r not in (o, q):
                    hit &= f[r] >= 0
            for idx in zip(*np.nonzero(hit)):
                centre = np.asarray(idx, float)
                centre[list(axes)] += 0.5
                pair = tuple(sorted((int(lab[o][idx]), int(lab[q][idx]))))
                found.setdefault(pair, []).append((float(mean[idx]), centre))
    rows = [(pair, x) for pair in sorted(found) for _, x in sorted(found[pair], key=lambda r: r[0])[:per_pair]]
    return (np.array([r[0] for r in rows], np.int64).reshape(-1, 2),
            np.array([r[1] for r in rows], float).reshape(-1, d))


def close_pairs_message(ids, gaps, places, spacing, min_gap: float, where: str, *, across_cell: bool = False,
                        hint: str = "move them apart, or merge them into one inclusion, or sample the field on a "
                                    "finer grid") -> str:
    """The error for pairs of inclusions closer than min_gap: the worst pairs by id, gap and place.

    places: (k, d) grid coordinates (in steps) of each pair's closest place. across_cell: the pairs
    come from `diagonal_gaps` (within one grid cell) rather than from `close_pairs` (at nodes)."""
    h = float(min(spacing))
    listed = []
    for (a, b), g, x in list(zip(ids, gaps, places))[:6]:
        place = tuple(round(float(c * s), 4) for c, s in zip(x, spacing))
        what = f"gap ~ {g / h:.3f} steps" if g >= 0 else f"overlap ~ {-g / h:.3f} steps" if across_cell else "overlap"
        listed.append(f"inclusions {a} and {b if b else 'a neighbour'}: {what} near x = {place}")
    why = ("closer across one grid cell (two diagonal samples inside different inclusions, their level sets "
           "interpolated between them touching or overlapping, so their surfaces would touch or cross)"
           if across_cell else "closer (touching or overlapping at the grid's resolution)")
    return (f"{where} expected inclusions separated by at least {min_gap / h:.3g} grid step ({min_gap:.4g}), "
            f"got {len(ids)} pair(s) {why}: " + "; ".join(listed) + f". Hint: {hint}.")


def node_places(nodes, shape) -> np.ndarray:
    """(k, d) grid coordinates of flat node indices (for close_pairs_message)."""
    return np.stack(np.unravel_index(np.asarray(nodes, np.int64), shape), axis=-1)


def check_field(values, where: str, labels: bool = False) -> np.ndarray:
    """A 2D/3D finite real field (float64), or for labels a non-negative integer / bool image."""
    try:
        a = np.asarray(values)
    except Exception as err:  # ragged lists, arbitrary objects
        raise ValueError(f"{where} expected a numeric 2D or 3D array, got {type(values).__name__}. "
                         "Hint: pass a NumPy array.") from err
    if labels:
        if a.dtype.kind not in "biu":
            raise ValueError(f"{where} expected an integer or bool label image, got dtype {a.dtype}. "
                             "Hint: cast with labels.astype(int), or use from_levelset for a level set.")
    elif a.dtype.kind not in "iuf" or a.dtype == bool:
        raise ValueError(f"{where} expected real level-set values, got dtype {a.dtype}. "
                         "Hint: use from_labels for integer / bool label images.")
    if a.ndim not in (2, 3) or min(a.shape) < 4:
        raise ValueError(f"{where} expected a 2D or 3D array with at least 4 nodes per axis, got shape "
                         f"{a.shape}. Hint: one array axis per spatial axis, axis 0 = x.")
    if labels:
        if a.dtype.kind == "i" and a.min() < 0:
            raise ValueError(f"{where} expected labels >= 0 (0 = matrix), got minimum {a.min()}. "
                             "Hint: shift or relabel the image; a level set (negative inside) in whole numbers is "
                             "read as one when stored as floats (phi.astype(float)).")
        return a
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{where} expected finite values, got {int(np.size(a) - np.isfinite(a).sum())} "
                         "NaN/inf samples. Hint: fill them (e.g. with a large positive distance).")
    return a


def check_box(box, shape, where: str, allow_none: bool = True) -> tuple[float, ...]:
    """Positive cell lengths, one per axis, giving equal spacing L_i / n_i (unit cube if None)."""
    d = len(shape)
    if box is None and allow_none:
        box = (1.0,) * d
    try:
        b = np.asarray(box, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where} expected box as {d} positive lengths, got {box!r}.") from err
    if b.shape != (d,) or not np.isfinite(b).all() or (b <= 0).any():
        raise ValueError(f"{where} expected box as {d} positive finite lengths (one per axis), got {box!r}. "
                         f"Hint: e.g. box={(1.0,) * d}.")
    h = b / np.asarray(shape)
    if (h.max() - h.min()) > 1e-6 * h.max():
        finest = h.min()
        counts = tuple(int(round(float(length / finest))) for length in b)
        raise ValueError(f"{where} expected equal grid spacing L_i / n_i on every axis (cubic voxels), got box "
                         f"{tuple(b.tolist())} over shape {tuple(shape)}: steps {tuple(float(f'{v:.6g}') for v in h)}. "
                         f"Hint: if the voxels are cubic, the box is {tuple(float(n * finest) for n in shape)}; "
                         f"if they are not, resample the grid to one step first, e.g. to shape {counts} "
                         "(a periodic level set: scipy.ndimage.map_coordinates(phi, new sample positions in "
                         "old steps, order=3, mode='grid-wrap')).")
    return tuple(float(x) for x in b)


def check_order(order) -> None:
    if order not in ("linear", "cubic"):
        raise ValueError(f"expected order 'cubic' or 'linear', got {order!r}. "
                         "Hint: 'cubic' is C2 (curvatures), 'linear' matches marching cubes.")


def check_points(points, d: int, where: str) -> np.ndarray:
    """Finite query points as float64 (m, d)."""
    try:
        p = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where} expected points (m, {d}), got {type(points).__name__}.") from err
    if p.ndim != 2 or p.shape[1] != d:
        raise ValueError(f"{where} expected points of shape (m, {d}), got {p.shape}. "
                         "Hint: one row per point, e.g. points.reshape(-1, d).")
    if not np.isfinite(p).all():
        raise ValueError(f"{where} expected finite points, got NaN/inf.")
    return p


def gradient_scale(values: np.ndarray, mask: np.ndarray, spacing, periodic: bool = True) -> tuple[float, float]:
    """Median |grad phi| (central differences) at the nodes next to the interface, 1 for a distance,
    and the ratio of its 90th to its 10th percentile there (the slope spread): about 1 for a sampled
    distance, below 1.5 for a first-order one (`first_order_distance`), above 2 for a thresholded
    Gaussian random field (`tests/test_microstructure.py::test_slope_spread_tells_distances_from_other_fields`).
    Not periodic: one-sided differences on the border slices and no pair across the wrap (the far
    sides of a field that is not periodic differ by anything: a jump there is no slope)."""
    grad2 = sum(g_k**2 for g_k in _gradient(values, np.asarray(spacing, float), periodic))
    edge = np.zeros_like(mask)
    for k in range(values.ndim):
        if periodic:
            edge |= mask != np.roll(mask, 1, k)
        else:
            lo, hi = [slice(None)] * values.ndim, [slice(None)] * values.ndim
            lo[k], hi[k] = slice(None, -1), slice(1, None)
            edge[tuple(hi)] |= mask[tuple(lo)] != mask[tuple(hi)]
    g = np.sqrt(grad2[edge])
    g = g[g > 0]
    if not g.size:
        return 1.0, 1.0
    low, median, high = np.percentile(g, [10, 50, 90])
    return float(median), float(high / low)


def _unresolved(count: int, thickness: float) -> bool:
    """An inclusion of `count` negative samples and `thickness` grid steps is too small for its grid."""
    return count < _MIN_SAMPLES or thickness < _MIN_THICKNESS


def size_errors(stats, descriptions) -> str:
    """Message listing inclusions not resolved by the grid ((count, thickness) per inclusion), or ''."""
    bad = []
    for i, ((count, thick), desc) in enumerate(zip(stats, descriptions), start=1):
        if _unresolved(count, thick):
            extra = f" (label {desc['label']})" if "label" in desc else ""
            bad.append(f"inclusion {i}{extra}: {count} negative samples, {thick:.2f} steps thick")
    if not bad:
        return ""
    return (f"expected every inclusion resolved by the grid (>= {_MIN_SAMPLES} negative samples, >= "
            f"{_MIN_THICKNESS} grid steps thick), got {len(bad)} smaller: " + "; ".join(bad[:10])
            + ". Hint: sample the field on a finer grid, or remove the specks "
            "(e.g. skimage.morphology.remove_small_objects).")


def box_cut_small(stats, labels: np.ndarray) -> list[int]:
    """Ids (1-based) of the inclusions that size_errors refuses and that touch the grid's border."""
    border = set()
    for k in range(labels.ndim):
        border |= set(np.unique(np.take(labels, [0, -1], axis=k)).tolist())
    return [i for i, (count, thick) in enumerate(stats, start=1) if _unresolved(count, thick) and i in border]


def neck_errors(found, where: str) -> str:
    """The error for necks found in the inputs ((inclusion name, x, chord in steps) each)."""
    listed = [f"{name} narrows to {chord:.2f} steps near x = {tuple(round(float(v), 4) for v in x)}"
              for name, x, chord in found[:6]]
    return (f"{where} expected every inclusion at least {_NECK_STEPS:g} grid step wide wherever it narrows, got "
            f"{len(found)} with a thinner neck (below the grid's resolution: no mesh can follow it): "
            + "; ".join(listed) + ". Hint: sample the field on a finer grid, smooth it, or cut the inclusion "
            "in two at the neck.")


def check_function_args(phi_fns, box, grid_shape, volumes, descriptions):
    """Validated (phi_fns list, box, grid_shape, volumes, descriptions) of from_functions."""
    if callable(phi_fns) or not isinstance(phi_fns, Sequence) or len(phi_fns) == 0:
        raise ValueError("from_functions expected a non-empty sequence of callables, got "
                         f"{type(phi_fns).__name__}. "
                         "Hint: pass [sphere_sdf(c, r) for ...], one callable per inclusion.")
    bad = [i for i, f in enumerate(phi_fns) if not callable(f)]
    if bad:
        raise ValueError(f"from_functions expected callables, got non-callable entries at {bad}.")
    try:
        shape = tuple(int(n) for n in grid_shape)
    except (TypeError, ValueError) as err:
        raise ValueError(f"from_functions expected grid_shape as d integers, got {grid_shape!r}.") from err
    if len(shape) not in (2, 3) or min(shape) < 4 or any(n != m for n, m in zip(shape, grid_shape)):
        raise ValueError(f"from_functions expected grid_shape of 2 or 3 integers >= 4, got {grid_shape!r}. "
                         "Hint: e.g. grid_shape=(64, 64, 64).")
    box = check_box(box, shape, "from_functions", allow_none=False)
    n = len(phi_fns)
    volumes = [None] * n if volumes is None else list(volumes)
    descriptions = [{"kind": "function"} for _ in range(n)] if descriptions is None else list(descriptions)
    if len(volumes) != n or len(descriptions) != n:
        raise ValueError(f"from_functions expected {n} volumes and descriptions (one per phi_fn), got "
                         f"{len(volumes)} and {len(descriptions)}.")
    for i, vol in enumerate(volumes):
        if vol is not None and not (np.isfinite(float(vol)) and float(vol) > 0):
            raise ValueError(f"from_functions expected positive volumes, got volumes[{i}] = {vol!r}.")
    volumes = [None if vol is None else float(vol) for vol in volumes]
    return list(phi_fns), box, shape, volumes, [dict(dsc) for dsc in descriptions]
