"""Box faces (paper 4.5) and the merge into one SurfaceMesh; the public entry point ``mesh_surfaces``.

The master faces x_a = 0 are meshed as 2D problems whose constrained segments are the inclusion
traces and the box edges (the 2D mesher's constrained Delaunay, truss relaxation and flips), then
copied to x_a = L by translation. Nodes are merged exactly by construction: every node is
registered by its exact coordinates, and periodic copies are built as exact translates.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._errors import MeshingError
from ._intersect import intersecting_pairs
from ._surface import SurfaceConfig, as_size_fn, mesh_inclusion
from ._surface_mesh import BOX_FACE, INTERFACE, OUTSIDE, SurfaceMesh
from ._triangulate2d import (
    component_labels,
    constrained_delaunay,
    distance_to_segments,
    flood_fill,
    improve_by_flips,
    missing_segments,
)
from ._truss import make_constraints, relax


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
    """A 3D size function restricted to the face x_axis = 0, as a function of the in-plane (b, c)."""

    h_fn: object
    axis: int = eqx.field(static=True)

    def __call__(self, uv):
        a, b, c = self.axis, (self.axis + 1) % 3, (self.axis + 2) % 3
        p = jnp.zeros((uv.shape[0], 3), uv.dtype).at[:, b].set(uv[:, 0]).at[:, c].set(uv[:, 1])
        del a
        return jnp.reshape(self.h_fn(p), uv.shape[:1])


def _edge_values(P: np.ndarray, axis: int, box, h_fn) -> np.ndarray:
    """Sorted coordinates of the nodes of the master box edge along ``axis``: 0, L, the interface
    crossings of the edge lines, and equal subdivisions of size ~h between them."""
    L = np.asarray(box, float)
    o = [k for k in range(3) if k != axis]
    on = np.ones(len(P), bool)
    for k in o:
        on &= (P[:, k] == 0.0) | (P[:, k] == L[k])
    breaks = np.unique(np.concatenate([[0.0, L[axis]], P[on, axis]]))
    vals = [breaks[:1]]
    for lo, hi in zip(breaks[:-1], breaks[1:]):
        mid = np.zeros((1, 3))
        mid[0, axis] = 0.5 * (lo + hi)
        h = float(np.asarray(h_fn(jnp.asarray(mid)))[0])
        m = max(1, int(round((hi - lo) / h)))
        inner = lo + (hi - lo) * np.arange(1, m) / m
        vals += [inner, [hi]]
    return np.concatenate(vals)


def _lattice(box2, h: float) -> np.ndarray:
    """Triangular lattice of spacing h strictly inside [0, Lb] x [0, Lc]."""
    dy = h * np.sqrt(3) / 2
    ys = np.arange(dy / 2, box2[1], dy)
    rows = [np.stack([np.arange((i % 2) * h / 2 + h / 4, box2[0], h), np.full_like(np.arange((i % 2) * h / 2 + h / 4,
            box2[0], h), y)], axis=1) for i, y in enumerate(ys)]  # fmt: skip
    return np.vstack(rows) if rows else np.zeros((0, 2))


def _mesh_face(axis, reg: _Registry, iface_tris: np.ndarray, edge_vals, ms, h_fn, config: SurfaceConfig, rng):
    """Mesh the master face x_axis = 0 and its copy at L; returns (triangles (m, 3), sides (m, 2))."""
    L = np.asarray(ms.box, float)
    a, b, c = axis, (axis + 1) % 3, (axis + 2) % 3
    P = reg.array()
    # box edges of the face: lines along c at x_b in {0, L_b}, lines along b at x_c in {0, L_c}
    for line_axis, other in ((c, b), (b, c)):
        for v in (0.0, L[other]):
            q = np.zeros((len(edge_vals[line_axis]), 3))
            q[:, line_axis], q[:, other] = edge_vals[line_axis], v
            reg.add(q)
            q[:, a] = L[a]
            reg.add(q)
    P = reg.array()
    face = np.flatnonzero(P[:, a] == 0.0)
    local = -np.ones(len(P), np.int64)
    local[face] = np.arange(len(face))
    segs = []
    for line_axis, other in ((c, b), (b, c)):
        for v in (0.0, L[other]):
            on = face[P[face, other] == v]
            on = on[np.argsort(P[on, line_axis])]
            segs.append(np.stack([on[:-1], on[1:]], axis=1))
    # trace segments: interface edges on x_a = 0, and those on x_a = L moved to their 0-copy
    e = np.concatenate([iface_tris[:, [0, 1]], iface_tris[:, [1, 2]], iface_tris[:, [2, 0]]])
    for side in (0.0, L[a]):
        m = (P[e[:, 0], a] == side) & (P[e[:, 1], a] == side)
        s = e[m]
        if side != 0.0:
            q = P[s.reshape(-1)].copy()
            q[:, a] = 0.0
            s = reg.lookup(q).reshape(-1, 2)
            if (s < 0).any():
                raise MeshingError("faces", f"face {axis}: a trace on x_{axis} = L has no translate on x_{axis} = 0")
        segs.append(s)
    seg = local[np.vstack(segs)]
    seg = np.unique(np.sort(seg, axis=1), axis=0)
    seg = seg[seg[:, 0] != seg[:, 1]]
    uv_fixed = P[face][:, [b, c]]
    box2 = (L[b], L[c])
    h2 = FaceSize(h_fn, axis)
    hmin = float(np.min(np.asarray(h2(jnp.asarray(np.vstack([uv_fixed, _lattice(box2, min(box2) / 8)]))))))
    lat = _lattice(box2, hmin)
    if len(lat):
        hl = np.asarray(h2(jnp.asarray(lat)))
        lat = lat[rng.random(len(lat)) < (hmin / hl) ** 2]
        d = distance_to_segments(lat, uv_fixed, seg, 0.1 * hmin)
        lat = lat[d > config.face_clearance * np.asarray(h2(jnp.asarray(lat)))]
    uv = np.vstack([uv_fixed, lat])
    nf = len(uv_fixed)
    tri_fn = lambda p: constrained_delaunay(p, seg)  # noqa: E731
    if len(lat):
        cons = make_constraints(len(uv), 2, fixed=np.arange(nf))
        res = relax(uv, tri_fn, h2, cons, config=config.face_truss, box=box2)
        uv = np.array(res.points)
        uv[:nf] = uv_fixed
    tri = tri_fn(uv)
    tri, _ = improve_by_flips(uv, tri, seg)
    if missing_segments(tri, seg, len(uv)).any():
        raise MeshingError("faces", f"face {axis}: constrained segments missing from the face triangulation")
    ncomp, comp = flood_fill(tri, seg, len(uv))
    cen = uv[tri].mean(axis=1)
    c3 = np.zeros((len(tri), 3))
    c3[:, b], c3[:, c] = cen[:, 0], cen[:, 1]
    labels, _ = component_labels(comp, ms.label(c3), n_components=ncomp)
    region = labels[comp]
    # 3D nodes: the fixed ones exist; interior ones are new on both faces
    q0 = np.zeros((len(lat), 3))
    q0[:, b], q0[:, c] = uv[nf:, 0], uv[nf:, 1]
    q1 = q0.copy()
    q1[:, a] = L[a]
    ids0 = np.concatenate([face, reg.add(q0)])
    q = P[face].copy()
    q[:, a] = L[a]
    ids1 = np.concatenate([reg.lookup(q), reg.add(q1)])
    if (ids1 < 0).any():
        raise MeshingError("faces", f"face {axis}: a node of x_{axis} = 0 has no translate on x_{axis} = L")
    t0 = ids0[tri][:, ::-1]  # CCW in (b, c) is +e_a: reverse so that the normal leaves the box at x_a = 0
    t1 = ids1[tri]
    sides = np.stack([region, np.full(len(tri), OUTSIDE)], axis=1)
    return np.vstack([t0, t1]), np.vstack([sides, sides])


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


def mesh_surfaces(microstructure, h, *, config: SurfaceConfig = SurfaceConfig(), seed: int = 0) -> SurfaceMesh:
    """Closed, periodic surface mesh of a 3D RVE: inclusion interfaces cut by the box plus box faces.

    Args:
        microstructure: a periodic 3D Microstructure (geometry.Microstructure).
        h: target edge length, a float > 0 or a JAX size callable points (m, 3) -> (m,) (e.g. a SizeField).
        config: SurfaceConfig. seed: seed of the face-node thinning (variable h).
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
    if microstructure.dim != 3 or not microstructure.periodic:
        raise ValueError(f"mesh_surfaces expected a periodic 3D microstructure, got dim={microstructure.dim}, "
                         f"periodic={microstructure.periodic}. Hint: mesh_2d handles 2D.")
    if not isinstance(config, SurfaceConfig):
        raise ValueError(f"config: expected SurfaceConfig, got {type(config).__name__}.")
    box = microstructure.box
    h_fn = as_size_fn(h, box)
    t0 = time.perf_counter()
    reg = _Registry()
    tris, sides, kinds = [], [], []
    for inc in microstructure.inclusions:
        out = mesh_inclusion(inc, h_fn, box, config)
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
    edge_vals = [_edge_values(P, a, box, h_fn) for a in range(3)]
    rng = np.random.default_rng(seed)
    for a in range(3):
        ft, fs = _mesh_face(a, reg, iface, edge_vals, microstructure, h_fn, config, rng)
        tris.append(ft)
        sides.append(fs)
        kinds.append(np.full(len(ft), BOX_FACE))
    t2 = time.perf_counter()
    mesh = SurfaceMesh(
        points=reg.array(), triangles=np.vstack(tris), sides=np.vstack(sides), kind=np.concatenate(kinds),
        node_inclusion=np.asarray(reg.inclusion, np.int64), box=box, periodic_pairs=_periodic_pairs(reg, box),
        metadata={"n_inclusions": len(microstructure.inclusions), "time_interfaces": t1 - t0, "time_faces": t2 - t1},
    )
    if config.check_intersections:
        bad = intersecting_pairs(mesh.points, mesh.triangles)
        mesh.metadata["time_intersections"] = time.perf_counter() - t2
        if len(bad):
            ids = np.unique(mesh.sides[bad.reshape(-1)])
            raise MeshingError("surfaces", f"{len(bad)} intersecting triangle pairs (regions {ids.tolist()})")
    mesh.metadata["n_self_intersections"] = 0 if config.check_intersections else None
    return mesh
