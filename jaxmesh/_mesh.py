"""The mesh result type, periodic node pairs, boundary node sets and facet tables (NumPy only)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

AXES = "xyz"
CELL_TYPES = {2: "triangle", 3: "tetra"}
FACET_TYPES = {2: "line", 3: "triangle"}
# Local facets of a simplex, facet i opposite vertex i, ordered so that the facet normal
# points out of a positively oriented cell.
LOCAL_FACETS = {
    2: np.array([[1, 2], [2, 0], [0, 1]]),
    3: np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]),
}


def face_names(dim: int) -> list[str]:
    """Box face names in the order face index = 2 * axis + side: xmin, xmax, ymin, ..."""
    return [f"{AXES[a]}{s}" for a in range(dim) for s in ("min", "max")]


def box_features(dim: int) -> list[tuple[tuple[int, int], ...]]:
    """Every box face/edge/corner as a tuple of (axis, side) constraints, side 0 = min, 1 = max.

    Ordered by number of constraints (faces first, corners last), then lexicographically.
    """
    out = []
    for k in range(1, dim + 1):
        for axes in itertools.combinations(range(dim), k):
            for sides in itertools.product((0, 1), repeat=k):
                out.append(tuple(zip(axes, sides)))
    return out


def feature_name(feature) -> str:
    """'xmin', 'xmin_ymax', 'xmin_ymin_zmin', ... for a tuple of (axis, side) constraints."""
    return "_".join(f"{AXES[a]}{'max' if s else 'min'}" for a, s in feature)


def _check_box(box, dim: int) -> np.ndarray:
    box = np.asarray(box, dtype=float).reshape(-1)
    if box.shape != (dim,) or not np.all(np.isfinite(box)) or np.any(box <= 0):
        raise ValueError(
            f"box must hold {dim} positive lengths (one per axis of the points), got {box.tolist()}; "
            "hint: box=(1.0,) * dim for the unit cell"
        )
    return box


def on_box_planes(points: np.ndarray, box, tol: float = 1e-9) -> np.ndarray:
    """(n, d, 2) bool: point lies on the min ([..., 0]) / max ([..., 1]) plane of each axis.

    The tolerance is relative: |x_a - side * L_a| <= tol * L_a.
    """
    points = np.asarray(points, dtype=float)
    box = _check_box(box, points.shape[1])
    atol = tol * box
    return np.stack([np.abs(points) <= atol, np.abs(points - box) <= atol], axis=-1)


def match_periodic_nodes(points, box, tol: float = 1e-9) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Match nodes on x_a = 0 with nodes on x_a = L_a by translation, tolerating failures.

    Args:
        points: (n, d) coordinates; box: (d,) lengths; tol: relative tolerance (times L).
    Returns:
        {axis: (pairs (k, 2) int64 (min-face node, max-face node), unmatched min-face nodes,
        unmatched max-face nodes)}.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"points must be (n, 2) or (n, 3), got shape {points.shape}")
    box = _check_box(box, points.shape[1])
    on = on_box_planes(points, box, tol)
    match_tol = tol * float(box.max())
    out = {}
    for a in range(points.shape[1]):
        lo, hi = np.flatnonzero(on[:, a, 0]), np.flatnonzero(on[:, a, 1])
        if len(lo) == 0 or len(hi) == 0:
            out[a] = (np.zeros((0, 2), dtype=np.int64), lo, hi)
            continue
        shifted = points[lo].copy()
        shifted[:, a] += box[a]
        dist, idx = cKDTree(points[hi]).query(shifted, distance_upper_bound=2 * match_tol + 1e-300)
        ok = np.isfinite(dist) & (dist <= match_tol)
        pairs = np.stack([lo[ok], hi[idx[ok]]], axis=1).astype(np.int64)
        # A max-face node claimed twice is matched once only: the rest count as unmatched.
        _, first = np.unique(pairs[:, 1], return_index=True)
        dup = np.setdiff1d(np.arange(len(pairs)), first)
        lo_bad = np.concatenate([lo[~ok], pairs[dup, 0]])
        pairs = pairs[np.sort(first)]
        hi_bad = np.setdiff1d(hi, pairs[:, 1])
        out[a] = (pairs, np.sort(lo_bad), hi_bad)
    return out


def make_periodic_pairs(points, box, tol: float = 1e-9) -> dict[int, np.ndarray]:
    """Pair every node on a min face x_a = 0 with its translate on x_a = L_a.

    Args:
        points: (n, d) coordinates in [0, L].
        box: (d,) lengths.
        tol: relative tolerance (times the box length) for "on the face" and for matching.
    Returns:
        {axis: (k, 2) int64 array of (node on x_a = 0, node on x_a = L_a)}, sorted by the first column.
    Raises:
        ValueError if a face node has no partner on the opposite face.

    Example: ``pairs = make_periodic_pairs(mesh.points, mesh.box)``.
    """
    points = np.asarray(points, dtype=float)
    matched = match_periodic_nodes(points, box, tol)
    out = {}
    for a, (pairs, lo_bad, hi_bad) in matched.items():
        if len(lo_bad) or len(hi_bad):
            bad = lo_bad[0] if len(lo_bad) else hi_bad[0]
            raise ValueError(
                f"axis {AXES[a]}: {len(lo_bad)} nodes on {AXES[a]}=0 and {len(hi_bad)} on "
                f"{AXES[a]}=L have no translated partner (e.g. node {bad} at "
                f"{points[bad].tolist()}); hint: the opposite face triangulations must be "
                "translates of each other, or pass periodic=False"
            )
        out[a] = pairs[np.argsort(pairs[:, 0], kind="stable")]
    return out


@dataclass(frozen=True)
class FacetTable:
    """Unique facets (edges in 2D, triangles in 3D) of a simplex mesh.

    facets: (F, d) sorted vertex ids; oriented: (F, d) the first occurrence as an outward facet
    of its cell; counts: (F,) number of cells holding it; cell_facet: (m, d+1) facet index of
    each cell's local facet i (opposite vertex i).
    """

    facets: np.ndarray
    oriented: np.ndarray
    counts: np.ndarray
    cell_facet: np.ndarray

    def owners(self) -> tuple[np.ndarray, np.ndarray]:
        """Cells holding each facet, CSR-style: (cells sorted by facet, offsets (F+1,))."""
        flat = self.cell_facet.ravel()
        order = np.argsort(flat, kind="stable")
        offsets = np.concatenate([[0], np.cumsum(self.counts)])
        return order // self.cell_facet.shape[1], offsets

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(facet ids with exactly two cells, (k, 2) those two cells)."""
        cells, offsets = self.owners()
        two = np.flatnonzero(self.counts == 2)
        return two, np.stack([cells[offsets[two]], cells[offsets[two] + 1]], axis=1)


