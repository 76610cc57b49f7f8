"""Cost of scoring the frames of a periodic grid (`jaxmesh._pipeline.box_plane_clearances`), against the
microstructure build it follows.

Usage:
    python benchmarks/bench_frame.py                       # the Table-1 geometry (128^3)
    python benchmarks/bench_frame.py --input g.npz         # a given input file

Rows: the microstructure build (read or generate), the score of the frame as given (every periodic
`mesh_rve` computes it to decide whether the default rolls), and the score of every frame (roll='auto',
the default's roll of a grazing box, and the retry after a failure), best of --repeat runs each, with
their ratios to the build. Not a test.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import time

import jax

jax.config.update("jax_enable_x64", True)


def best_of(repeat: int, fn):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def main() -> None:
    from jaxmesh import load_input, microstructure_from_specs, random_inclusions
    from jaxmesh._pipeline import box_plane_clearances

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--input", default=None, help="a periodic input file instead of the generated RVEs")
    parser.add_argument("--grid", type=int, nargs="+", default=[128],
                        help="grids of the generated RVE (gap 0.01: 128 or finer)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    print(f"# {platform.machine()}, {os.cpu_count()} cores, {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
          f"commit {code}")
    cases = [(args.input, lambda: load_input(args.input))] if args.input else []
    if not args.input:
        box = (1.0, 1.0, 1.0)
        specs = random_inclusions(box, n=200, volume_fraction=0.48, shape="sphere", radius=(0.08, 0.015),
                                  min_gap=0.01, seed=0)
        cases = [(f"200 spheres at 48 %, {n}^3", lambda n=n: microstructure_from_specs(specs, box, (n,) * 3))
                 for n in args.grid]
    print("| input | build (s) | frame as given (s) | every frame (s) | ratios to the build "
          "| clearance as given / best |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, build in cases:
        t_build, ms = best_of(args.repeat, build)
        t_origin, _ = best_of(args.repeat, lambda ms=ms: box_plane_clearances(ms, origin_only=True))
        t_all, (clear, best) = best_of(args.repeat, lambda ms=ms: box_plane_clearances(ms))
        print(f"| {name} | {t_build:.2f} | {t_origin:.2f} | {t_all:.2f} | {t_origin / t_build:.2f} / "
              f"{t_all / t_build:.2f} | {clear[(0,) * ms.dim]:.3g} / {clear[best]:.3g} at {list(best)} |")


if __name__ == "__main__":
    main()
