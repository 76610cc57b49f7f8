"""The one home of periodic (minimum-image / wrap) arithmetic.

Works on NumPy arrays and on JAX arrays (traced or not) alike: the array module is picked
from the argument, and jax is only imported when a JAX array arrives, so NumPy topology
code can use these functions without importing jax.
"""

from __future__ import annotations

import numpy as np


def _array_module(x):
    if isinstance(x, (np.ndarray, np.generic, float, int, list, tuple)):
        return np
    import jax.numpy as jnp  # only reached for JAX arrays / tracers

    return jnp


def wrap(points, box):
    """Map points into the periodic cell [0, L) along every axis.

    points: (..., d); box: (d,) lengths. Returns the same shape.
    """
    xp = _array_module(points)
    box = xp.asarray(box, dtype=points.dtype if hasattr(points, "dtype") else None)
    return points - box * xp.floor(points / box)


def minimum_image(delta, box):
    """Shortest periodic representative of a difference vector: each component in [-L/2, L/2].

    delta: (..., d); box: (d,). Returns the same shape.
    """
    xp = _array_module(delta)
    box = xp.asarray(box, dtype=delta.dtype if hasattr(delta, "dtype") else None)
    return delta - box * xp.round(delta / box)


def periodic_distance(a, b, box):
    """Euclidean minimum-image distance between points a (..., d) and b (..., d)."""
    xp = _array_module(a)
    d = minimum_image(a - b, box)
    return xp.sqrt(xp.sum(d * d, axis=-1))


def image_shifts(dim: int, box) -> np.ndarray:
    """The 3**dim lattice translations {-L, 0, L}^dim, (3**dim, dim), zero shift first."""
    grids = np.meshgrid(*[np.array([0, -1, 1])] * dim, indexing="ij")
    k = np.stack([g.ravel() for g in grids], axis=-1).astype(float)
    return k * np.asarray(box, dtype=float)


def nearest_images_suffice(centre, spread, box) -> bool:
    """Whether, per axis, the two images of a point nearest a shape's centre (2^d of the 3^d shifts
    `image_shifts` gives) always hold its periodic minimum, for a shape between two balls about the
    centre whose radii differ by spread (0 for a sphere, a_max - a_min for an ellipsoid).

    NumPy only. With the centre in the cell the best image per axis lies within L/2 of it, so the
    best of the kept images is at a <= D/2 (D the cell's diagonal); a dropped image is on some axis
    the farthest of three, at least L_min farther in square, so its value is at least
    sqrt(a^2 + L_min^2) - R while the kept one's is at most a - r: it cannot be smaller when
    spread <= sqrt(D^2/4 + L_min^2) - D/2 (0.457 L for a cube).
    """
    centre, box = np.asarray(centre, float), np.asarray(box, float)
    half_diagonal = 0.5 * float(np.linalg.norm(box))
    bound = float(np.hypot(half_diagonal, box.min())) - half_diagonal
    return bool(np.all((centre >= 0) & (centre <= box))) and float(spread) <= bound


def nearest_image_shifts(offsets, box):
    """Per point, the 2^d shifts of {-L, 0, L}^d that keep, per axis, the two images of offsets
    (point - centre, (m, d)) nearest the centre: 0 and -L where the offset is >= 0, else 0 and +L.
    Returns (2^d, m, d), the zero shift first (NumPy or JAX, like offsets)."""
    xp = _array_module(offsets)
    dim = offsets.shape[-1]
    box = xp.asarray(box, dtype=offsets.dtype)
    other = xp.where(offsets >= 0, -box, box)
    corners = np.stack(np.meshgrid(*[np.array([0.0, 1.0])] * dim, indexing="ij"), axis=-1).reshape(-1, dim)
    return xp.asarray(corners, dtype=offsets.dtype)[:, None, :] * other[None]


def points_near(points, centres, radii, box, periodic: bool = True) -> list[np.ndarray]:
    """Per centre i, the sorted indices of points within radii[i] of it (minimum image when periodic).

    NumPy only. A k-d tree over the points (periodic: scipy's boxsize) instead of a distance from
    every point to every centre.
    """
    from scipy.spatial import cKDTree

    points, centres = np.asarray(points, dtype=float), np.asarray(centres, dtype=float)
    if not len(points) or not len(centres):
        return [np.zeros(0, np.int64) for _ in range(len(centres))]
    box = np.asarray(box, dtype=float)
    if periodic:
        points, centres = wrap(points, box), wrap(centres, box)
        points = np.where(points >= box, points - box, points)  # wrap can round up to L itself
        centres = np.where(centres >= box, centres - box, centres)
        tree = cKDTree(points, boxsize=box)
    else:
        tree = cKDTree(points)
    found = tree.query_ball_point(centres, np.asarray(radii, dtype=float))
    return [np.sort(np.asarray(f, dtype=np.int64)) for f in found]


