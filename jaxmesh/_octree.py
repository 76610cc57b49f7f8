"""Periodic octree (quadtree in 2D) initial node distribution from a size function (paper 4.3).

NumPy only (never imports jax). Dimension-generic: the same code builds the 2D quadtree.

The box is covered by a base grid of near-cubic root cells (n_a = round(L_a / min L) per axis).
A cell is split in 2^d when h, interpolated at its mid-edges and its centre, is smaller than its
(largest) edge times ``density``. The paper's rule is density 1; since the minimum over the cell
decides, its leaves then have edges of 0.5-0.6 h. The default 0.75 centres the Delaunay edge
lengths of the nodes on h (median ~0.8 h, > 90 % within [0.5, 1.5] h in tests/test_octree.py). The tree lives on the torus: cells are
integer (level, index) pairs whose neighbours wrap across the periodic faces, and the 2:1
balance (neighbours through faces, edges AND corners differ by at most one level) is enforced
across them too. The nodes are the cell vertices, collected modulo the periodic lattice, so a
node on the face x = 0 is also a node of the face x = L: both faces carry exactly the same
trace, whichever side refined it (hanging nodes are kept: they are just points).

Output convention: ``points`` fill the CLOSED box [0, L]^d: every node with a coordinate 0 is
repeated with that coordinate L (a box corner 2^d times), and ``periodic_pairs[axis]`` lists the
(lower, upper) index pairs with points[upper] = points[lower] + L e_axis exactly (x = 0 + L).
``canonical`` maps every point to its representative in [0, L)^d.
Nodes closer to an interface than removal_fraction * h are removed (the interfaces get their own
nodes); the box corners are always kept.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ._periodic import wrap

Sampler = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class OctreeNodes:
    """Nodes of a periodic octree / quadtree.

    Attributes:
        points: (n, d) nodes in the closed box [0, L]^d (upper-face copies included).
        depth: (n,) finest level among the leaves sharing the node (0: root cells).
        canonical: (n,) index of each point's representative in [0, L)^d (itself if inside).
        periodic_pairs: axis -> (k, 2) int pairs (i, j), points[j] = points[i] + L e_axis.
        cell_origin, cell_size: (m, d) lower corner and edge lengths of the leaf cells.
        cell_depth: (m,) level of each leaf.
        box: (d,) lengths; periodic: whether the tree wraps.
    """

    points: np.ndarray
    depth: np.ndarray
    canonical: np.ndarray
    periodic_pairs: dict[int, np.ndarray]
    cell_origin: np.ndarray
    cell_size: np.ndarray
    cell_depth: np.ndarray
    box: tuple[float, ...]
    periodic: bool = True
    removed: int = field(default=0)

    @property
    def dim(self) -> int:
        return len(self.box)

    def wrapped(self) -> np.ndarray:
        """(n_w, d) one point per periodic class, in [0, L)^d."""
        return self.points[self.canonical == np.arange(len(self.points))]


def interpolate_grid(values: np.ndarray, box: Sequence[float], points: np.ndarray) -> np.ndarray:
    """Periodic multilinear interpolation of node-centred grid samples (node i at i * L / n).

    The NumPy twin of jaxmesh.geometry._grid.interpolate_linear (same convention, same result),
    so that the octree and the JAX code see the same h(x).

    Args:
        values: (nx, ny[, nz]) samples; box: (d,) lengths; points: (m, d), wrapped periodically.

    Returns:
        (m,) values.
    """
    values = np.asarray(values, dtype=float)
    shape, d = np.array(values.shape), values.ndim
    t = wrap(np.asarray(points, dtype=float), np.asarray(box, dtype=float)) * (shape / np.asarray(box))
    base = np.floor(t)
    frac = t - base
    base = base.astype(np.int64)
    flat = values.reshape(-1)
    strides = [int(np.prod(shape[a + 1 :])) for a in range(d)]
    lo = [(base[:, a] % shape[a]) * strides[a] for a in range(d)]  # per-axis flat offsets
    hi = [((base[:, a] + 1) % shape[a]) * strides[a] for a in range(d)]
    out = np.zeros(len(t))
    for corner in itertools.product((0, 1), repeat=d):
        index, weight = 0, 1.0
        for a, c in enumerate(corner):
            index = index + (hi[a] if c else lo[a])
            weight = weight * (frac[:, a] if c else 1.0 - frac[:, a])
        out += weight * flat[index]
    return out


def _sampler(source, box, name: str) -> Sampler:
    if callable(source):
        return lambda p: np.asarray(source(p), dtype=float).reshape(len(p))
    arr = np.asarray(source, dtype=float)
    if arr.ndim != len(box) or min(arr.shape) < 2 or not np.all(np.isfinite(arr)):
        raise ValueError(f"periodic_octree_nodes expected {name} as a finite {len(box)}D node-centred grid "
                         f"(or a callable), got shape {arr.shape}. Hint: SizeField.values / Microstructure.dn1.")
    return lambda p: interpolate_grid(arr, box, p)


def _sample_offsets(d: int) -> np.ndarray:
    """Mid-edges (one coordinate 1/2, the others 0 or 1) and the centre, in cell units."""
    mids = [c for c in itertools.product((0.0, 0.5, 1.0), repeat=d) if sum(x == 0.5 for x in c) == 1]
    return np.array(mids + [(0.5,) * d])


class _Leaves:
    """Leaf cells per level as sorted linear keys of their integer index (periodic torus)."""

    def __init__(self, roots: np.ndarray, periodic: bool):
        self.roots, self.periodic, self.d = roots, periodic, len(roots)
        self.keys: dict[int, np.ndarray] = {}

    def dims(self, level: int) -> np.ndarray:
        return self.roots * 2**level

    def encode(self, level: int, idx: np.ndarray) -> np.ndarray:
        return np.ravel_multi_index(tuple(idx.T), tuple(self.dims(level)))

    def decode(self, level: int, keys: np.ndarray) -> np.ndarray:
        return np.stack(np.unravel_index(keys, tuple(self.dims(level))), axis=-1)

    def add(self, level: int, idx: np.ndarray) -> None:
        old = self.keys.get(level, np.zeros(0, dtype=np.int64))
        self.keys[level] = np.union1d(old, self.encode(level, idx))

    def contains(self, level: int, keys: np.ndarray) -> np.ndarray:
        have = self.keys.get(level)
        if have is None or have.size == 0:
            return np.zeros(keys.shape, dtype=bool)
        pos = np.minimum(np.searchsorted(have, keys), have.size - 1)
        return have[pos] == keys

    def split(self, level: int, keys: np.ndarray) -> None:
        """Replace leaves (level, keys) by their 2^d children."""
        self.keys[level] = np.setdiff1d(self.keys[level], keys)
        idx = self.decode(level, keys)
        kids = (2 * idx[:, None, :] + np.array(list(itertools.product((0, 1), repeat=self.d)))[None])
        self.add(level + 1, kids.reshape(-1, self.d))

    def balance(self) -> None:
        """2:1 balance over face, edge and corner neighbours (across periodic faces if periodic)."""
        offsets = np.array([o for o in itertools.product((-1, 0, 1), repeat=self.d) if any(o)])
        while True:
            marks: dict[int, set] = {}
            for level in sorted(k for k, v in self.keys.items() if v.size and k >= 2):
                idx = self.decode(level, self.keys[level])
                nb = (idx[:, None, :] + offsets[None]).reshape(-1, self.d)
                n = self.dims(level)
                if self.periodic:
                    nb %= n
                else:
                    nb = nb[np.all((nb >= 0) & (nb < n), axis=1)]
                # the parent-level regions next to the leaves (integer keys: np.unique(axis=0) is slow)
                nb = self.decode(level - 1, np.unique(self.encode(level - 1, nb // 2)))
                for coarse in range(level - 1):  # a leaf at coarse < level - 1 covering one must split
                    keys = np.unique(self.encode(coarse, nb // 2 ** (level - 1 - coarse)))
                    hit = keys[self.contains(coarse, keys)]
                    if hit.size:
                        marks.setdefault(coarse, set()).update(hit.tolist())
            if not marks:
                return
            for level in sorted(marks):
                self.split(level, np.fromiter(marks[level], dtype=np.int64))


def periodic_octree_nodes(h_grid, box: Sequence[float], *, max_depth: int | None = None, balance: bool = True,
                          interface_phi=None, removal_fraction: float = 0.5, density: float = 0.75,
                          periodic: bool = True) -> OctreeNodes:
    """Node distribution of a periodic octree (3D) / quadtree (2D) refined to the size function.

    Args:
        h_grid: sizes on the node-centred periodic grid (SizeField.values as NumPy), or a callable
            points (m, d) -> (m,) h.
        box: (d,) cell lengths, d = 2 or 3.
        max_depth: deepest level below the root cells (default: deep enough for min h, <= 16).
        balance: enforce the 2:1 balance (also across the periodic faces).
        interface_phi: DN1 grid (or callable) of the interfaces; nodes with |phi| <
            removal_fraction * h are removed (box corners kept). None: no removal.
        removal_fraction: see interface_phi.
        density: split when h < density * edge (paper: 1; larger gives finer trees).
        periodic: wrap neighbours and identify opposite faces (False: a plain box octree).

    Returns:
        :class:`OctreeNodes`.

    Example:
        >>> nodes = periodic_octree_nodes(np.asarray(field.values), field.box, interface_phi=ms.dn1)
        >>> nodes.points.shape, nodes.periodic_pairs[0].shape
    """
    box_arr = np.asarray(box, dtype=float)
    d = box_arr.size
    if d not in (2, 3) or box_arr.ndim != 1 or not np.all(np.isfinite(box_arr) & (box_arr > 0)):
        raise ValueError(f"periodic_octree_nodes expected 2 or 3 positive box lengths, got {box!r}. "
                         "Hint: box=(Lx, Ly[, Lz]).")
    if not (0.0 <= removal_fraction < 2.0) or not (0.1 <= density <= 10.0):
        raise ValueError(f"periodic_octree_nodes expected removal_fraction in [0, 2) and density in [0.1, 10], "
                         f"got {removal_fraction}, {density}. Hint: the defaults are 0.5 and 0.75.")
    h_fn = _sampler(h_grid, box_arr, "h_grid")
    roots = np.maximum(1, np.round(box_arr / box_arr.min())).astype(np.int64)
    root_size = box_arr / roots
    h_min = float(np.min(h_grid)) if not callable(h_grid) else None
    if h_min is not None and h_min <= 0:
        raise ValueError(f"periodic_octree_nodes expected positive sizes, got min h = {h_min}. "
                         "Hint: pass SizeField.values.")
    key_limit = int((62 / d) - math.log2(roots.max()))  # linear keys must fit in int64
    if max_depth is None:
        ratio = root_size.max() * density / (h_min if h_min is not None else root_size.max() / 2**12)
        max_depth = min(key_limit, 16, max(0, math.ceil(math.log2(max(ratio, 1.0))) + 1))
    if not 0 <= max_depth <= key_limit:
        raise ValueError(f"periodic_octree_nodes expected max_depth in [0, {key_limit}], got {max_depth}.")

    leaves = _Leaves(roots, periodic)
    offsets = _sample_offsets(d)
    active = np.stack(np.meshgrid(*[np.arange(n) for n in roots], indexing="ij"), -1).reshape(-1, d)
    for level in range(max_depth + 1):
        size = root_size / 2**level
        # samples on the half-cell lattice: mid-edges are shared by 2^(d-1) cells, evaluate each once
        half = (2 * active[:, None, :] + (2 * offsets[None]).astype(np.int64)).reshape(-1, d)
        keys, inverse = np.unique(np.ravel_multi_index(tuple(half.T), tuple(2 * leaves.dims(level) + 1)),
                                  return_inverse=True)
        uniq = np.stack(np.unravel_index(keys, tuple(2 * leaves.dims(level) + 1)), axis=-1) * (size / 2)
        h = h_fn(uniq)[inverse.reshape(-1)].reshape(len(active), len(offsets)).min(axis=1)
        split = (h < density * size.max()) if level < max_depth else np.zeros(len(active), bool)
        leaves.add(level, active[~split])
        kids = 2 * active[split][:, None, :] + np.array(list(itertools.product((0, 1), repeat=d)))[None]
        active = kids.reshape(-1, d)
        if active.size == 0:
            break
    if balance:
        leaves.balance()
    return _collect(leaves, root_size, box_arr, h_fn, interface_phi, removal_fraction, periodic)


def _collect(leaves: _Leaves, root_size, box, h_fn, interface_phi, removal_fraction, periodic) -> OctreeNodes:
    """Cell vertices (modulo the lattice if periodic), removal near interfaces, face copies."""
    d = len(box)
    top = max(k for k, v in leaves.keys.items() if v.size)
    fine = leaves.dims(top)  # integer node lattice of the finest level: N_a = n_a 2^top
    corners = np.array(list(itertools.product((0, 1), repeat=d)))
    origins, sizes, depths, node_keys, node_depth = [], [], [], [], []
    lattice = fine if periodic else fine + 1
    for level, keys in sorted(leaves.keys.items()):
        if keys.size == 0:
            continue
        idx = leaves.decode(level, keys)
        origins.append(idx * (root_size / 2**level))
        sizes.append(np.broadcast_to(root_size / 2**level, idx.shape))
        depths.append(np.full(len(idx), level))
        verts = ((idx[:, None, :] + corners[None]) * 2 ** (top - level)).reshape(-1, d)
        verts = verts % fine if periodic else verts
        node_keys.append(np.ravel_multi_index(tuple(verts.T), tuple(lattice)))
        node_depth.append(np.full(len(verts), level))
    keys, depth = np.concatenate(node_keys), np.concatenate(node_depth)
    order = np.lexsort((-depth, keys))  # per key, the deepest leaf first
    keys, depth = keys[order], depth[order]
    first = np.r_[True, keys[1:] != keys[:-1]]
    keys, depth = keys[first], depth[first]
    ints = np.stack(np.unravel_index(keys, tuple(lattice)), axis=-1)
    points = ints * box / fine  # k * L / N: x = 0 exactly on the lower faces
    removed = 0
    if interface_phi is not None and removal_fraction > 0:
        phi = _sampler(interface_phi, box, "interface_phi")(points)
        corner = np.all((ints == 0) | (ints == fine), axis=1)
        keep = (np.abs(phi) >= removal_fraction * h_fn(points)) | corner
        removed = int((~keep).sum())
        points, ints, depth = points[keep], ints[keep], depth[keep]
    canonical = np.arange(len(points))
    pairs: dict[int, np.ndarray] = {}
    if periodic:
        for axis in range(d):  # copy every lower-face node (earlier copies included) to the upper face
            low = np.nonzero(ints[:, axis] == 0)[0]
            up_pts, up_ints = points[low].copy(), ints[low].copy()
            up_pts[:, axis] = points[low, axis] + box[axis]  # 0 + L: exact
            up_ints[:, axis] = fine[axis]
            points, ints = np.concatenate([points, up_pts]), np.concatenate([ints, up_ints])
            depth, canonical = np.concatenate([depth, depth[low]]), np.concatenate([canonical, canonical[low]])
        keys = np.ravel_multi_index(tuple(ints.T), tuple(fine + 1))
        order = np.argsort(keys)
        for axis in range(d):
            low = np.nonzero(ints[:, axis] == 0)[0]
            partner = ints[low].copy()
            partner[:, axis] = fine[axis]
            pos = np.searchsorted(keys[order], np.ravel_multi_index(tuple(partner.T), tuple(fine + 1)))
            pairs[axis] = np.stack([low, order[pos]], axis=1)
    return OctreeNodes(points, depth, canonical, pairs, np.concatenate(origins), np.concatenate(sizes),
                       np.concatenate(depths), tuple(float(b) for b in box), periodic, removed)
