"""Volume relaxation (paper 4.7): quality optimisation by flips and smoothing of the interior nodes
(and of the surface nodes, sliding on their level set or box plane when it is given), then sliver removal;
optionally first a truss with surface nodes fixed, surface-keeping retriangulation and ball-vertex
springs (VolumeConfig.truss). JAX enters through the truss only.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from ._mesh import Mesh
from ._quality import cell_quality
from ._slivers import improve_topology, insert_steiner, min_dihedral, smooth_vertices
from ._surface_mesh import SurfaceMesh
from ._surface_slide import SurfaceSlide
from ._truss import TrussConfig, make_constraints, relax
from ._volume import VolumeConfig, _check_h, _make_mesh, conforming_delaunay, delaunay_tets
from ._volume_recover import distance_to_surface, triangle_keys

__all__ = ["relax_volume", "remove_slivers", "grid_size_fn"]


def grid_size_fn(h_fn: Callable, box, n: int = 32) -> Callable:
    """A JAX size function: the NumPy h_fn sampled on a periodic n^3 grid, interpolated linearly."""
    from .geometry._grid import interpolate_linear

    box = tuple(float(b) for b in box)
    axes = [np.arange(n) * (L / n) for L in box]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = jnp.asarray(_check_h(h_fn, g).reshape(n, n, n))
    return lambda points: interpolate_linear(values, box, points)


def _truss_config(config: VolumeConfig) -> TrussConfig | None:
    """The truss of the relaxation, or None to skip it (the default).

    Measured on spheres with BCC interior nodes: the truss (surface fixed, Delaunay retriangulations)
    lowered the mean quality of the conforming Delaunay from 0.83 to 0.76 and diverged; flips plus
    optimisation-based smoothing (`optimise_mesh`) from the unrelaxed mesh reach 0.84-0.86.
    """
    if config.truss is None:
        return None
    if not isinstance(config.truss, TrussConfig):
        raise ValueError(f"VolumeConfig.truss: expected a TrussConfig or None, got {type(config.truss).__name__}")
    return config.truss


def relax_volume(mesh: Mesh, surface: SurfaceMesh, h_fn: Callable, config: VolumeConfig = VolumeConfig(), *,
                 h_jax_fn: Callable | None = None, project_fn: Callable | None = None,
                 phi_fn: Callable | None = None, return_surface: bool = False):
    """Improve the interior of a conforming mesh and remove slivers; the surface stays exact.

    Surface nodes (the first surface.n_points nodes of the mesh) are fixed, except that with phi_fn
    (the global level set) and config.slide_surface they slide while the quality is optimised
    (`remove_slivers`: interface nodes on phi = 0, box-face nodes in their plane with their periodic
    copy; the surface keeps its triangles). With a truss in config
    the interior nodes are relaxed first: each retriangulation is a Delaunay that must contain every
    surface triangle, otherwise the previous topology is kept, and a conforming Delaunay of the moved
    nodes is rebuilt (recovery as in `conforming_delaunay`). Then `remove_slivers` runs (flips and
    smoothing, then the sliver fixes).

    Args:
        mesh: Mesh from the conforming Delaunay (points = surface points then interior nodes).
        surface: the SurfaceMesh kept in it. h_fn: NumPy size function (k, 3) -> (k,).
        config: VolumeConfig (truss, ball_vertex_stiffness, sliver_angle, sliver_passes).
        h_jax_fn: JAX size function for the truss (default `grid_size_fn(h_fn, box)`).
        project_fn: projection of split interface midpoints if recovery must split.
        phi_fn: NumPy global level set points (k, 3) -> (k,), for the sliding surface nodes.
        return_surface: also return the SurfaceMesh kept (refined if recovery split edges).
    Returns:
        Mesh with metadata['volume'] updated (relaxation stop reason, sliver counts, quality).
    """
    if not isinstance(mesh, Mesh) or not isinstance(surface, SurfaceMesh):
        raise ValueError(f"relax_volume expects (Mesh, SurfaceMesh), got ({type(mesh).__name__}, "
                         f"{type(surface).__name__}); hint: pass tetrahedralize(..., config=VolumeConfig(relax=False))")
    ns, n = surface.n_points, mesh.n_points
    if n < ns or not np.array_equal(mesh.points[:ns], surface.points):
        raise ValueError("relax_volume: the mesh's first nodes must be the surface nodes; hint: use the mesh "
                         "and the surface returned by tetrahedralize(..., return_surface=True)")
    box = np.asarray(mesh.box, dtype=float)
    meta = {k: (dict(v) if isinstance(v, dict) else v) for k, v in mesh.metadata.items()}
    meta.setdefault("times", {})
    vinfo = meta.setdefault("volume", {})
    t0 = time.perf_counter()
    points, cells = mesh.points, mesh.cells
    truss = _truss_config(config)
    if n > ns and truss is not None:
        cons = make_constraints(n, 3, fixed=np.arange(ns))
        skeys = triangle_keys(surface.triangles, n)
        state = {"cells": mesh.cells, "kept_old": 0}

        def triangulate(p):
            cells, info = delaunay_tets(np.asarray(p, dtype=float), box, config)
            ok = not info["flat_interior"] and np.isin(skeys, _face_keys(cells, n)).all()
            if ok:
                state["cells"] = cells
            else:
                state["kept_old"] += 1
            return state["cells"]

        hj = h_jax_fn if h_jax_fn is not None else grid_size_fn(h_fn, box)
        res = relax(jnp.asarray(points, dtype=jnp.result_type(float)), triangulate, hj, cons, config=truss, box=box)
        points = np.array(res.points, dtype=float)
        points[:ns] = surface.points  # bit-identical surface
        vinfo.update({"relax_stop": res.stop_reason, "relax_iterations": int(res.n_iterations),
                      "relax_retriangulations": int(res.n_retriangulations),
                      "relax_kept_old_topology": state["kept_old"]})
        interior = points[ns:]
        eps = 1e-9 * box
        interior = interior[np.all((interior > eps) & (interior < box - eps), axis=1)]
        h = _check_h(h_fn, interior) if len(interior) else np.zeros(0)
        near = distance_to_surface(interior, surface, 0.25 * h) < 0.25 * h  # drifted onto a surface
        interior = interior[~near]
        points, cells, surface, rinfo = conforming_delaunay(surface, interior, config, project_fn)
        vinfo.update({f"relax_recovery_{k}": v for k, v in rinfo.items()})
    meta["times"]["relax"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    points, cells, surface, sinfo = remove_slivers(points, cells, surface, config, phi_fn=phi_fn)
    vinfo.update(sinfo)
    meta["times"]["slivers"] = time.perf_counter() - t1
    out = _make_mesh(points, cells, surface, meta)
    q = cell_quality(out.points, out.cells)
    out.metadata["volume"].update({"q_min": float(q.min()), "q_mean": float(q.mean()),
                                   "frac_q_below_0.3": float(np.mean(q < 0.3)),
                                   "min_dihedral": float(min_dihedral(out.points, out.cells).min())})
    return (out, surface) if return_surface else out


def _face_keys(cells: np.ndarray, n: int) -> np.ndarray:
    return triangle_keys(cells[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), n)


def optimise_mesh(points: np.ndarray, cells: np.ndarray, surface: SurfaceMesh, rounds: int = 5,
                  threshold: float = 0.85, free: np.ndarray | None = None,
                  min_gain: float = 1e-3, local: bool = False,
                  slide: SurfaceSlide | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Rounds of flips (`improve_topology`) then smoothing of the interior nodes (`smooth_vertices`),
    until a round raises the mean quality by less than min_gain.

    Flips first: the conforming Delaunay's slivers are mostly fixed by edge removals, and smoothing
    then works on a better topology. Surface triangles never change; surface nodes move only with
    `slide` (a SurfaceSlide). With `local` the flips too stay at tets
    with a `free` vertex (the clean-up around Steiner points).
    """
    if free is None:
        free = np.arange(len(points)) >= surface.n_points
    protected = np.unique(triangle_keys(surface.triangles, len(points)))
    info = {"opt_flips": 0, "opt_moves": 0, "opt_rounds": 0}
    mean = cell_quality(points, cells).mean()
    for rnd in range(rounds):
        cells, flipped = improve_topology(points, cells, protected, threshold, passes=2, near=free if local else None)
        points, moved = smooth_vertices(points, cells, free, sweeps=2, seed=rnd, slide=slide)
        info["opt_flips"] += flipped
        info["opt_moves"] += moved
        info["opt_rounds"] += 1
        prev, mean = mean, cell_quality(points, cells).mean()
        if mean - prev < min_gain:
            break
    return points, cells, info


