"""Box faces (paper 4.5) and the merge into one SurfaceMesh; the public entry point ``mesh_surfaces``.

The master faces x_a = 0 are meshed as 2D problems whose constrained segments are the inclusion
traces and the box edges (the 2D mesher's constrained Delaunay, truss relaxation and flips), then
copied to x_a = L by translation. Nodes are merged exactly by construction: every node is
registered by its exact coordinates, and periodic copies are built as exact translates.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ._contours import edge_parameters
from ._errors import MeshingError
from ._intersect import intersecting_pairs
from ._octree import periodic_octree_nodes
from ._periodic import wrap
from ._surface import SurfaceConfig, as_size_fn, evaluate_size, mesh_inclusion
from ._surface_mesh import BOX_FACE, INTERFACE, OUTSIDE, SurfaceMesh
from ._triangulate2d import (
    SegmentRecoveryError,
    circumcenters,
    component_labels,
    constrained_delaunay,
    distance_to_segments,
    flood_fill,
    improve_by_flips,
    missing_segments,
    smooth_free_nodes,
    triangle_angles,
)
from ._truss import make_constraints, relax
from ._truss._topology import pad_nodes_to_bucket
from .geometry._grid import interpolate_linear


class _Registry:
    """Nodes keyed by their exact coordinates: equal coordinates are one node."""

    def __init__(self):
        self.index: dict[tuple, int] = {}
        self.points: list = []
        self.inclusion: list = []

    def add(self, pts: np.ndarray, inclusion: int = 0) -> np.ndarray:
        ids = np.empty(len(pts), np.int64)
        for k, p in enumerate(np.asarray(pts, float).tolist()):
            key = tuple(p)
            i = self.index.get(key)
            if i is None:
                i = self.index[key] = len(self.points)
                self.points.append(p)
                self.inclusion.append(inclusion)
            ids[k] = i
        return ids

    def lookup(self, pts: np.ndarray) -> np.ndarray:
        return np.array([self.index.get(tuple(p), -1) for p in np.asarray(pts, float).tolist()], np.int64)

    def array(self) -> np.ndarray:
        return np.asarray(self.points, float).reshape(-1, 3)


class FaceSize(eqx.Module):
    """A 3D size function restricted to the face x_axis = 0, as a function of the in-plane (b, c),
    capped by the spacing of the fixed nodes (traces, box edges) grown at a gradient: next to a
    trace whose nodes are closer than h, the face triangles match the trace instead of fanning out.
    The cap is sampled on a periodic grid of the face (a dense node-to-point distance matrix does
    not fit in memory for RVEs with thousands of trace nodes)."""

    h_fn: object
    cap: jax.Array  # (nb, nc) node-centred periodic samples of the cap over the face
    plane: jax.Array  # the face's x_axis (0, or L on a non-periodic box)
    box2: tuple = eqx.field(static=True)
    frame: jax.Array  # (3, 3) unit rows e_axis, e_b, e_c: traced, so the faces share a compilation

    def __call__(self, uv):
        # exact: each coordinate is one term times 1 plus zeros
        p = self.plane * self.frame[0] + uv[:, :1] * self.frame[1] + uv[:, 1:] * self.frame[2]
        h = jnp.reshape(self.h_fn(p.astype(uv.dtype)), uv.shape[:1])
        return jnp.minimum(h, interpolate_linear(self.cap.astype(uv.dtype), self.box2, uv))


def node_spacing(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(n,) length of the shortest segment at each node (inf where none): a face triangle on a
    short trace segment must be about as small, or its angle there closes."""
    length = np.linalg.norm(points[segments[:, 0]] - points[segments[:, 1]], axis=1)
    out = np.full(len(points), np.inf)
    np.minimum.at(out, segments.reshape(-1), np.repeat(length, 2))
    return out


def feature_spacing(points: np.ndarray, segments: np.ndarray, box) -> np.ndarray:
    """node_spacing, also capped by the distance from the node to the box planes it is not on
    (down to half the node spacing): a trace passing a fraction of h from a box edge needs box-edge
    nodes about as close. Thinner lenses between a trace and a box edge are features below h that
    the fixed trace nodes cannot resolve; refining the box edge further only makes more needles."""
    L = np.asarray(box, float)
    gap = np.minimum(points, L - points)
    gap = np.where(gap > 0, gap, np.inf).min(axis=1)
    spacing = node_spacing(points, segments)
    return np.minimum(spacing, np.maximum(gap, 0.5 * spacing))