def facet_table(cells, n_points: int | None = None, *, structured: bool | None = None) -> FacetTable:
    """Deduplicate the facets of (m, d+1) simplices with integer keys (no np.unique(axis=0)).

    Args:
        cells: (m, d+1) vertex ids.
        n_points: number of vertices (default cells.max() + 1).
        structured: force the structured-dtype fallback (True) or the packed int64 key (False);
            default picks the packed key when n_points**d fits in an int64.
    Returns:
        FacetTable.
    """
    cells = np.asarray(cells, dtype=np.int64)
    m, k = cells.shape
    d = k - 1
    n = int(n_points if n_points is not None else (cells.max() + 1 if m else 1))
    oriented_all = cells[:, LOCAL_FACETS[d]].reshape(-1, d)
    srt = np.sort(oriented_all, axis=1)
    if structured is None:
        structured = n**d >= 2**62
    if not structured:
        key = srt[:, 0].copy()
        for j in range(1, d):
            key = key * n + srt[:, j]
    else:
        rec = np.dtype([(f"v{j}", np.int64) for j in range(d)])
        key = np.ascontiguousarray(srt).view(rec).ravel()
    _, first, inverse, counts = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    return FacetTable(
        facets=srt[first],
        oriented=oriented_all[first],
        counts=counts.astype(np.int64),
        cell_facet=inverse.reshape(m, k).astype(np.int64),
    )


def classify_facets(points, facets, box, tol: float = 1e-9) -> np.ndarray:
    """Box face index (2 * axis + side) of facets whose vertices all lie on one box face plane, else -1.

    Args:
        points: (n, d); facets: (F, d) vertex ids; box: (d,); tol: relative plane tolerance.
    Returns:
        (F,) int64.
    """
    on = on_box_planes(points, box, tol)[np.asarray(facets, dtype=np.int64)]  # (F, d, d, 2)
    all_on = on.all(axis=1).reshape(len(on), -1)  # (F, 2d): face index 2a + s
    face = np.argmax(all_on, axis=1)
    return np.where(all_on.any(axis=1), face, -1).astype(np.int64)


