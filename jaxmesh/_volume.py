"""The volume step (paper 4.6): a tetrahedral mesh that keeps every surface triangle, and its labels.

NumPy/SciPy only (never imports jax). Nodes = surface nodes + interior nodes kept away from the
surfaces; Delaunay by Qhull (the convex hull is the box: the 8 corners and the box faces are surface
nodes); missing surface triangles recovered (`_volume_recover`); phases by flood fill across the
faces that are not surface triangles. The relaxation and sliver removal live in `_volume_relax`.
DESIGN.md sections 2-3.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree

from ._errors import MeshingError
from ._mesh import Mesh, classify_facets, facet_table
from ._quality import cross3, longest_edges, signed_volumes
from ._face_flips import delaunay_box_faces, delaunay_interfaces
from ._surface_mesh import INTERFACE, OUTSIDE, SurfaceMesh
from ._volume_recover import (
    distance_to_surface,
    encroached_free_nodes,
    missing_triangles,
    split_edges,
    triangle_keys,
)

__all__ = ["VolumeConfig", "interior_nodes", "conforming_delaunay", "label_cells", "tetrahedralize"]


@dataclass(frozen=True)
class VolumeConfig:
    """Parameters of the volume step, validated on creation.

    Attributes:
        clearance: interior nodes closer than clearance * h to a surface triangle are removed.
        jitter: deterministic jitter of interior nodes, a fraction of h (breaks lattice degeneracy).
        seed: seed of the jitter.
        qhull_options: options of scipy.spatial.Delaunay.
        max_recovery_rounds: Delaunay + recovery rounds before MeshingError.
        min_split_edge: recovery stops (MeshingError) when it would split an edge shorter than this
            share of the surface's median edge: halving edges down to there only chases an interface
            that grazes a box edge or plane, until Qhull merges the nodes.
        flat_eps: a tet is flat when |V| <= flat_eps * l_max^3.
        relax: run the truss relaxation in `tetrahedralize` (needs jax; `_volume_relax`).
        truss: a jaxmesh._truss.TrussConfig for the relaxation, or None for the volume defaults.
        ball_vertex_stiffness: ball-vertex spring constant in the relaxation (section 4.7).
        sliver_angle: sliver removal targets tets with a dihedral angle below this (degrees).
        sliver_passes: passes of vertex moves / flips / insertions.
        slide_surface: let surface nodes slide in the quality smoothing when the global level set is
            known (`tetrahedralize`'s phi_fn; `_surface_slide`): interface nodes on it, box-face nodes
            in their plane with their periodic copy; trace, box-edge and corner nodes stay.
    """

    clearance: float = 0.6
    jitter: float = 1e-3
    seed: int = 0
    qhull_options: str = "Qbb Qc Qz Q12"
    max_recovery_rounds: int = 12
    min_split_edge: float = 3e-3
    flat_eps: float = 1e-10
    relax: bool = True
    truss: Any = None
    ball_vertex_stiffness: float = 1.0
    sliver_angle: float = 10.0
    sliver_passes: int = 6
    slide_surface: bool = True

    def __post_init__(self):
        for name, lo, hi in (("clearance", 0.0, 2.0), ("jitter", 0.0, 0.5), ("flat_eps", 0.0, 1e-3),
                             ("min_split_edge", 0.0, 0.5),
                             ("sliver_angle", 0.0, 60.0), ("ball_vertex_stiffness", 0.0, np.inf)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and lo <= v <= hi):
                raise ValueError(f"VolumeConfig.{name}: expected a number in [{lo}, {hi}], got {v!r}; "
                                 "hint: see the VolumeConfig docstring for the defaults")
        for name in ("max_recovery_rounds", "sliver_passes", "seed"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"VolumeConfig.{name}: expected an integer >= 0, got {v!r}")


def _check_h(h_fn, points: np.ndarray) -> np.ndarray:
    h = np.asarray(h_fn(points), dtype=float).reshape(-1)
    if h.shape != (len(points),) or not np.all(np.isfinite(h)) or (h.size and h.min() <= 0):
        raise ValueError(f"h_fn: expected finite sizes > 0, one per point ({len(points)},), got shape {h.shape}; "
                         "hint: h_fn maps points (k, 3) to target edge lengths (k,)")
    return h


def _bcc_axes(box: np.ndarray, a: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Cube-corner coordinates per axis of the BCC lattice of cube side ~a fitted to the box (shifted
    off the box planes), and the cube sides; the cube centres are the corners + step / 2."""
    n = np.maximum(1, np.round(box / a)).astype(int)
    step = box / n
    return [(np.arange(k) + 0.25) * s for k, s in zip(n, step)], step


def _bcc(box: np.ndarray, a: float) -> np.ndarray:
    """Body-centred cubic lattice of cube side ~a fitted to the box: cube corners, then centres."""
    axes, step = _bcc_axes(box, a)
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return np.concatenate([g, g + 0.5 * step])


def _bcc_where(box: np.ndarray, a: float, h_fn: Callable, lo: float, hi: float, chunk: int = 2**20) -> np.ndarray:
    """The nodes of `_bcc(box, a)` where lo <= h < hi, in the same order, built and sized in slabs
    along x: the finest octave's full lattice can hold ~1e8 nodes (GBs) for a few thousand kept."""
    axes, step = _bcc_axes(box, a)
    rows = max(1, chunk // (len(axes[1]) * len(axes[2])))
    kept = []
    for shift in (0.0, 0.5):  # cube corners, then centres (as `_bcc`)
        for i in range(0, len(axes[0]), rows):
            g = np.stack(np.meshgrid(axes[0][i : i + rows], axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
            g = g + shift * step if shift else g
            h = _check_h(h_fn, g)
            kept.append(g[(h >= lo) & (h < hi)])
    return np.concatenate(kept)


def interior_nodes(surface: SurfaceMesh, h_fn: Callable, config: VolumeConfig = VolumeConfig()) -> np.ndarray:
    """Interior nodes: BCC lattices at h (one level per octave of h), away from the surface, jittered.

    Args:
        surface: the SurfaceMesh (its triangles repel the nodes). h_fn: NumPy points (k, 3) -> (k,).
        config: clearance, jitter, seed.
    Returns:
        (k, 3) float64 points strictly inside the box.
    """
    box = np.asarray(surface.box, dtype=float)
    probe = _bcc(box, box.min() / 16)
    hp = _check_h(h_fn, probe)
    h_hi, h_lo = float(hp.max()), float(hp.min())
    levels = [h_hi]
    while levels[-1] > 1.05 * h_lo and len(levels) < 8:
        levels.append(levels[-1] / 2)
    chunks = []
    for k, a in enumerate(levels):  # keep lattice nodes where a <= h < 2a (coarsest: h >= a; finest: h < 2a)
        chunks.append((_bcc_where(box, a, h_fn, a if k < len(levels) - 1 else -np.inf, 2 * a if k else np.inf), a))
    pts = np.concatenate([c for c, _ in chunks]) if chunks else np.zeros((0, 3))
    if len(levels) > 1:  # level transitions: drop nodes too close to an already accepted one
        h = _check_h(h_fn, pts)
        tree = cKDTree(pts)
        pairs = tree.query_pairs(0.5 * float(h.min()), output_type="ndarray")
        if len(pairs):
            d = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
            close = d < 0.5 * np.minimum(h[pairs[:, 0]], h[pairs[:, 1]])
            drop = np.zeros(len(pts), bool)
            for i, j in pairs[close]:  # greedy: keep the first of each close pair
                if not drop[i]:
                    drop[j] = True
            pts = pts[~drop]
    rng = np.random.default_rng(config.seed)
    h = _check_h(h_fn, pts)
    pts = pts + config.jitter * h[:, None] * rng.uniform(-1.0, 1.0, pts.shape)
    dist = distance_to_surface(pts, surface, config.clearance * h)
    inside = np.all((pts > 0) & (pts < box), axis=1)
    return pts[inside & (dist >= config.clearance * h)]


def delaunay_tets(points: np.ndarray, box, config: VolumeConfig = VolumeConfig()) -> tuple[np.ndarray, dict]:
    """Positively oriented Delaunay tets of points in a box whose hull is the box.

    Flat tets (|V| <= flat_eps l_max^3, from cospherical points) are dropped when all four vertices
    lie on one box plane (they only choose a diagonal of the hull); elsewhere they are reported.

    Returns:
        (cells (m, 4) int64, info {'flat_dropped', 'flat_interior', 'coplanar'}).
    """
    box = np.asarray(box, dtype=float)
    cells, coplanar = _enclosed_delaunay(points, box, config.qhull_options)
    if cells is not None:
        cells, info = _positive_drop_flat(points, cells, box, config.flat_eps, coplanar)
        if not info["flat_interior"]:  # the far corners can make cospherical nodes pick flat tets
            return cells, info
    tri = Delaunay(points, qhull_options=config.qhull_options)
    return _positive_drop_flat(points, np.asarray(tri.simplices, dtype=np.int64), box, config.flat_eps,
                               len(tri.coplanar))


def _positive_drop_flat(points, cells, box, flat_eps: float, coplanar: int) -> tuple[np.ndarray, dict]:
    """`delaunay_tets`'s cells made positive, flat ones on a box plane dropped, and its info."""
    vol = signed_volumes(points, cells)
    neg = vol < 0
    cells[neg, :2] = cells[neg, 1::-1]
    p = points[cells]
    flat = np.abs(vol) <= flat_eps * longest_edges(p) ** 3
    on_plane = np.zeros(len(cells), bool)
    for a in range(3):
        for s in (0.0, 1.0):
            on_plane |= np.all(np.abs(p[:, :, a] - s * box[a]) <= 1e-9 * box[a], axis=1)
    info = {"flat_dropped": int((flat & on_plane).sum()), "flat_interior": int((flat & ~on_plane).sum()),
            "coplanar": int(coplanar)}
    return cells[~(flat & on_plane)], info


def _enclosed_delaunay(points: np.ndarray, box: np.ndarray, options: str) -> tuple[np.ndarray | None, int]:
    """Delaunay tets of points in the box, computed with the corners of a 3x larger box added.

    Qhull slows down when thousands of nodes lie on the hull's planar faces (the box faces); with
    the far corners the box faces are inside the hull (about half the Delaunay time on the Table-1
    RVEs). The tets without a far corner are kept if they fill the box exactly: volumes summing to
    the box's and boundary faces on the box planes. Returns (None, 0) otherwise (then plain Qhull).
    """
    n = len(points)
    far = np.stack(np.meshgrid(*[[-1.0, 2.0]] * 3, indexing="ij"), -1).reshape(-1, 3) * box
    tri = Delaunay(np.concatenate([points, far]), qhull_options=options)
    cells = np.asarray(tri.simplices, dtype=np.int64)
    cells = cells[(cells < n).all(axis=1)]
    if abs(np.abs(signed_volumes(points, cells)).sum() - np.prod(box)) > 1e-9 * np.prod(box):
        return None, 0
    table = facet_table(cells, n)
    on_box = classify_facets(points, table.facets[table.counts == 1], box) >= 0
    return (cells, len(tri.coplanar)) if on_box.all() else (None, 0)


def conforming_delaunay(surface: SurfaceMesh, interior: np.ndarray, config: VolumeConfig = VolumeConfig(),
                        project_fn: Callable | None = None) -> tuple[np.ndarray, np.ndarray, SurfaceMesh, dict]:
    """Delaunay of surface + interior nodes in which every surface triangle is a tet face.

    Rounds: Delaunay -> missing triangles -> remove the interior nodes in their smallest
    circumscribed balls, or (none there) split their longest edge (`split_edges`) -> repeat.

    Args:
        surface: SurfaceMesh; interior: (k, 3) interior nodes.
        config: VolumeConfig. project_fn: see `split_edges` (projects interface midpoints).
    Returns:
        (points (n, 3) = surface.points then kept interior nodes, cells (m, 4), the possibly
        refined SurfaceMesh, info counts).
    Raises:
        MeshingError('volume', ...) naming the inclusion when recovery does not finish.
    """
    interior = np.asarray(interior, dtype=float).reshape(-1, 3)
    info = {"rounds": 0, "missing_first": 0, "interior_removed": 0, "surface_splits": 0, "flat_dropped": 0,
            "flat_interior": 0}
    history: list[int] = []  # missing triangles per round
    split_floor = config.min_split_edge * _median_edge(surface.points[surface.triangles])
    last_missing = None  # (surface, missing mask) of the previous round, for the error's place
    for rnd in range(config.max_recovery_rounds + 1):
        surface, face_flips = delaunay_box_faces(surface)  # box faces lie on the hull: they must be 2D Delaunay
        surface, interface_flips = delaunay_interfaces(surface)
        info["surface_flips"] = info.get("surface_flips", 0) + face_flips + interface_flips
        ns = surface.n_points
        points = np.concatenate([surface.points, interior])
        cells, dinfo = delaunay_tets(points, surface.box, config)
        info["flat_dropped"] += dinfo["flat_dropped"]
        if dinfo["coplanar"]:  # Qhull left nodes out (duplicates): a surface node must never be one
            if last_missing is None:
                raise MeshingError("volume", f"Qhull skipped {dinfo['coplanar']} coincident nodes; hint: the "
                                   "surface holds duplicate nodes or interior nodes coincide with it")
            place, at_plane = _missing_cause(*last_missing)
            raise MeshingError("volume", f"surface recovery stalled: its splits brought {dinfo['coplanar']} nodes "
                               f"within Qhull's precision of others{place}",
                               inclusion=_missing_inclusion(*last_missing), at_box_plane=at_plane)
        miss = missing_triangles(surface.triangles, cells, len(points))
        info["rounds"] = rnd
        history.append(int(miss.sum()))
        info["missing_first"] = history[0]
        if len(history) >= 6 and history[-1] > history[-2] > history[-3] > history[-4] > history[-5]:
            place, at_plane = _missing_cause(surface, miss)
            raise MeshingError("volume", f"surface recovery diverges (missing triangles per round: {history})"
                               f"{place}", inclusion=_missing_inclusion(surface, miss), at_box_plane=at_plane)
        if not miss.any() and not dinfo["flat_interior"]:
            info["flat_interior"] = 0
            return points, cells, surface, info
        if rnd == config.max_recovery_rounds:
            break
        if not miss.any():  # flat interior tets only: re-jitter the interior nodes
            if not len(interior):
                raise MeshingError("volume", f"{dinfo['flat_interior']} flat tets between surface nodes and no "
                                   "interior node to move (hint: a smaller h)")
            rng = np.random.default_rng(config.seed + 1000 + rnd)
            span = np.ptp(interior, axis=0).max(initial=1.0) / max(len(interior), 1) ** (1 / 3)
            interior = interior + 1e-3 * span * rng.uniform(-1, 1, interior.shape)
            continue
        tris = surface.triangles[miss]
        free = np.zeros(len(points), bool)
        free[ns:] = True
        enc = encroached_free_nodes(points, tris, free)
        if len(enc):
            keep = np.ones(len(interior), bool)
            keep[enc - ns] = False
            interior = interior[keep]
            info["interior_removed"] += int(len(enc))
            continue
        P = surface.points[tris]
        el = np.linalg.norm(P[:, [1, 2, 0]] - P, axis=-1)  # edge j = (j, j+1)
        j = np.argmax(el, axis=1)
        edges = np.stack([tris[np.arange(len(tris)), j], tris[np.arange(len(tris)), (j + 1) % 3]], 1)
        shortest = float(el.max(axis=1).min())  # of the edges about to be split
        if shortest < split_floor:
            place, at_plane = _missing_cause(surface, miss)
            raise MeshingError("volume", f"surface recovery stalled: {int(miss.sum())} triangles still missing after "
                               f"{rnd + 1} rounds and their edges split down to {shortest:.2g}, under "
                               f"{config.min_split_edge:g} of the median surface edge{place}",
                               inclusion=_missing_inclusion(surface, miss), at_box_plane=at_plane)
        last_missing = (surface, miss)
        surface, added = split_edges(surface, edges, project_fn)
        info["surface_splits"] += int(added)
        if not added:  # the next round would be the same Delaunay: fail now, not after max_recovery_rounds
            raise MeshingError("volume", f"{int(miss.sum())} surface triangles missing and none of their longest "
                               "edges can be split inside the box (hint: an inclusion crossing a box plane by less "
                               "than the surface resolution was meshed as not crossing it; move it off the plane or "
                               "across it)", inclusion=_missing_inclusion(surface, miss), at_box_plane=True)
    place, at_plane = _missing_cause(surface, miss)
    raise MeshingError("volume", f"{int(miss.sum())} surface triangles still missing and "
                       f"{dinfo['flat_interior']} flat tets after {config.max_recovery_rounds} recovery rounds"
                       f"{place}", inclusion=_missing_inclusion(surface, miss), at_box_plane=at_plane)


def _median_edge(corners: np.ndarray) -> float:
    """Median edge length of triangles given by their corners (k, 3, 3); 0 for none."""
    return float(np.median(np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=-1))) if len(corners) else 0.0


def _missing_place(surface: SurfaceMesh, miss: np.ndarray) -> str:
    """The message part of `_missing_cause`."""
    return _missing_cause(surface, miss)[0]


def _missing_cause(surface: SurfaceMesh, miss: np.ndarray) -> tuple[str, bool]:
    """' near x = (...)' and the likely cause, from where most missing triangles gather, for the error
    message; and whether that cause is an interface grazing a box plane (beside an edge or not).

    Beside a box edge (the second-nearest box plane within ten triangle sizes), or against one box
    plane (the interface nearly tangent to it: the nodes that splits add there come ever closer to the
    plane, a plain-box excursion set at 0.45), or between interfaces. Where the missing interface
    triangles there run along the nearest plane, the region between them and it is named as well, and
    the plane is the cause however thick that layer is against the triangles.
    """
    if not miss.any():
        return "", False
    box = np.asarray(surface.box, dtype=float)
    P = surface.points[surface.triangles[miss]]
    centroids = P.mean(axis=1)
    size = _median_edge(P)
    crowd = cKDTree(centroids).query_ball_point(centroids, 0.05 * float(box.min()), return_length=True)
    centre = centroids[int(np.argmax(crowd))]
    to_plane = np.minimum(centre, box - centre)
    first, second = np.argsort(to_plane)[:2]
    place = f" near x = {tuple(round(float(v), 4) for v in centre)}"
    plane = f"x_{first} = {'0L'[int(centre[first] > 0.5 * box[first])]}"
    interface = surface.kind[miss] == INTERFACE
    layer = _layer_along_plane(P[interface], centroids[interface], surface.sides[miss][interface], box, centre,
                               int(first), 0.05 * float(box.min()))
    if layer:
        across = ", going on across it into the periodic image" if surface.periodic else ""
        place += f" ({layer} along the box plane {plane}{across})"
    remedy = ("--roll auto moves the box off grazing meetings with the interfaces (tried once by default "
              "where that moves it farther)"
              if surface.periodic else
              "--close-box-layers closes the layers along a plain box's planes thinner than a sixth of a "
              "grid step (level sets; tried once by default); a periodic field meshed periodic (with --roll "
              "auto) avoids the plane")
    if to_plane[second] <= 10.0 * size:
        return (f"{place}, {to_plane[second]:.2g} from a box edge (seen where an interface passes a small fraction "
                "of a grid step from a box edge: a layer thinner than the input resolves; hint: move the "
                f"inclusion off the edge or across it, or sample the field finer; {remedy})"), True
    if layer or to_plane[first] <= size:  # a layer along the plane: its triangles may be far smaller than it is thick
        return (f"{place}, {to_plane[first]:.2g} from the box plane {plane}: the interface there is nearly tangent "
                "to the plane (it grazes it, or a layer thinner than the grid step meets it), and the nodes recovery "
                "adds come ever closer to the plane; hint: sample or smooth the field so that the interface crosses "
                f"the plane at an angle there; {remedy}"), True
    return (f"{place} (interfaces closer to each other than the surface resolves; hint: sample the field finer or "
            "raise max_recovery_rounds)"), False


def _layer_along_plane(P: np.ndarray, centroids: np.ndarray, sides: np.ndarray, box: np.ndarray, centre: np.ndarray,
                       axis: int, radius: float) -> str:
    """What lies between the plane x_axis nearest `centre` and the missing interface triangles P (k, 3, 3)
    near it, when most of those run along the plane (normals within 30 degrees of its normal): e.g. 'a
    layer of inclusion 3 about 0.0002 thick'; '' otherwise. The right-hand normal points from sides[:, 0]
    to sides[:, 1]."""
    near = np.linalg.norm(centroids - centre, axis=1) <= radius
    normal = cross3(P[near, 1] - P[near, 0], P[near, 2] - P[near, 0])
    along = normal[:, axis] / np.maximum(np.linalg.norm(normal, axis=1), np.finfo(float).tiny)
    flat = np.abs(along) >= np.cos(np.radians(30.0))
    if not near.any() or 2 * flat.sum() <= len(flat):
        return ""
    at_zero = centre[axis] < 0.5 * box[axis]
    away = along[flat] * (1.0 if at_zero else -1.0) > 0  # the normal points away from the plane
    sides = sides[near][flat]
    values, counts = np.unique(np.where(away, sides[:, 0], sides[:, 1]), return_counts=True)
    region = int(values[np.argmax(counts)])
    height = np.abs(centroids[near][flat, axis] - (0.0 if at_zero else box[axis]))
    what = f"inclusion {region}" if region > 0 else "matrix"
    return f"a layer of {what} about {float(np.median(height)):.2g} thick"


def _missing_inclusion(surface: SurfaceMesh, miss: np.ndarray) -> int | None:
    """The first inclusion that a missing triangle bounds, for the error message (None: box faces only)."""
    sides = surface.sides[miss]
    return int(sides[sides > 0][0]) if np.any(sides > 0) else None


def label_cells(points: np.ndarray, cells: np.ndarray, surface: SurfaceMesh) -> tuple[np.ndarray, dict]:
    """Region id of every tet: flood fill across faces that are not surface triangles.

    Each face-connected component takes the region on its side of the surface triangles that bound
    it (the right-hand normal points from sides[:, 0] to sides[:, 1]).

    Returns:
        (inclusion_id (m,) int64, info {'components', 'conflicts'}).
    Raises:
        MeshingError if a component has no bounding triangle or its bounding triangles disagree.
    """
    n, m = len(points), len(cells)
    table = facet_table(cells, n)
    fkeys = triangle_keys(table.facets, n)  # sorted: facet_table orders facets by the same packed key
    skeys = triangle_keys(surface.triangles, n)
    barrier = np.zeros(len(fkeys), bool)
    fidx = np.searchsorted(fkeys, skeys)
    if np.any(fidx >= len(fkeys)) or np.any(fkeys[np.minimum(fidx, len(fkeys) - 1)] != skeys):
        raise MeshingError("volume", "labels: some surface triangles are not tet faces")
    barrier[fidx] = True
    two, owners = table.pairs()
    open_ = ~barrier[two]
    a, b = owners[open_, 0], owners[open_, 1]
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(m, m))
    n_comp, comp = connected_components(graph, directed=False)
    cells_by, offsets = table.owners()
    votes = []  # (component, region)
    tri = surface.triangles
    for rep in range(2):  # up to two cells per surface face
        has = table.counts[fidx] > rep
        c = cells_by[offsets[fidx[has]] + rep]
        t = tri[has]
        apex = cells[c].sum(axis=1) - t.sum(axis=1)  # the tet's vertex that is not on the triangle
        x = points
        side = np.einsum("ij,ij->i", cross3(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]), x[apex] - x[t[:, 0]])
        region = np.where(side > 0, surface.sides[has, 1], surface.sides[has, 0])
        votes.append(np.stack([comp[c], region], 1))
    votes = np.concatenate(votes)
    label = np.full(n_comp, -2, dtype=np.int64)
    conflicts = 0
    for cid, regions in zip(*_group(votes[:, 0], votes[:, 1])):
        vals, cnt = np.unique(regions, return_counts=True)
        label[cid] = vals[np.argmax(cnt)]
        conflicts += int(len(vals) > 1)
    bad = np.flatnonzero(label < 0)
    if len(bad) or conflicts:
        k = [int(v) for v in np.unique(votes[:, 1]) if v > 0]
        raise MeshingError("volume", f"labels: {len(bad)} components without a valid region ({OUTSIDE} means a "
                           f"box-face triangle is oriented inwards), {conflicts} with conflicting sides; hint: "
                           "check the orientation of the surface triangles", inclusion=k[0] if k else None)
    return label[comp], {"components": int(n_comp), "conflicts": conflicts}


def _group(keys: np.ndarray, values: np.ndarray):
    order = np.argsort(keys, kind="stable")
    k, v = keys[order], values[order]
    uniq, start = np.unique(k, return_index=True)
    return uniq, np.split(v, start[1:])


def tetrahedralize(surface: SurfaceMesh, interior_points: np.ndarray | None = None, *, h_fn: Callable,
                   config: VolumeConfig = VolumeConfig(), project_fn: Callable | None = None,
                   label_fn: Callable | None = None, phi_fn: Callable | None = None,
                   h_jax_fn: Callable | None = None, return_surface: bool = False):
    """Tetrahedral mesh of an RVE (periodic or not) that contains every (possibly refined) surface triangle.

    Args:
        surface: SurfaceMesh (interfaces + box faces, periodic pairs).
        interior_points: (k, 3) interior nodes (e.g. octree nodes), or None for BCC lattices on h.
            They are filtered by clearance * h from the surface and jittered.
        h_fn: NumPy size function points (k, 3) -> (k,).
        config: VolumeConfig.
        project_fn: projection of split interface midpoints (see `levelset_projector`).
        label_fn: optional field labels points (k, 3) -> (k,) ids, checked at the centroids of
            cells with no surface vertex (MeshingError on disagreement).
        phi_fn: optional global level set (NumPy, negative inside): the label check tolerates
            centroids near it, and the smoothing slides surface nodes (config.slide_surface).
        h_jax_fn: JAX size function for the relaxation (default: h_fn sampled on a periodic grid).
        return_surface: also return the SurfaceMesh actually kept (refined if recovery split edges).
    Returns:
        Mesh (positively oriented cells, inclusion_id, periodic_pairs); with return_surface,
        (Mesh, SurfaceMesh).

    Example: ``mesh = tetrahedralize(surface, h_fn=lambda p: np.full(len(p), 0.1))``.
    """
    if not isinstance(surface, SurfaceMesh):
        raise ValueError(f"tetrahedralize expects a SurfaceMesh, got {type(surface).__name__}; "
                         "hint: build it with jaxmesh._surface_mesh.SurfaceMesh")
    if not isinstance(config, VolumeConfig):
        raise ValueError(f"config: expected VolumeConfig, got {type(config).__name__}")
    if not callable(h_fn):
        raise ValueError(f"h_fn: expected a callable points (k, 3) -> (k,), got {type(h_fn).__name__}")
    t0 = time.perf_counter()
    times = {}
    if interior_points is None:
        interior = interior_nodes(surface, h_fn, config)
    else:
        interior = np.asarray(interior_points, dtype=float)
        if interior.ndim != 2 or interior.shape[1] != 3 or not np.all(np.isfinite(interior)):
            raise ValueError(f"interior_points: expected finite (k, 3) points, got shape {interior.shape}")
        box = np.asarray(surface.box)
        h = _check_h(h_fn, interior) if len(interior) else np.zeros(0)
        rng = np.random.default_rng(config.seed)
        interior = interior + config.jitter * h[:, None] * rng.uniform(-1, 1, interior.shape)
        dist = distance_to_surface(interior, surface, config.clearance * h)
        interior = interior[np.all((interior > 0) & (interior < box), axis=1) & (dist >= config.clearance * h)]
    times["interior_nodes"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    points, cells, surface, info = conforming_delaunay(surface, interior, config, project_fn)
    times["delaunay_recovery"] = time.perf_counter() - t1
    meta = {"volume": dict(info), "times": times}
    if config.relax:
        from ._volume_relax import relax_volume  # jax is imported only here

        mesh = _make_mesh(points, cells, surface, meta)
        mesh, surface = relax_volume(mesh, surface, h_fn, config, h_jax_fn=h_jax_fn, project_fn=project_fn,
                                     phi_fn=phi_fn, return_surface=True)  # surface nodes may slide
    else:
        mesh = _make_mesh(points, cells, surface, meta)
    if label_fn is not None:
        check_labels(mesh, surface, label_fn, phi_fn)
    mesh.metadata["times"]["volume_total"] = time.perf_counter() - t0
    return (mesh, surface) if return_surface else mesh


def _make_mesh(points, cells, surface, meta) -> Mesh:
    t = time.perf_counter()
    ids, linfo = label_cells(points, cells, surface)
    meta = dict(meta)
    meta["volume"] = {**meta.get("volume", {}), **linfo, "n_points": len(points), "n_cells": len(cells),
                      "n_surface_points": surface.n_points, "n_surface_triangles": surface.n_triangles}
    meta.setdefault("times", {})["labels"] = time.perf_counter() - t
    pairs = {a: np.asarray(p, dtype=np.int64) for a, p in surface.periodic_pairs.items()} or None
    return Mesh(points, cells, ids, surface.box, periodic=surface.periodic, periodic_pairs=pairs, metadata=meta)


def check_labels(mesh: Mesh, surface: SurfaceMesh, label_fn: Callable, phi_fn: Callable | None = None) -> int:
    """Compare the flood-fill labels with label_fn at the centroids of cells with no surface vertex.

    With phi_fn (global signed distance), a centroid closer to the level set than half its cell's
    longest edge may fall either side (the validator's rule): the surface triangles are chords of it.
    Returns the number of checked cells; raises MeshingError naming an inclusion on disagreement.
    """
    deep = np.all(mesh.cells >= surface.n_points, axis=1)
    if not deep.any():
        return 0
    cen = mesh.points[mesh.cells[deep]].mean(axis=1)
    lab = np.asarray(label_fn(cen)).reshape(-1).astype(np.int64)
    bad = lab != mesh.inclusion_id[deep]
    if phi_fn is not None and bad.any():
        disagree = np.flatnonzero(bad)
        lmax = longest_edges(mesh.points[mesh.cells[deep][disagree]])
        bad[disagree] = np.abs(np.asarray(phi_fn(cen[disagree]), dtype=float).reshape(-1)) > 0.5 * lmax
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshingError("volume", f"labels: {int(bad.sum())} of {int(deep.sum())} deep cells disagree with the "
                           f"field (e.g. mesh {int(mesh.inclusion_id[deep][i])} vs field {int(lab[i])})",
                           inclusion=int(max(lab[i], mesh.inclusion_id[deep][i])))
    return int(deep.sum())