def nearest_centres(points, centres, box, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-image distances (m, k) from each point to its k nearest centres and their indices.

    NumPy only (scipy's periodic k-d tree). k is capped at the number of centres.
    """
    from scipy.spatial import cKDTree

    box = np.asarray(box, dtype=float)
    points, centres = wrap(np.asarray(points, dtype=float), box), wrap(np.asarray(centres, dtype=float), box)
    points = np.where(points >= box, points - box, points)  # wrap can round up to L itself
    centres = np.where(centres >= box, centres - box, centres)
    k = min(int(k), len(centres))
    dist, idx = cKDTree(centres, boxsize=box).query(points, k=k)
    return dist.reshape(len(points), k), idx.reshape(len(points), k)


def wrap_index(index, n):
    """Periodic grid index wrap (integer arrays, NumPy or JAX)."""
    return index % n


def plane_clearances(lower, upper, box, shape) -> list[np.ndarray]:
    """Per axis a, (n_a,) the periodic distance from each grid plane x_a = k L_a / n_a to the nearest
    inclusion extent bound along a (lower[:, a] or upper[:, a]).

    A box plane near such a bound meets an inclusion at a grazing angle (a shallow cap or a surface
    just clear of it), which leaves a wedge of the domain thinner than the elements.
    lower, upper: (N, d) inclusion bounds (unwrapped); box: (d,); shape: grid samples per axis.
    """
    lower, upper = np.asarray(lower, float).reshape(-1, len(box)), np.asarray(upper, float).reshape(-1, len(box))
    return [_distance_to_heights(n, length, np.concatenate([lower[:, a], upper[:, a]]))
            for a, (length, n) in enumerate(zip(box, shape))]


def clearest_roll(lower, upper, box, shape, values=None) -> tuple[int, ...]:
    """Per axis, the grid sample k whose plane lies farthest from every inclusion bound
    (`plane_clearances`); 0 where the plane x_a = 0 is already as clear. Rolling the periodic
    grid by -k puts the box faces there. Given the samples values (shape), the sample whose box is
    farthest from every grazing meeting with their interface as well (`frame_clearance`), as
    roll='auto' takes it."""
    if values is not None:
        return clearest_frame(frame_clearance(values, box, lower, upper))
    return clearest_planes(plane_clearances(lower, upper, box, shape))


def clearest_planes(clearances: list[np.ndarray]) -> tuple[int, ...]:
    """`clearest_roll` from the per-axis clearances of `plane_clearances`."""
    return tuple(0 if c[0] >= c.max() else int(np.argmax(c)) for c in clearances)


# --- the frame of a periodic grid: where its box planes, edges and corners meet the interface ---------
#
# A box plane tangent to the interface, a trace on a box face tangent to a box edge, or an interface
# through a box corner leaves a wedge of the domain thinner than the elements. Rolling a periodic grid
# moves the box to any sample; these functions score each sample as the box corner. Distances are
# physical; the interface is the zero set of the samples, linearly interpolated (marching cubes or
# squares), which finds tangencies to well within a step of where the cubic field has them.

_PAD = 2  # samples of periodic padding: contour vertices in the cell then have their whole neighbourhood


def _ahead(points: np.ndarray, a: int, i, j) -> np.ndarray:
    """Whether points[j] comes after points[i] along axis a, ties broken by the next axes in turn:
    the height function tilted by an infinitesimal, so vertices sharing a grid coordinate (most do)
    make no spurious extremes."""
    order = [a] + [b for b in range(points.shape[1]) if b != a]
    ahead = np.zeros(np.shape(i), bool)
    decided = np.zeros(np.shape(i), bool)
    for b in order:
        u, v = points[i, b], points[j, b]
        ahead |= ~decided & (v > u)
        decided |= u != v
    return ahead


def _contour_critical_heights(values: np.ndarray, step: np.ndarray) -> list[np.ndarray]:
    """The zero set of the periodic samples values (2D or 3D): per axis a, the coordinates x_a (in
    [0, L_a)) of its points where it is tangent to a plane x_a = const (extremes, and in 3D saddles, of
    the height x_a on it)."""
    from skimage.measure import find_contours, marching_cubes

    dim = values.ndim
    padded = np.pad(values, _PAD, mode="wrap")
    padded = np.where(padded == 0.0, 1e-12 * float(np.abs(values).max() or 1.0), padded)
    box = step * np.array(values.shape)
    if dim == 3:
        if padded.min() >= 0 or padded.max() <= 0:
            return [np.empty(0)] * 3
        verts, faces, _, _ = marching_cubes(padded, 0.0, spacing=tuple(step), allow_degenerate=False)
        points = verts.astype(float) - _PAD * step
        # a vertex is regular when the signs of its link's vertices (above/below it) change twice round it;
        # each link edge is the far edge of one incident triangle, so count triangles whose far ends differ
        corner = faces.reshape(-1)
        far = [np.roll(faces, -1, axis=1).reshape(-1), np.roll(faces, -2, axis=1).reshape(-1)]

        def links(a):
            changes = _ahead(points, a, corner, far[0]) != _ahead(points, a, corner, far[1])
            return np.bincount(corner, changes, minlength=len(points))
    else:
        contours = [c * step for c in find_contours(padded, 0.0)]
        if not contours:
            return [np.empty(0)] * 2
        points = np.concatenate(contours) - _PAD * step
        starts = np.cumsum([0] + [len(c) for c in contours[:-1]])
        ends = starts + np.array([len(c) for c in contours]) - 1
        closed = np.array([np.array_equal(c[0], c[-1]) for c in contours])
        index = np.arange(len(points))
        owner = np.repeat(np.arange(len(contours)), [len(c) for c in contours])
        prev, nxt = index - 1, index + 1
        # a closed polyline repeats its first point last: its ends' neighbours are across that point
        prev = np.where(index == starts[owner], np.where(closed[owner], ends[owner] - 1, -1), prev)
        nxt = np.where(index == ends[owner], np.where(closed[owner], starts[owner] + 1, -1), nxt)
        interior = (prev >= 0) & (nxt >= 0) & ~(closed[owner] & (index == ends[owner]))

        def links(a):
            i = np.flatnonzero(interior)
            out = np.full(len(points), 2)
            out[i] = 2 * (_ahead(points, a, i, prev[i]) != _ahead(points, a, i, nxt[i]))
            return out
    inside = np.all((points >= 0) & (points < box), axis=1)
    return [points[inside & (links(a) != 2), a] for a in range(dim)]


def _distance_to_heights(n: int, length: float, heights: np.ndarray) -> np.ndarray:
    """(n,) periodic distance from each grid plane k L / n to the nearest of heights (inf if none)."""
    if not len(heights):
        return np.full(n, np.inf)
    planes = np.arange(n) * (length / n)
    return np.abs(minimum_image(planes[:, None] - np.asarray(heights)[None, :], np.array([length]))).min(axis=1)


def _edge_crossings(values: np.ndarray, a: int) -> np.ndarray:
    """(values.shape) where the zero set crosses the grid edge from each sample to the next along axis a
    (periodic), as the fraction t in [0, 1] of the edge (linear interpolation); inf where the signs agree."""
    ahead = np.roll(values, -1, axis=a)
    with np.errstate(divide="ignore", invalid="ignore"):  # a sign change means different values: no 0 / 0
        return np.where(np.sign(values) != np.sign(ahead), values / (values - ahead), np.inf)


def _corner_crossings(values: np.ndarray, step: np.ndarray, a: int) -> np.ndarray:
    """(values.shape) distance along axis a from each sample to the zero crossing of the grid line
    through it in its two adjacent cells (inf where neither crosses): an interface near a box corner."""
    t = _edge_crossings(values, a)
    to_ahead = np.where(np.isfinite(t), (1.0 - t), np.inf)  # from sample k+1 back to the crossing in [k, k+1]
    return step[a] * np.minimum(t, np.roll(to_ahead, 1, axis=a))


def _crossing_slopes(values: np.ndarray, step: np.ndarray, origin_only: bool = False):
    """How steeply the interface crosses the grid's planes and (in 3D) lines, at the zero crossings of
    grid edges (gradient by periodic central differences, interpolated along the edge): per axis a,
    (n_a,) the smallest tan of the angle between the interface and the plane x_a = k L_a / n_a; in 3D
    also per axis b, (n, n) over the other two axes' samples, the smallest tan of the angle between a
    trace on either plane through the line along b and that line. inf where nothing crosses.
    origin_only: only the edges in the planes through sample 0 (the other entries stay inf)."""
    dim, shape = values.ndim, values.shape
    planes = [np.full(n, np.inf) for n in shape]
    lines = [np.full([shape[x] for x in range(3) if x != b], np.inf) for b in range(dim)] if dim == 3 else []

    def shifted(index, a, by):
        index = list(index)
        index[a] = wrap_index(index[a] + by, shape[a])
        return tuple(index)

    def gradient(index):
        return np.stack([(values[shifted(index, a, 1)] - values[shifted(index, a, -1)]) / (2 * step[a])
                         for a in range(dim)])

    def crossing_edges(b, a=None):  # edges along b (in the plane x_a = 0 only, given a): indices, and t
        t = _edge_crossings(values if a is None else np.take(values, [0], axis=a), b)
        index = np.nonzero(np.isfinite(t))
        return index, t[index]

    for b in range(dim):
        found = [crossing_edges(b, a) for a in range(dim) if a != b] if origin_only else [crossing_edges(b)]
        index = tuple(np.concatenate([f[0][x] for f in found]) for x in range(dim))
        t = np.concatenate([f[1] for f in found])
        if not len(t):
            continue
        normal = np.abs((1 - t) * gradient(index) + t * gradient(shifted(index, b, 1)))
        squared = (normal**2).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):  # a flat gradient: NaN, which fmin skips
            for a in (x for x in range(dim) if x != b):  # the edge lies in the planes of the other axes
                np.fmin.at(planes[a], index[a], np.sqrt(np.maximum(squared - normal[a] ** 2, 0.0)) / normal[a])
            if dim == 3:  # the traces on the two planes through the line along b: tangent to it where n_b = 0
                a, c = (x for x in range(3) if x != b)
                np.fmin.at(lines[b], (index[a], index[c]), normal[b] / np.maximum(normal[a], normal[c]))
    return planes, lines


def frame_clearance(values, box, lower=None, upper=None, origin_only: bool = False) -> np.ndarray:
    """For a periodic grid of samples values (n_1, ..., n_d) (negative inside), the array (n_1, ..., n_d)
    whose entry k is the smallest distance, in the frame whose box corner is sample k, between the box
    and a grazing meeting with the interface: a box plane and a point where the interface is tangent
    to it (or an inclusion extent bound, lower/upper (N, d), when given; NaN: none along that axis); in
    3D a box edge and a point where a box face's trace is tangent to it; a box corner and the
    interface's crossing of a box edge; and a shallow crossing, as the wedge it leaves one step from
    where it crosses: step * tan(angle) between the interface and a box plane, or in 3D between a
    face's trace and a box edge (`_crossing_slopes`). Tangencies inside a cell cross no grid plane:
    the distances above cover them.

    NumPy and scikit-image only. Rolling the grid by -k puts the box corner at sample k. origin_only:
    the frame as given only, an array of ones in shape (its face traces only, not every frame's: the
    most of the cost, and no array of the grid's size)."""
    values = np.asarray(values, dtype=float)
    box = np.asarray(box, dtype=float)
    dim, shape = values.ndim, values.shape
    step = box / np.array(shape)
    frames = (1,) * dim if origin_only else shape

    def expand(array, axes):  # broadcast over the frames' other axes
        return array.reshape([frames[b] if b in axes else 1 for b in range(dim)])

    def planes(a, heights):  # the frames' box planes of axis a: distances to heights
        return _distance_to_heights(shape[a], box[a], heights)[:frames[a]]

    clearance = np.full(frames, np.inf)
    heights = _contour_critical_heights(values, step)
    if lower is not None and len(lower):
        bounds = np.concatenate([np.asarray(lower, float).reshape(-1, dim), np.asarray(upper, float).reshape(-1, dim)])
        heights = [np.concatenate([h, bounds[np.isfinite(bounds[:, a]), a]]) for a, h in enumerate(heights)]
    for a in range(dim):
        np.minimum(clearance, expand(planes(a, heights[a]), (a,)), out=clearance)
        lines = values[tuple(slice(None) if b == a else slice(frames[b]) for b in range(dim))]
        np.minimum(clearance, np.take(_corner_crossings(lines, step, a), range(frames[a]), axis=a), out=clearance)
    if dim == 3:
        for a in range(3):
            b, c = [x for x in range(3) if x != a]
            along_b, along_c = np.full((frames[a], frames[b]), np.inf), np.full((frames[a], frames[c]), np.inf)
            for k in range(frames[a]):
                hb, hc = _contour_critical_heights(np.take(values, k, axis=a), step[[b, c]])
                along_b[k], along_c[k] = planes(b, hb), planes(c, hc)
            np.minimum(clearance, expand(along_b, (a, b)), out=clearance)
            np.minimum(clearance, expand(along_c, (a, c)), out=clearance)
    plane_slopes, line_slopes = _crossing_slopes(values, step, origin_only)
    for a, slopes in enumerate(plane_slopes):
        np.minimum(clearance, expand(step.min() * slopes[:frames[a]], (a,)), out=clearance)
    for b, slopes in enumerate(line_slopes):
        a, c = (x for x in range(3) if x != b)
        np.minimum(clearance, expand(step.min() * slopes[:frames[a], :frames[c]], (a, c)), out=clearance)
    return clearance


def clearest_frame(clearance: np.ndarray) -> tuple[int, ...]:
    """The sample of `frame_clearance` farthest from every grazing meeting; zeros where the frame as
    given is already as clear."""
    if clearance[(0,) * clearance.ndim] >= clearance.max():
        return (0,) * clearance.ndim
    return tuple(int(k) for k in np.unravel_index(np.argmax(clearance), clearance.shape))
