"""Microstructure.phi on analytic inclusions: one compiled call per kind against one call per inclusion.

Usage:
    python benchmarks/bench_phi.py                  # the Table-1 RVE (200 spheres, 128^3 grid)
    python benchmarks/bench_phi.py --shape ellipsoid --n 100 --grid 64

`Microstructure.phi` (and `label`) evaluate every analytic inclusion of one kind (sphere_sdf,
ellipsoid_sdf) in one compiled call over all the points within reach of them; the first reference
evaluates each inclusion's phi_fn on its own points, one call each (what phi did before). A periodic
analytic inclusion evaluates only the 2^d images nearest its centre per point (`_Periodized`'s
nearest_images); the second reference is phi over all 3^d images. All on the same points near the
interfaces, in one process; prints seconds per call and the largest differences. Not a test.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shape", choices=("sphere", "ellipsoid"), default="sphere")
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--volume-fraction", type=float, default=0.48)
    parser.add_argument("--min-gap", type=float, default=0.01)
    parser.add_argument("--grid", type=int, default=128)
    parser.add_argument("--points", type=int, nargs="+", default=(300, 3000, 30000))
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from bench_pipeline import commit
    from jaxmesh import microstructure_from_specs, random_inclusions
    from jaxmesh.geometry._microstructure import _PHI_MARGIN, Inclusion, Microstructure, _Periodized, evaluate

    specs = random_inclusions((1.0,) * 3, n=args.n, volume_fraction=args.volume_fraction, shape=args.shape,
                              radius=(0.08, 0.015), min_gap=args.min_gap, seed=0)
    ms = microstructure_from_specs(specs, (1.0,) * 3, (args.grid,) * 3)
    margin = _PHI_MARGIN * max(ms.spacing)
    every_image = [Inclusion(inc.id, _Periodized(inc.phi_fn.fn, inc.phi_fn.box, False), inc.lower, inc.upper,
                             inc.volume, inc.description) for inc in ms.inclusions]
    ms_every_image = Microstructure(ms.box, ms.periodic, every_image, ms.grid_shape, ms.dn1, ms.dn2, ms.nearest_id,
                                    ms.reach)
    kept = sum(bool(inc.phi_fn.nearest_images) for inc in ms.inclusions)

    def one_by_one(pts):
        out = np.full(len(pts), np.inf)
        for inc, sel in zip(ms.inclusions, ms._near_bounds(pts, margin)):
            if len(sel):
                out[sel] = np.minimum(out[sel], evaluate(inc.phi_fn, pts[sel]))
        return out

    rng = np.random.default_rng(0)
    print(f"# bench_phi, {datetime.date.today().isoformat()}, commit {commit()}, {platform.machine()}, "
          f"{len(ms.inclusions)} {args.shape}s ({kept} over the nearest images only), grid {args.grid}^3, "
          f"jax {jax.__version__} on {jax.default_backend()}")
    print("| points | one call per kind (s) | one call per inclusion (s) | ratio | all 3^d images (s) | ratio | "
          "max difference | max difference, all images |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for m in args.points:
        pts = rng.random((4 * m, 3))
        pts = pts[np.abs(ms.phi(pts)) < 3 * max(ms.spacing)][:m]  # near the interfaces: no grid fallback
        ms.phi(pts), one_by_one(pts), ms_every_image.phi(pts)  # compile all at these sizes
        times = {}
        for name, fn in (("stacked", ms.phi), ("one", one_by_one), ("every", ms_every_image.phi)):
            t = time.perf_counter()
            for _ in range(args.repeat):
                vals = fn(pts)
            times[name] = ((time.perf_counter() - t) / args.repeat, vals)
        diff = np.abs(times["stacked"][1] - times["one"][1]).max()
        diff_every = np.abs(times["stacked"][1] - times["every"][1]).max()
        print(f"| {len(pts):,} | {times['stacked'][0]:.4f} | {times['one'][0]:.4f} | "
              f"{times['one'][0] / times['stacked'][0]:.1f} | {times['every'][0]:.4f} | "
              f"{times['every'][0] / times['stacked'][0]:.1f} | {diff:.1e} | {diff_every:.1e} |", flush=True)


if __name__ == "__main__":
    main()
