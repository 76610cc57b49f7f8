"""The volume quality optimisation alone, with and without sliding surface nodes (one run, ratios).

Usage:
    python benchmarks/bench_optimise.py                       # Table-1 coarse RVE (bench_pipeline's preset)
    python benchmarks/bench_optimise.py --preset fine --surface-cache /tmp/surf.npz
    python benchmarks/bench_optimise.py --clearance 0.6 0.5 0.45   # interior-node clearance vs count and q

Builds the RVE, size function and surfaces as `bench_pipeline.py` does (the surfaces optionally from
`--surface-cache`), then the conforming Delaunay once, and runs `optimise_mesh` (flips and smoothing,
the first pass of the sliver stage) on that same mesh for each variant: surface nodes fixed, interface
nodes sliding on the level set, or those and the box-face nodes (`SurfaceSlide`); flips around tets
below q 0.7 or 0.85. Prints seconds, mean q, min dihedral and the mean q per number of surface nodes
of a tet. With --clearance, instead: per clearance (interior nodes closer than clearance * h to a surface
are dropped; `VolumeConfig.clearance`, default 0.6) a new conforming Delaunay, optimised with the interface
and box-face nodes sliding; prints its node and tet counts too. Not a test.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import numpy as np

import bench_pipeline as bp


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(bp.PRESETS), default="coarse")
    parser.add_argument("--surface-cache", default=None, help=".npz to store / reuse the surface mesh")
    parser.add_argument("--clearance", type=float, nargs="+", default=None,
                        help="compare these interior-node clearances (fractions of h) instead of the sliding variants")
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxmesh import MeshConfig, cell_quality, microstructure_from_specs, random_inclusions
    from jaxmesh._faces import mesh_surfaces
    from jaxmesh._sizing import SizeParams, size_function
    from jaxmesh._slivers import min_dihedral
    from jaxmesh._surface import evaluate_size
    from jaxmesh._surface_slide import SurfaceSlide
    from jaxmesh._volume import VolumeConfig, conforming_delaunay, interior_nodes
    from jaxmesh._volume_recover import levelset_projector
    from jaxmesh._volume_relax import optimise_mesh

    code = bp.commit()
    defaults = bp.parse_args([])
    specs = random_inclusions((1.0, 1.0, 1.0), n=defaults.n, volume_fraction=defaults.volume_fraction,
                              shape="sphere", radius=tuple(defaults.radius), min_gap=defaults.min_gap, seed=0)
    ms = microstructure_from_specs(specs, (1.0, 1.0, 1.0), (defaults.grid,) * 3)
    config = MeshConfig(**bp.PRESETS[args.preset])
    field = size_function(ms, SizeParams(**config.size_kwargs()))
    h_np = lambda p: evaluate_size(field, p)  # noqa: E731
    if args.surface_cache and os.path.exists(args.surface_cache):
        surface, _ = bp.load_surface(args.surface_cache)
    else:
        t = time.perf_counter()
        surface = mesh_surfaces(ms, field)
        if args.surface_cache:
            bp.save_surface(args.surface_cache, surface, time.perf_counter() - t, np.asarray(field.values))
    project = levelset_projector(ms.inclusion_phi)
    ms.phi(np.zeros((8, 3)))  # compile before timing
    head = (f"# bench_optimise, {datetime.date.today().isoformat()}, commit {code}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__}; "
            f"preset {args.preset}: {len(ms.inclusions)} inclusions, {surface.n_points:,} surface nodes")

    def report(p, c, n_surface):
        q = cell_quality(p, c)
        on_surface = (c < n_surface).sum(axis=1)
        by = " / ".join(f"{q[on_surface == k].mean():.3f}" for k in range(5))
        return f"{q.mean():.4f} | {min_dihedral(p, c).min():.2f} | {by} |"

    if args.clearance:
        print(head)
        print("| clearance | interior nodes | tets | time (s) | mean q | min dihedral (deg) | mean q by surface nodes 0/1/2/3/4 |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: | --- |")
        for clearance in args.clearance:
            vconfig = VolumeConfig(clearance=clearance)
            t = time.perf_counter()
            points, cells, surf, _ = conforming_delaunay(surface, interior_nodes(surface, h_np, vconfig), vconfig,
                                                         project_fn=project)
            slide = SurfaceSlide(points, surf.triangles, surf.node_inclusion, surf.box, ms.phi, surf.periodic_pairs)
            p, c, _ = optimise_mesh(points, cells, surf, threshold=0.85, slide=slide)
            print(f"| {clearance} | {len(points) - surf.n_points:,} | {len(c):,} | {time.perf_counter() - t:.1f} | "
                  f"{report(p, c, surf.n_points)}", flush=True)
        return
    points, cells, surface, _ = conforming_delaunay(surface, interior_nodes(surface, h_np), project_fn=project)
    print(f"{head}; {len(points):,} nodes, {len(cells):,} tets")
    print("| sliding nodes | flips below q | time (s) | mean q | min dihedral (deg) | mean q by surface nodes 0/1/2/3/4 |")
    print("| --- | ---: | ---: | ---: | ---: | --- |")
    for sliding, threshold in (("none", 0.7), ("none", 0.85), ("interface", 0.85), ("interface + box faces", 0.85)):
        t = time.perf_counter()
        slide = None if sliding == "none" else SurfaceSlide(
            points, surface.triangles, surface.node_inclusion, surface.box, ms.phi,
            surface.periodic_pairs if "box" in sliding else None)
        p, c, _ = optimise_mesh(points, cells, surface, threshold=threshold, slide=slide)
        seconds = time.perf_counter() - t
        count = "" if slide is None else f" ({int(slide.mask.sum()):,})"
        print(f"| {sliding}{count} | {threshold} | {seconds:.1f} | {report(p, c, surface.n_points)}", flush=True)


if __name__ == "__main__":
    main()