def _face_size(h_fn, axis: int, plane: float, uv: np.ndarray, spacing: np.ndarray, grad: float, box2) -> FaceSize:
    """FaceSize with the cap min_j (spacing_j + grad |x - x_j|) sampled at half the finest spacing
    (at most 1024 samples per side); the k nearest nodes stand in for all of them."""
    keep = np.isfinite(spacing)
    uv, spacing = uv[keep], spacing[keep]
    box2 = tuple(float(v) for v in box2)
    finest = float(spacing.min()) if len(spacing) else max(box2)
    n = [int(np.clip(np.ceil(2 * L / finest), 8, 1024)) for L in box2]
    grid = np.stack(np.meshgrid(*[np.arange(k) * L / k for k, L in zip(n, box2)], indexing="ij"), -1).reshape(-1, 2)
    cap = _spacing_cap(cKDTree(uv), spacing, grad, grid).reshape(n) if len(uv) else np.full(n, np.inf)
    frame = np.eye(3)[[axis, (axis + 1) % 3, (axis + 2) % 3]]
    return FaceSize(h_fn, jnp.asarray(np.minimum(cap, 1e6)), jnp.asarray(float(plane)), box2, jnp.asarray(frame))


def _spacing_cap(tree: cKDTree, spacing: np.ndarray, grad: float, points: np.ndarray) -> np.ndarray:
    """(m,) min over the 8 nearest tree nodes j of spacing_j + grad |x - x_j|."""
    k = min(8, tree.n)
    d, j = tree.query(points, k=k)
    return np.min(np.reshape(spacing[j] + grad * d, (len(points), k)), axis=1)