@dataclass(eq=False)
class Mesh:
    """A periodic, conforming simplex mesh of a box holding a matrix and inclusions.

    Attributes:
        points: (n, d) float64, d = 2 or 3, in [0, L] with boundary nodes exactly on 0 and L.
        cells: (m, d+1) int64 triangles / tetrahedra, positively oriented.
        inclusion_id: (m,) int64, 0 = matrix, k = inclusion k.
        box: (d,) box lengths.
        periodic: whether opposite faces are translates of each other.
        periodic_pairs: {axis: (k, 2) (node on x_a = 0, its translate on x_a = L_a)}; computed
            by `make_periodic_pairs` when left None on a periodic mesh.
        metadata: parameters, timings, counts.

    Example: ``Mesh(points, cells, np.zeros(len(cells), int), (1.0, 1.0)).write("rve.vtu")``.
    """

    points: np.ndarray
    cells: np.ndarray
    inclusion_id: np.ndarray
    box: tuple[float, ...]
    periodic: bool = True
    periodic_pairs: dict[int, np.ndarray] | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] not in (2, 3) or not np.all(np.isfinite(pts)):
            raise ValueError(
                f"points must be a finite (n, 2) or (n, 3) float array, got shape {pts.shape}; "
                "hint: stack coordinates as rows"
            )
        d = pts.shape[1]
        cells = np.asarray(self.cells)
        if cells.ndim != 2 or cells.shape[1] != d + 1 or not np.issubdtype(cells.dtype, np.integer):
            raise ValueError(
                f"cells must be an integer (m, {d + 1}) array for {d}D points, got shape "
                f"{cells.shape} dtype {cells.dtype}; hint: {CELL_TYPES[d]} vertex ids"
            )
        if cells.size and (cells.min() < 0 or cells.max() >= len(pts)):
            raise ValueError(f"cells refer to vertex ids outside [0, {len(pts)})")
        ids = np.asarray(self.inclusion_id)
        if ids.shape != (len(cells),) or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
            raise ValueError(
                f"inclusion_id must be an integer ({len(cells)},) array, got shape {ids.shape} "
                f"dtype {ids.dtype}; hint: 0 for matrix cells"
            )
        if ids.size and ids.min() < 0:
            raise ValueError(f"inclusion_id must be >= 0 (0 = matrix), got min {ids.min()}")
        self.points = pts
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self.inclusion_id = np.ascontiguousarray(ids, dtype=np.int64)
        self.box = tuple(float(x) for x in _check_box(self.box, d))
        self.periodic = bool(self.periodic)
        if self.periodic_pairs is None:
            self.periodic_pairs = make_periodic_pairs(pts, self.box) if self.periodic else {}
        else:
            pp = {}
            for a, p in dict(self.periodic_pairs).items():
                p = np.asarray(p, dtype=np.int64).reshape(-1, 2)
                if int(a) not in range(d):
                    raise ValueError(f"periodic_pairs keys must be axes 0..{d - 1}, got {a}")
                pp[int(a)] = p
            self.periodic_pairs = pp

    @property
    def dim(self) -> int:
        return int(self.points.shape[1])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cells.shape[0])

    @property
    def phase(self) -> np.ndarray:
        """(m,) int8: 0 = matrix, 1 = any inclusion."""
        return (self.inclusion_id > 0).astype(np.int8)

    def cell_arrays(self) -> dict[str, np.ndarray]:
        """Cell data written with the mesh: inclusion_id, phase, and for a labelled-image input
        (metadata["inclusions"] with labels) label, each cell's label value in the image (0: matrix)."""
        out = {"inclusion_id": self.inclusion_id, "phase": self.phase}
        table = self.metadata.get("inclusions") or []
        if table and all("label" in row for row in table):
            lut = np.zeros(max(int(row["id"]) for row in table) + 1, np.int64)
            lut[[int(row["id"]) for row in table]] = [int(row["label"]) for row in table]
            if self.inclusion_id.size and self.inclusion_id.max() < len(lut):
                out["label"] = lut[self.inclusion_id]
        return out

    def __repr__(self) -> str:
        n_inc = len(np.unique(self.inclusion_id[self.inclusion_id > 0]))
        return (
            f"Mesh(dim={self.dim}, n_points={self.n_points}, n_cells={self.n_cells}, "
            f"inclusions={n_inc}, box={self.box}, periodic={self.periodic})"
        )

    def boundary_nodes(self) -> dict[str, np.ndarray]:
        """Node sets by coordinate (tolerance 1e-9 * L): faces 'xmin', 'xmax', ...; edges
        'xmin_ymin', ... (the sides in 2D); corners 'xmin_ymin' (2D) / 'xmin_ymin_zmin' (3D).

        A face set holds its edge and corner nodes too. Returns {name: sorted int64 ids}.
        """
        on = on_box_planes(self.points, self.box)
        out = {}
        for feat in box_features(self.dim):
            mask = np.ones(self.n_points, dtype=bool)
            for a, s in feat:
                mask &= on[:, a, s]
            out[feature_name(feat)] = np.flatnonzero(mask).astype(np.int64)
        return out

    def facets(self) -> FacetTable:
        """The facet table of the cells (see `facet_table`)."""
        return facet_table(self.cells, self.n_points)

    def interface_nodes(self) -> np.ndarray:
        """Sorted ids of the nodes on an interface: a facet whose two cells have different inclusion ids."""
        table = self.facets()
        two, cells = table.pairs()
        between = two[self.inclusion_id[cells[:, 0]] != self.inclusion_id[cells[:, 1]]]
        return np.unique(table.facets[between])

    def boundary_facets(self) -> dict[str, np.ndarray]:
        """Outward-oriented boundary facets (in one cell) per box face name, {name: (k, d)}."""
        table = self.facets()
        one = table.counts == 1
        face = classify_facets(self.points, table.facets[one], self.box)
        oriented = table.oriented[one]
        return {name: oriented[face == f] for f, name in enumerate(face_names(self.dim))}

    def to_meshio(self):
        """A meshio.Mesh with the `cell_arrays` as cell_data, point_sets = boundary node sets."""
        import meshio

        return meshio.Mesh(
            self.points,
            [(CELL_TYPES[self.dim], self.cells)],
            cell_data={name: [values] for name, values in self.cell_arrays().items()},
            point_sets=self.boundary_nodes(),
        )

    def write(self, path: str | Path, file_format: str | None = None) -> Path:
        """Write the mesh atomically; see `jaxmesh.io._write.write_mesh` for the formats."""
        from .io._write import write_mesh

        return write_mesh(self, path, file_format)