def remove_slivers(points: np.ndarray, cells: np.ndarray, surface: SurfaceMesh,
                   config: VolumeConfig = VolumeConfig(), phi_fn: Callable | None = None):
    """Quality optimisation (`optimise_mesh`: flips and smoothing; with phi_fn and config.slide_surface
    the surface nodes slide, `SurfaceSlide`), then up to config.sliver_passes
    rounds for the slivers left (dihedral angle below config.sliver_angle): Steiner points in local
    cavities that keep the surface (`insert_steiner`), optimised again near them. Slivers stay where
    thin surface triangles force them: every tet on a surface triangle with a small angle is flat.

    Returns:
        (points, cells, the SurfaceMesh (its nodes where they slid), info {'slivers_before',
        'slivers_after', 'inserted', 'opt_flips', 'opt_moves', 'slid'}).
    """
    angle = config.sliver_angle
    info = {"slivers_before": int((min_dihedral(points, cells) < angle).sum()), "inserted": 0, "opt_flips": 0,
            "opt_moves": 0, "opt_rounds": 0}
    free = np.arange(len(points)) >= surface.n_points
    slide = None
    if phi_fn is not None and config.slide_surface:
        slide = SurfaceSlide(points, surface.triangles, surface.node_inclusion, surface.box, phi_fn,
                             surface.periodic_pairs, surface.periodic)
    first = points[: surface.n_points].copy()
    for rnd in range(config.sliver_passes + 1):
        # the surface nodes slide in the global pass only; the Steiner clean-ups stay local
        points, cells, oinfo = optimise_mesh(points, cells, surface, free=free, local=rnd > 0,
                                             slide=slide if rnd == 0 else None)
        for k, v in oinfo.items():
            info[k] += v
        bad = np.flatnonzero(min_dihedral(points, cells) < angle)
        if not len(bad) or rnd == config.sliver_passes:
            break
        protected = np.unique(triangle_keys(surface.triangles, len(points)))
        points, cells, added = insert_steiner(points, cells, protected, bad)
        if not len(added):
            break
        info["inserted"] += len(added)
        free = np.zeros(len(points), bool)  # later rounds move the new vertices and their neighbours
        near = np.any(np.isin(cells, added), axis=1)
        free[cells[near].ravel()] = True
        free[: surface.n_points] = False
    info["slivers_after"] = int((min_dihedral(points, cells) < angle).sum())
    slid = np.any(points[: surface.n_points] != first, axis=1)
    info["slid"] = int(slid.sum())
    if slid.any():
        surface = dataclasses.replace(surface, points=points[: surface.n_points].copy())
    return points, cells, surface, info