def trace_spacing(P: np.ndarray, iface_tris: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Trace nodes (interface nodes on a box plane) and their feature_spacing."""
    L = np.asarray(box, float)
    e = np.concatenate([iface_tris[:, [0, 1]], iface_tris[:, [1, 2]], iface_tris[:, [2, 0]]])
    pu, pv = P[e[:, 0]], P[e[:, 1]]
    same = ((pu == 0.0) & (pv == 0.0)) | ((pu == L) & (pv == L))
    seg = e[same.any(axis=1)]
    sp = feature_spacing(P, seg, box)  # inf off the traces
    nodes = np.flatnonzero(np.isfinite(sp))
    return nodes, sp[nodes]


def _line_size(h_fn, box, nodes: np.ndarray, spacing: np.ndarray, grad: float, periodic: bool = True):
    """NumPy size along the box edges: h capped by the trace spacing grown at rate grad, with
    periodic distances when periodic (the four parallel edges are one edge); the 8 nearest trace
    nodes decide."""
    L = np.asarray(box, float)

    def wrapped(x):
        if not periodic:
            return x
        w = wrap(x, L)
        return np.where(w >= L, 0.0, w)  # rounding can give L; cKDTree's periodic box is half-open

    tree = cKDTree(wrapped(nodes), boxsize=L if periodic else None) if len(nodes) else None

    def size(p):
        h = evaluate_size(h_fn, p)
        return h if tree is None else np.minimum(h, _spacing_cap(tree, spacing, grad, wrapped(p)))

    return size


def _edge_values(P: np.ndarray, axis: int, box, size, at: dict | None = None) -> np.ndarray:
    """Sorted coordinates of the nodes of a box edge along ``axis``: 0, L, the interface crossings,
    and nodes ~size apart between them (size: NumPy (m, 3) -> (m,)). at: {other axis: 0 or L} picks
    one of the four parallel edges (not periodic); None: the master edge, crossed where any of the
    four is (periodic: they are one edge)."""
    L = np.asarray(box, float)
    on = np.ones(len(P), bool)
    for k in (k for k in range(3) if k != axis):
        on &= (P[:, k] == 0.0) | (P[:, k] == L[k]) if at is None else (P[:, k] == at[k])
    breaks = np.unique(np.concatenate([[0.0, L[axis]], P[on, axis]]))

    def line_point(t):
        q = np.zeros((len(t), 3))
        q[:, axis] = t
        for k, v in (at or {}).items():
            q[:, k] = v
        return q

    return edge_parameters(breaks, line_point, size)


def _interior_nodes(uv_fixed, seg, h2, box2, clearance: float, periodic: bool = True) -> np.ndarray:
    """Face interior nodes: the vertices of a (periodic) quadtree refined to h2 (paper 4.3), less
    those closer than clearance * h to a constrained segment or 0.8 h to a fixed node."""
    h_np = lambda q: evaluate_size(h2, q)  # noqa: E731
    nodes = periodic_octree_nodes(h_np, box2, periodic=periodic).points
    nodes = nodes[np.all(nodes < np.asarray(box2), axis=1)]  # the upper-border copies are fixed nodes
    if len(nodes) == 0:
        return nodes
    hc = h_np(nodes)
    # square quadtree cells put four nodes on a circle: where h is uniform the relaxation keeps
    # them there and the face triangulation (and the 3D Delaunay on it) is ambiguous
    jitter = np.random.default_rng(len(nodes)).uniform(-0.15, 0.15, nodes.shape) * hc[:, None]
    nodes = np.clip(nodes + jitter, 0.0, np.asarray(box2) * (1 - 1e-9))
    hmin = float(hc.min())
    ok = distance_to_segments(nodes, uv_fixed, seg, 0.1 * hmin) > clearance * hc
    ok &= cKDTree(uv_fixed).query(nodes)[0] > 0.8 * hc
    return nodes[ok]


def _encroached(pts: np.ndarray, nodes: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """(m,) bool: points inside the diametral circle of a segment."""
    a, b = nodes[seg[:, 0]], nodes[seg[:, 1]]
    mid, rad = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
    out = np.zeros(len(pts), bool)
    for i, hit in enumerate(cKDTree(mid).query_ball_point(pts, float(rad.max()) * (1 + 1e-9))):
        out[i] = any(np.linalg.norm(pts[i] - mid[s]) < rad[s] for s in hit)
    return out


def _refine_face(uv, tri, seg, nf: int, h2, box2, min_angle: float, rounds: int = 6):
    """Delaunay refinement of a face: circumcentres of triangles below min_angle are inserted where
    they stay in the box, do not encroach a constrained segment (the traces are fixed here: they
    cannot be split) and keep 0.3 h from every node; then flips and a smoothing of the free nodes."""
    box = np.asarray(box2, float)
    for _ in range(rounds):
        bad = np.flatnonzero(triangle_angles(uv, tri).min(axis=1) < min_angle)
        if bad.size == 0:
            break
        cc = circumcenters(uv[tri[bad]])
        cc = cc[np.all((cc > 0) & (cc < box), axis=1)]
        if len(cc):
            hc = evaluate_size(h2, cc)
            d, _ = cKDTree(uv).query(cc)
            ok = (d > 0.3 * hc) & ~_encroached(cc, uv[:nf], seg)
            cc, hc = cc[ok], hc[ok]
        keep = []
        for i in range(len(cc)):  # one node per cluster of nearby circumcentres
            if all(np.linalg.norm(cc[i] - cc[j]) > 0.5 * hc[i] for j in keep):
                keep.append(i)
        if not keep:
            break
        uv = np.vstack([uv, cc[keep]])
        tri, _ = improve_by_flips(uv, constrained_delaunay(uv, seg), seg)
        uv = smooth_free_nodes(uv, tri, nf)
        tri, _ = improve_by_flips(uv, tri, seg)
    return uv, tri


def _mesh_face(axis, reg: _Registry, iface_tris: np.ndarray, edge_vals, ms, h_fn, config: SurfaceConfig,
               side: float = 0.0):
    """Mesh the face x_axis = side (not periodic), or the master face x_axis = 0 and its copy at L
    (periodic). edge_vals(line_axis, at): node coordinates of the box edge along line_axis at
    {axis: value}. Returns (triangles (m, 3), sides (m, 2))."""
    periodic = ms.periodic
    L = np.asarray(ms.box, float)
    a, b, c = axis, (axis + 1) % 3, (axis + 2) % 3
    # box edges of the face: lines along c at x_b in {0, L_b}, lines along b at x_c in {0, L_c}
    for line_axis, other in ((c, b), (b, c)):
        for v in (0.0, L[other]):
            vals = edge_vals(line_axis, {a: side, other: v})
            q = np.zeros((len(vals), 3))
            q[:, line_axis], q[:, other], q[:, a] = vals, v, side
            reg.add(q)
            if periodic:
                q[:, a] = L[a]
                reg.add(q)
    P = reg.array()
    face = np.flatnonzero(P[:, a] == side)
    local = -np.ones(len(P), np.int64)
    local[face] = np.arange(len(face))
    segs = []
    for line_axis, other in ((c, b), (b, c)):
        for v in (0.0, L[other]):
            on = face[P[face, other] == v]
            on = on[np.argsort(P[on, line_axis])]
            segs.append(np.stack([on[:-1], on[1:]], axis=1))
    # trace segments: interface edges on the face, and (periodic) those on x_a = L moved to their 0-copy
    e = np.concatenate([iface_tris[:, [0, 1]], iface_tris[:, [1, 2]], iface_tris[:, [2, 0]]])
    for plane in ((0.0, L[a]) if periodic else (side,)):
        m = (P[e[:, 0], a] == plane) & (P[e[:, 1], a] == plane)
        s = e[m]
        if plane != side:
            q = P[s.reshape(-1)].copy()
            q[:, a] = side
            s = reg.lookup(q).reshape(-1, 2)
            if (s < 0).any():
                raise MeshingError("faces", f"face {axis}: a trace on x_{axis} = L has no translate on x_{axis} = 0")
        segs.append(s)
    seg = local[np.vstack(segs)]
    seg = np.unique(np.sort(seg, axis=1), axis=0)
    seg = seg[seg[:, 0] != seg[:, 1]]
    uv_fixed = P[face][:, [b, c]]
    box2 = (L[b], L[c])
    h2 = _face_size(h_fn, axis, side, uv_fixed, feature_spacing(uv_fixed, seg, box2), config.trace_grading, box2)
    lat = _interior_nodes(uv_fixed, seg, h2, box2, config.face_clearance, periodic)
    uv = np.vstack([uv_fixed, lat])
    nf = len(uv_fixed)
    tri_fn = lambda p: constrained_delaunay(p, seg)  # noqa: E731
    if len(lat):
        # padded with fixed copies of a node to a capacity bucket: faces of similar size share a compilation
        n = len(uv)
        padded, cap = pad_nodes_to_bucket(uv)
        cons = make_constraints(cap, 2, fixed=np.concatenate([np.arange(nf), np.arange(n, cap)]))
        truss = config.face_truss
        for cfg in (truss, dataclasses.replace(truss, dt=truss.dt * truss.dt_retry_factor)):
            try:
                res = relax(padded, lambda p: tri_fn(p[:n]), h2, cons, config=cfg, box=box2)
            except MeshingError:  # a free node stepped onto a trace: back off, finally keep the lattice
                continue
            uv = np.array(res.points)[:n]
            uv[:nf] = uv_fixed
            break
    try:
        tri = tri_fn(uv)
        tri, _ = improve_by_flips(uv, tri, seg)
        uv, tri = _refine_face(uv, tri, seg, nf, h2, box2, config.face_min_angle)
    except SegmentRecoveryError as err:  # traces that cross or fold: say whose and where
        raise _trace_error(axis, face[list(err.segment)], reg, P, ms, h_fn, 1) from None
    lat = uv[nf:]
    missing = missing_segments(tri, seg, len(uv))
    if missing.any():
        raise _trace_error(axis, face[seg[missing].ravel()], reg, P, ms, h_fn, int(missing.sum()))
    ncomp, comp = flood_fill(tri, seg, len(uv))
    cen = uv[tri].mean(axis=1)
    c3 = np.full((len(tri), 3), side)
    c3[:, b], c3[:, c] = cen[:, 0], cen[:, 1]
    labels, _ = component_labels(comp, ms.label(c3), n_components=ncomp)
    region = labels[comp]
    # 3D nodes: the fixed ones exist; interior ones are new (on both faces when periodic)
    q0 = np.full((len(lat), 3), side)
    q0[:, b], q0[:, c] = uv[nf:, 0], uv[nf:, 1]
    ids0 = np.concatenate([face, reg.add(q0)])
    # CCW in (b, c) is +e_a: reverse at x_a = 0 so that the normal leaves the box
    sides = np.stack([region, np.full(len(tri), OUTSIDE)], axis=1)
    if not periodic:
        return (ids0[tri][:, ::-1] if side == 0.0 else ids0[tri]), sides
    q1 = q0.copy()
    q1[:, a] = L[a]
    q = P[face].copy()
    q[:, a] = L[a]
    ids1 = np.concatenate([reg.lookup(q), reg.add(q1)])
    if (ids1 < 0).any():
        raise MeshingError("faces", f"face {axis}: a node of x_{axis} = 0 has no translate on x_{axis} = L")
    return np.vstack([ids0[tri][:, ::-1], ids1[tri]]), np.vstack([sides, sides])


class _TraceError(MeshingError):
    """A trace that the face triangulation cannot hold, with the ids of the inclusions it belongs to."""

    def __init__(self, message: str, inclusions: tuple[int, ...]):
        super().__init__("faces", message, inclusions[0] if len(inclusions) == 1 else None)
        self.inclusions = inclusions


def _trace_error(axis: int, ends: np.ndarray, reg: _Registry, P: np.ndarray, ms, h_fn, count: int) -> _TraceError:
    """The error for trace segments (node ids `ends`, all trace nodes) that the face triangulation
    cannot hold: it names the inclusions and the place, and what resolves it there."""
    ids = sorted({int(reg.inclusion[i]) for i in ends} - {0})
    x = tuple(round(float(v), 4) for v in P[ends[0]])
    whose = f"inclusions {ids}" if len(ids) > 1 else "the inclusion" if ids else "an inclusion"
    h_here = float(evaluate_size(h_fn, P[ends[:1]])[0])
    step = float(np.min(np.asarray(ms.box, float) / np.asarray(ms.grid_shape)))
    if h_here < step:  # a finer mesh cannot separate traces that pinch below the field's resolution
        shift = ("--roll auto, or the field rolled by a few samples (numpy.roll)" if ms.periodic else
                 "one grid layer more or less at that face, the box length changed to match")
        cause = (f"they meet closer than the mesh there separates, and it is already finer (h = {h_here:.2g}) than "
                 f"the grid step ({step:.2g}): a feature below the grid's resolution, such as a saddle of the field "
                 "on the box plane, which a smaller iis will not resolve")
        remedy = f"smooth the field there, or move the box plane off the place ({shift})"
    else:
        cause = ("an inclusion surface folds, or crosses the box plane at a saddle, where the mesh size exceeds "
                 "its features")
        remedy = ("a smaller iis / h_max, a smoother field, or the periodic field shifted by a few grid steps "
                  "(numpy.roll) so that the box planes cut it elsewhere" if ms.periodic else
                  "a smaller iis / h_max or a smoother field")
    return _TraceError(f"face {axis}: a trace of {whose} near x = {x} loses {count} segment(s) in the face "
                       f"triangulation (interface traces cross or touch: {cause}). Hint: {remedy}.", tuple(ids))


def _periodic_pairs(reg: _Registry, box) -> dict[int, np.ndarray]:
    P = reg.array()
    out = {}
    for a in range(3):
        lo = np.flatnonzero(P[:, a] == 0.0)
        q = P[lo].copy()
        q[:, a] = box[a]
        hi = reg.lookup(q)
        if (hi < 0).any():
            raise MeshingError("merge", f"{int((hi < 0).sum())} nodes on x_{a} = 0 have no translate on x_{a} = L")
        out[a] = np.stack([lo, hi], axis=1)
    return out


_FLAT_SLOPE = 0.5  # |grad phi| below this at an intersection: blame the field's saddle, not thinness
_RESAMPLE_SCALES = (0.8, 1.25)  # marching-cubes steps (x the default) tried on inclusions whose triangles cross


def _assemble(microstructure, surfaces: dict, h_fn, config: SurfaceConfig, t0: float) -> SurfaceMesh:
    """The inclusion surfaces (id -> mesh_inclusion output) registered into one node set, plus the
    box faces meshed against their traces."""
    box, periodic = microstructure.box, microstructure.periodic
    reg = _Registry()
    tris, sides, kinds = [], [], []
    for inc in microstructure.inclusions:
        out = surfaces[inc.id]
        t = reg.add(out["points"], inc.id)[out["triangles"]]
        # pieces cut at a box edge can share a point: (a, a, b) has zero area, and dropping it
        # leaves the edge a-b in its two neighbours
        t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])]
        tris.append(t)
        sides.append(np.tile([inc.id, 0], (len(t), 1)))
        kinds.append(np.full(len(t), INTERFACE))
    t1 = time.perf_counter()
    iface = np.vstack(tris) if tris else np.zeros((0, 3), np.int64)
    P = reg.array()
    tnodes, tsp = trace_spacing(P, iface, box)
    line_size = _line_size(h_fn, box, P[tnodes], tsp, config.trace_grading, periodic)
    # every box edge from the interface nodes alone, before any face adds nodes to it
    if periodic:
        masters = [_edge_values(P, a, box, line_size) for a in range(3)]
        edge_vals = lambda line_axis, at: masters[line_axis]  # noqa: E731
    else:
        L = np.asarray(box, float)
        edges = {}
        for a in range(3):
            o1, o2 = (k for k in range(3) if k != a)
            for v1 in (0.0, L[o1]):
                for v2 in (0.0, L[o2]):
                    edges[a, v1, v2] = _edge_values(P, a, box, line_size, {o1: v1, o2: v2})
        edge_vals = lambda line_axis, at: edges[(line_axis, *(at[k] for k in sorted(at)))]  # noqa: E731
    for a in range(3):
        for side in ((0.0,) if periodic else (0.0, float(box[a]))):
            ft, fs = _mesh_face(a, reg, iface, edge_vals, microstructure, h_fn, config, side)
            tris.append(ft)
            sides.append(fs)
            kinds.append(np.full(len(ft), BOX_FACE))
    t2 = time.perf_counter()
    mesh = SurfaceMesh(
        points=reg.array(), triangles=np.vstack(tris), sides=np.vstack(sides), kind=np.concatenate(kinds),
        node_inclusion=np.asarray(reg.inclusion, np.int64), box=box,
        periodic_pairs=_periodic_pairs(reg, box) if periodic else {},
        metadata={"n_inclusions": len(microstructure.inclusions), "time_interfaces": t1 - t0, "time_faces": t2 - t1},
        periodic=periodic,
    )
    return mesh


def _raise_intersections(microstructure, mesh: SurfaceMesh, bad: np.ndarray, resampled: dict):
    ids = np.unique(mesh.sides[bad.reshape(-1)])
    x = tuple(round(float(v), 4) for v in mesh.points[mesh.triangles[bad[0]]].reshape(-1, 3).mean(axis=0))
    slope = _gradient_norm(microstructure, np.asarray(x))
    cause = ("seen where an inclusion is thinner than about a grid step (a membrane or a filament of the "
             "field); hint: sample the field finer or smooth it, or a smaller iis / h_max")
    if slope < _FLAT_SLOPE:
        cause = (f"the level set is nearly flat there (|grad phi| = {slope:.2g}; a distance has 1): a saddle "
                 "of the field close to zero, two lobes about to merge or a neck about to pinch, whose zero "
                 "set the grid does not pin down; hint: --redistance (MeshConfig(redistance=True)) makes the "
                 "field a distance to its zero set first; or smooth the field, or move its threshold off "
                 "the saddle")
    tried = (f" (inclusions {sorted(resampled)} also resampled at {list(_RESAMPLE_SCALES)} of the marching-cubes "
             "step)" if resampled else "")
    raise MeshingError("surfaces", f"{len(bad)} intersecting triangle pairs (regions {ids.tolist()}), the "
                       f"first near x = {x}{tried}; {cause}", frame_dependent=slope >= _FLAT_SLOPE,
                       redistance_helps=slope < _FLAT_SLOPE)


def _gradient_norm(microstructure, x: np.ndarray) -> float:
    """|grad phi| of the microstructure's level set at x, by central differences of a tenth of a step."""
    d = 0.1 * float(np.min(microstructure.spacing))
    probes = x[None] + d * np.vstack([np.eye(3), -np.eye(3)])
    values = np.asarray(microstructure.phi(probes), float)
    return float(np.linalg.norm((values[:3] - values[3:]) / (2 * d)))


def _resample(microstructure, surfaces: dict, ids, scale: float, h_fn, config: SurfaceConfig, resampled: dict):
    """Mesh the inclusions `ids` again at `scale` times the marching-cubes step, in `surfaces`: the
    sampling decides how a surface passes a saddle of the field near zero, and another one often
    passes clean (its triangles no longer cross or fold, its traces no longer touch on a box face)."""
    resampling = dataclasses.replace(config, mc_step=config.mc_step * scale)
    for inc in microstructure.inclusions:
        if inc.id in ids:
            try:
                surfaces[inc.id] = mesh_inclusion(inc, h_fn, microstructure.box, resampling, microstructure.periodic)
            except MeshingError:
                pass  # that sampling fails otherwise: keep the last surface, try the next one
    resampled.update({int(i): scale for i in ids})


def _assemble_resampling(microstructure, surfaces: dict, h_fn, config: SurfaceConfig, t0: float,
                         resampled: dict) -> SurfaceMesh:
    """_assemble, with the inclusions of a trace that a box face cannot hold sampled again (at each of
    _RESAMPLE_SCALES) before the error stands; it names the place where the first sampling failed."""
    tried, first = [], None
    for scale in (*_RESAMPLE_SCALES, None):
        try:
            return _assemble(microstructure, surfaces, h_fn, config, t0)
        except _TraceError as err:
            first = first or err
            if scale is None or not err.inclusions:
                if not tried:
                    raise
                raise MeshingError("faces", f"{first.message} (inclusions {sorted(set(tried))} also resampled at "
                                   f"{list(_RESAMPLE_SCALES)} of the marching-cubes step)", first.inclusion) from None
            tried += err.inclusions
            _resample(microstructure, surfaces, err.inclusions, scale, h_fn, config, resampled)


def mesh_surfaces(microstructure, h, *, config: SurfaceConfig = SurfaceConfig()) -> SurfaceMesh:
    """Closed surface mesh of a 3D RVE: inclusion interfaces cut by the box plus box faces.

    Periodic microstructure: the pieces outside the box wrap into it, the master faces are meshed
    once and copied, and the result has periodic pairs. Not periodic: the pieces outside are
    dropped and each of the six faces (and twelve edges) is meshed on its own.

    Args:
        microstructure: a 3D Microstructure (geometry.Microstructure), periodic or not.
        h: target edge length, a float > 0 or a JAX size callable points (m, 3) -> (m,) (e.g. a SizeField).
        config: SurfaceConfig (the face nodes are deterministic: no seed).
    Returns:
        SurfaceMesh: interface triangles sides (k, 0), box-face triangles (region, OUTSIDE), periodic pairs.
    Raises:
        ValueError: bad input. MeshingError: a stage failed (names the stage / inclusion).

    Example:
        >>> ms = Microstructure.from_functions([sphere_sdf(c, 0.2)], (1, 1, 1), (32, 32, 32))
        >>> surf = mesh_surfaces(ms, 0.05)
    """
    if not (hasattr(microstructure, "inclusions") and hasattr(microstructure, "box")):
        raise ValueError(f"microstructure: expected a jaxmesh Microstructure, got {type(microstructure).__name__}. "
                         "Hint: Microstructure.from_functions / from_levelset.")
    if microstructure.dim != 3:
        raise ValueError(f"mesh_surfaces expected a 3D microstructure, got dim={microstructure.dim}. "
                         "Hint: mesh_2d handles 2D.")
    if not isinstance(config, SurfaceConfig):
        raise ValueError(f"config: expected SurfaceConfig, got {type(config).__name__}.")
    box, periodic = microstructure.box, microstructure.periodic
    h_fn = as_size_fn(h, box, periodic)
    t0 = time.perf_counter()
    surfaces = {inc.id: mesh_inclusion(inc, h_fn, box, config, periodic) for inc in microstructure.inclusions}
    resampled, fewest = {}, None
    mesh = _assemble_resampling(microstructure, surfaces, h_fn, config, t0, resampled)
    for scale in (*_RESAMPLE_SCALES, None):
        crossing = np.zeros(0, np.int64)
        if config.check_intersections:
            t2 = time.perf_counter()
            bad = intersecting_pairs(mesh.points, mesh.triangles)
            mesh.metadata["time_intersections"] = time.perf_counter() - t2
            if len(bad):
                if fewest is None or len(bad) < len(fewest[1]):
                    fewest = (mesh, bad)
                crossing = np.unique(mesh.sides[bad.reshape(-1)][mesh.kind[bad.reshape(-1)] == INTERFACE, 0])
                if scale is None or not len(crossing):
                    _raise_intersections(microstructure, *fewest, resampled)  # where the field is worst resolved
        folding = [i for i, out in surfaces.items() if out["folds"]]
        if scale is None or not (len(crossing) or folding):
            break  # folds that no sampling removes are left to the volume stage's recovery
        _resample(microstructure, surfaces, np.union1d(crossing, folding), scale, h_fn, config, resampled)
        mesh = _assemble_resampling(microstructure, surfaces, h_fn, config, t0, resampled)
    mesh.metadata["folded_inclusions"] = sorted(int(i) for i in folding)  # the loop leaves by its break
    mesh.metadata["resampled_inclusions"] = resampled
    mesh.metadata["n_self_intersections"] = 0 if config.check_intersections else None
    return mesh