def structured_mesh(divisions, box=None) -> Mesh:
    """A periodic structured simplex mesh of a box, all cells labelled 0 (matrix).

    2D: every grid square split into 2 triangles along the same diagonal; 3D: every cube split
    into the 6 Kuhn tetrahedra around its main diagonal. Both are translation invariant, so
    opposite faces match and the result is periodic.

    Args:
        divisions: (d,) number of grid intervals per axis (>= 1), d = 2 or 3.
        box: (d,) lengths (default unit box).
    Returns:
        Mesh with positively oriented cells.

    Example: ``structured_mesh((8, 8))`` has 128 triangles.
    """
    div = np.asarray(divisions, dtype=np.int64).reshape(-1)
    if div.size not in (2, 3) or np.any(div < 1):
        raise ValueError(f"divisions must be 2 or 3 positive integers, got {div.tolist()}")
    d = div.size
    box = _check_box(np.ones(d) if box is None else box, d)
    axes = [np.linspace(0.0, box[a], div[a] + 1) for a in range(d)]
    grid = np.meshgrid(*axes, indexing="ij")
    points = np.stack([g.ravel() for g in grid], axis=-1)
    shape = tuple(div + 1)
    base = np.stack(np.meshgrid(*[np.arange(n) for n in div], indexing="ij"), -1).reshape(-1, d)
    simplices = []
    for perm in itertools.permutations(range(d)):  # Kuhn: walk the axes in every order
        verts, cur = [base.copy()], base.copy()
        for a in perm:
            cur = cur.copy()
            cur[:, a] += 1
            verts.append(cur)
        simplices.append(np.stack([np.ravel_multi_index(v.T, shape) for v in verts], axis=1))
    cells = np.concatenate(simplices)
    from ._quality import signed_volumes

    neg = signed_volumes(points, cells) < 0
    cells[neg, :2] = cells[neg, 1::-1]
    return Mesh(points, cells, np.zeros(len(cells), dtype=np.int64), tuple(box))
