"""Per-stage times and quality of the full 3D pipeline on a generated RVE (the shape of the paper's Table 1).

Usage: python benchmarks/bench_pipeline.py [--n 200 --volume-fraction 0.48 --grid 128 --iis 0.05 --seed 0]
Prints a table with the machine and date. Not a test: timings are never asserted.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--volume-fraction", type=float, default=0.48)
    parser.add_argument("--radius", type=float, nargs=2, default=(0.07, 0.02), help="mean, std of the radius")
    parser.add_argument("--min-gap", type=float, default=0.01)
    parser.add_argument("--grid", type=int, default=128)
    parser.add_argument("--iis", type=float, default=0.05)
    parser.add_argument("--h", type=float, default=None, help="uniform size instead of the size function")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--interior", choices=("bcc", "octree"), default="bcc")
    parser.add_argument("--input", default=None, help="mesh this input file instead of generating an RVE")
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxmesh import MeshConfig, load_input, mesh_rve, microstructure_from_specs, quality_report, random_inclusions

    box = (1.0, 1.0, 1.0)
    t0 = time.perf_counter()
    if args.input:
        ms = load_input(args.input)
    else:
        specs = random_inclusions(box, n=args.n, volume_fraction=args.volume_fraction, shape="sphere",
                                  radius=tuple(args.radius), min_gap=args.min_gap, seed=args.seed)
        ms = microstructure_from_specs(specs, box, (args.grid,) * 3)
    t_input = time.perf_counter() - t0
    config = MeshConfig(iis=args.iis, h=args.h, seed=args.seed, interior=args.interior)
    mesh = mesh_rve(ms, config, progress=print)
    q = quality_report(mesh)
    timings = mesh.metadata["timings"]

    print()
    print(f"# jaxmesh pipeline benchmark, {datetime.date.today().isoformat()}, {platform.node()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__} "
          f"on {jax.default_backend()}")
    print(f"# RVE: {args.input or 'generated'}, {len(ms.inclusions)} inclusions, volume fraction "
          f"{ms.volume_fraction():.4f}, grid {tuple(ms.grid_shape)}, iis {args.iis}, h {args.h}, "
          f"interior {args.interior}")
    print("| stage | time (s) |")
    print("| --- | --- |")
    print(f"| input (generate or read) | {t_input:.2f} |")
    for name, seconds in timings.items():
        print(f"| {name} | {seconds:.2f} |")
    print(f"| nodes / tets | {mesh.n_points} / {mesh.n_cells} |")
    print(f"| mean q / min q | {q['q_mean']:.3f} / {q['q_min']:.3f} |")
    print(f"| tets with q < 0.3 | {100 * q['frac_below']:.3f} % |")
    print(f"| min dihedral | {q['min_dihedral_deg']:.2f} deg |")
    print(f"| valid | {mesh.metadata['validation']['ok']} |")


if __name__ == "__main__":
    main()
