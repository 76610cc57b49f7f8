"""Benchmark of the periodic 2D mesher (not a test; timings are printed, never asserted).

Input: 30 random ellipses (periodic RSA, ~40 % area fraction, gap 2 grid steps of a 256 grid,
analytic signed distances through Microstructure.from_functions). Mesh: uniform h chosen for
~50k triangles (or the size function with --iis). The mesher runs twice on the same input: the
first run includes every JAX compilation (level-set kernel, truss scan), the second is warm.
Prints the time of each stage, counts, quality, validation, the machine and the date.

Usage:  .venv/bin/python benchmarks/bench_mesh2d.py [--n 30] [--h 0.0068] [--iis IIS] [--seed 0]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

os.environ.setdefault("JAX_ENABLE_X64", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxmesh._generate import random_inclusions  # noqa: E402
from jaxmesh._mesh2d import mesh_2d  # noqa: E402
from jaxmesh._quality import cell_quality, min_angles  # noqa: E402
from jaxmesh._validate import validate  # noqa: E402
from jaxmesh.geometry._microstructure import Microstructure  # noqa: E402
from jaxmesh.geometry._shapes import ellipsoid_sdf, ellipsoid_volume  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--fraction", type=float, default=0.4)
    ap.add_argument("--grid", type=int, default=256)
    ap.add_argument("--h", type=float, default=0.0068, help="uniform size (~50k triangles at 0.0068)")
    ap.add_argument("--iis", type=float, default=None, help="use the size function with this iis instead")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    t0 = time.perf_counter()
    specs = random_inclusions((1.0, 1.0), n=args.n, volume_fraction=args.fraction, shape="ellipsoid",
                              radius=(0.08, 0.02), min_gap=2.0 / args.grid, seed=args.seed)
    fns = [ellipsoid_sdf(jnp.asarray(s.center), jnp.asarray(s.axes), jnp.asarray(s.rotation)) for s in specs]
    ms = Microstructure.from_functions(fns, (1.0, 1.0), (args.grid, args.grid),
                                       volumes=[float(ellipsoid_volume(s.axes)) for s in specs])
    t_input = time.perf_counter() - t0
    kwargs = {"iis": args.iis} if args.iis else {"h": args.h}

    runs = []
    for label in ("cold", "warm"):
        t0 = time.perf_counter()
        mesh = mesh_2d(ms, seed=args.seed, **kwargs)
        runs.append((label, time.perf_counter() - t0, mesh))
    mesh = runs[-1][2]
    t0 = time.perf_counter()
    report = validate(mesh, ms)
    t_validate = time.perf_counter() - t0
    q = cell_quality(mesh.points, mesh.cells)
    ang = min_angles(mesh.points, mesh.cells)

    print(f"# bench_mesh2d  {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, python {platform.python_version()}, jax {jax.__version__} "
          f"({jax.default_backend()}), float64")
    print(f"# input: {len(specs)} ellipses, area fraction {ms.volume_fraction():.3f}, grid {args.grid}^2 "
          f"(from_functions {t_input:.1f} s); size: {kwargs}")
    stages = list(runs[0][2].metadata["timings"])
    print(f"\n| stage | {' | '.join(r[0] + ' (s)' for r in runs)} |")
    print("| --- |" + " ---: |" * len(runs))
    for st in stages:
        print(f"| {st} | {' | '.join(f'{r[2].metadata['timings'][st]:.2f}' for r in runs)} |")
    print(f"| **total mesh_2d** | {' | '.join(f'{r[1]:.2f}' for r in runs)} |")
    print(f"| validate | {t_validate:.2f} | |")
    c = mesh.metadata["counts"]
    print(f"\npoints {mesh.n_points}, triangles {mesh.n_cells}, interface/box nodes {c['constrained_nodes']}, "
          f"crossings {c['n_crossings']}, refinement {c['refinement']}")
    print(f"relaxation: {mesh.metadata['relaxation']}")
    print(f"quality: mean q {q.mean():.3f}, min q {q.min():.3f}, q<0.5 {np.mean(q < 0.5):.2%}, "
          f"min angle {ang.min():.1f} deg, angles<20 {np.count_nonzero(ang < 20)}")
    print(f"validation: {'OK' if report.ok else 'FAILED'}")
    if not report.ok:
        print(report.summary())


if __name__ == "__main__":
    main()
