"""Per-stage times, counts, quality and peak memory of the full 3D pipeline (the shape of the paper's Table 1).

Usage:
    python benchmarks/bench_pipeline.py --preset coarse        # Table 1, coarse row
    python benchmarks/bench_pipeline.py --preset fine          # Table 1, fine row
    python benchmarks/bench_pipeline.py --table1               # both, one process each
    python benchmarks/bench_pipeline.py --n 200 --iis 0.05 ... # any other RVE / setting
    python benchmarks/bench_pipeline.py --input rve.npz        # a given input file

Table 1 of the paper (MATLAB): 222 inclusions at 50.87 %, coarse 50,839 nodes / 305,892 tets
(iis = 0.05), fine 366,536 nodes / 2,178,896 tets (iis = 0.03). The paper gives neither its gaps
nor its narrowness setting, so the presets are chosen to land near those counts:

* Geometry (both presets): 200 spheres wanted at 48 %, radius ~ N(0.08, 0.015) truncated,
  minimum gap 0.01, seed 0, 128^3 grid. At 48 % with 200 spheres the gap cannot be much wider:
  with radius N(0.08, 0.015) the generator jams at gap 0.02 (effective fraction of the spheres
  grown by half the gap ~0.68, above random close packing), and gap 0.01 is what issue 2 uses.
* Size function: with gaps of 0.01 the narrowness term (h_nar = DN2 / nb_el) sets h almost
  everywhere, so iis alone barely changes the mesh: on 180 spheres of radius N(0.081, 0.015) the
  predicted count (c * integral of h^-3, `SizeField.element_count`) was the same for iis 0.05
  and 0.03 at nb_el 3 (4.7M) and at nb_el 1 (0.59M). The presets therefore also set nb_el:
  coarse iis 0.05, nb_el 0.5 (half an element across the narrowest gaps); fine iis 0.03, nb_el 1.25
  (nb_el 1 gave 1.40M tets; `--estimate` predicted 648k at 1.0, 873k at 1.2, 1.0M at 1.3 on 2026-11-28).
  Measured on 2026-11-28 (benchmarks/README.md): coarse 321k tets at commit 94a7df0 (nb_el 0.5; it
  failed in the surfaces before the thin-cap and fold fixes), where nb_el 0.75 gave 791k and a mean
  q of 0.838 instead of 0.822; fine 1.40M at nb_el 1, 2.23M at nb_el 1.25 (fdf44f6, with box gaps;
  coarse then 346k). `--estimate` prints the predicted count of a setting
  without meshing.

Prints per-stage times (size, surfaces, volume sub-stages: interior nodes, Delaunay + recovery,
labels, relaxation, slivers; validation, quality report), node / tet counts, mean q, % q < 0.3,
min dihedral, validity, peak RSS after each stage, machine, date and commit. Not a test: timings
are never asserted. `--surface-cache file.npz` stores the surface mesh (and reuses it when the
file exists; the printed surface time is then the one stored with it, marked cached).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np

PRESETS = {  # Table 1 rows: mesh settings (the geometry is the same, see the docstring)
    "coarse": {"iis": 0.05, "nb_el": 0.5},
    "fine": {"iis": 0.03, "nb_el": 1.25},
}


def peak_rss_gb() -> float:
    """Peak resident memory of this process so far (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


class StageRows(list):
    """(stage, seconds as text, peak RSS so far or None) rows; prints each as it comes (long runs)."""

    def append(self, row):
        super().append(row)
        rss = "" if row[2] is None else f", peak RSS {row[2]:.2f} GiB"
        print(f"[bench] {row[0]}: {row[1]} s{rss}", flush=True)


def save_surface(path: str, surface, seconds: float, h_values: np.ndarray) -> None:
    extra = {f"pair_{a}": np.asarray(p) for a, p in surface.periodic_pairs.items()}
    np.savez(path, points=surface.points, triangles=surface.triangles, sides=surface.sides, kind=surface.kind,
             node_inclusion=surface.node_inclusion, box=np.asarray(surface.box), seconds=seconds,
             h_values=h_values, **extra)


def load_surface(path: str):
    from jaxmesh._surface_mesh import SurfaceMesh

    d = np.load(path)
    pairs = {int(k[5:]): d[k] for k in d.files if k.startswith("pair_")}
    surface = SurfaceMesh(d["points"], d["triangles"], d["sides"], d["kind"], d["node_inclusion"],
                          tuple(d["box"]), pairs)
    return surface, float(d["seconds"])


def commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=os.path.dirname(os.path.abspath(__file__)), check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", ":/jaxmesh"],
                               capture_output=True, text=True, cwd=os.path.dirname(os.path.abspath(__file__)),
                               check=True).stdout.strip()
        return out + (" (jaxmesh/ modified)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None, help="a Table 1 row (sets iis, nb_el)")
    parser.add_argument("--table1", action="store_true", help="run the coarse and the fine preset, one process each")
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--volume-fraction", type=float, default=0.48)
    parser.add_argument("--radius", type=float, nargs=2, default=(0.08, 0.015), help="mean, std of the radius")
    parser.add_argument("--min-gap", type=float, default=0.01)
    parser.add_argument("--grid", type=int, default=128)
    parser.add_argument("--iis", type=float, default=None, help="default 0.05, or the preset's")
    parser.add_argument("--nb-el", type=float, default=None, help="elements across the narrowest gaps (default 3, "
                        "or the preset's)")
    parser.add_argument("--grad", type=float, default=None, help="gradient limit of the size function (default "
                        "MeshConfig's 0.3, or the preset's)")
    parser.add_argument("--h", type=float, default=None, help="uniform size instead of the size function")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--input", default=None, help="mesh this input file instead of generating an RVE")
    parser.add_argument("--surface-cache", default=None, help=".npz to store / reuse the surface mesh (with a preset: name_<preset>.npz)")
    parser.add_argument("--compilation-cache", default=None, help="persistent XLA cache folder (as the CLI's "
                        "~/.cache/jaxmesh/xla): run twice to time a warm start")
    parser.add_argument("--estimate", action="store_true", help="only print the size function's predicted count")
    args = parser.parse_args(argv)
    chosen = PRESETS[args.preset] if args.preset else {"iis": 0.05, "nb_el": 3.0}
    args.iis = chosen["iis"] if args.iis is None else args.iis  # explicit options win over the preset
    args.nb_el = chosen["nb_el"] if args.nb_el is None else args.nb_el
    args.grad = chosen.get("grad") if args.grad is None else args.grad  # None: MeshConfig's default
    return args


def run(args) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)

    if args.compilation_cache:
        from jaxmesh import enable_compilation_cache

        enable_compilation_cache(args.compilation_cache)

    from jaxmesh import (MeshConfig, cell_quality, load_input, microstructure_from_specs, quality_report,
                         random_inclusions)
    from jaxmesh._faces import mesh_surfaces
    from jaxmesh._sizing import SizeParams, predicted_element_count, size_function
    from jaxmesh._surface import evaluate_size
    from jaxmesh._validate import validate
    from jaxmesh._volume import tetrahedralize
    from jaxmesh._volume_recover import levelset_projector

    code = commit()  # read now: the library imported at the start is what runs
    rows = StageRows()
    box = (1.0, 1.0, 1.0)
    t = time.perf_counter()
    if args.input:
        ms = load_input(args.input)
    else:
        specs = random_inclusions(box, n=args.n, volume_fraction=args.volume_fraction, shape="sphere",
                                  radius=tuple(args.radius), min_gap=args.min_gap, seed=args.seed)
        ms = microstructure_from_specs(specs, box, (args.grid,) * 3)
    rows.append(("input (generate or read)", f"{time.perf_counter() - t:.2f}", peak_rss_gb()))
    grad = {} if args.grad is None else {"grad": args.grad}
    config = MeshConfig(iis=args.iis, nb_el=args.nb_el, h=args.h, seed=args.seed, **grad)
    args.grad = config.grad

    t = time.perf_counter()
    if args.h is not None:
        h_jax = float(args.h)
        h_np = lambda p: np.full(len(p), float(args.h))  # noqa: E731
        h_values = np.full((1, 1, 1), float(args.h))
    else:
        field = size_function(ms, SizeParams(**config.size_kwargs()))
        h_values = np.asarray(field.values)  # blocks until computed
        h_jax = field
        h_np = lambda p: evaluate_size(field, p)  # noqa: E731
    rows.append((f"size function (h in [{h_values.min():.4f}, {h_values.max():.4f}])",
                 f"{time.perf_counter() - t:.2f}", peak_rss_gb()))
    predicted = float(predicted_element_count(h_values, ms.box))
    if args.estimate:
        print(f"predicted count (c * integral h^-3): {predicted:.0f}; {len(ms.inclusions)} inclusions, "
              f"volume fraction {ms.volume_fraction():.4f}, iis {args.iis}, nb_el {args.nb_el}, grad {args.grad}")
        return

    t = time.perf_counter()
    cache = args.surface_cache
    if cache and args.preset:  # one cache per preset: --table1 passes the same name to both
        cache = cache.removesuffix(".npz") + f"_{args.preset}.npz"
    cached = bool(cache and os.path.exists(cache))
    if cached:
        surface, t_surf = load_surface(cache)
    else:
        surface = mesh_surfaces(ms, h_jax)
        t_surf = time.perf_counter() - t
        if cache:
            save_surface(cache, surface, t_surf, h_values)
    rows.append((f"surfaces ({surface.n_points:,} nodes, {surface.n_triangles:,} triangles)"
                 + (", cached from an earlier run" if cached else ""), f"{t_surf:.2f}", peak_rss_gb()))

    t = time.perf_counter()
    mesh, kept_surface = tetrahedralize(surface, None, h_fn=h_np, project_fn=levelset_projector(ms.inclusion_phi),
                                        label_fn=ms.label, phi_fn=ms.phi, return_surface=True)
    t_vol = time.perf_counter() - t
    vol_peak = peak_rss_gb()
    times = mesh.metadata["times"]
    for key, label in (("interior_nodes", "interior nodes (graded BCC)"), ("delaunay_recovery", "Delaunay + recovery"),
                       ("relax", "relaxation (truss; off by default)"), ("slivers", "flips, smoothing, slivers"),
                       ("labels", "labels (last call)")):
        if key in times:
            rows.append((f"  volume: {label}", f"{times[key]:.2f}", None))
    rows.append((f"volume total ({mesh.n_points:,} nodes, {mesh.n_cells:,} tets)", f"{t_vol:.2f}", vol_peak))

    t = time.perf_counter()
    report = validate(mesh, ms)
    rows.append(("validate (8 checks)", f"{time.perf_counter() - t:.2f}", peak_rss_gb()))
    t = time.perf_counter()
    q = quality_report(mesh)
    rows.append(("quality report", f"{time.perf_counter() - t:.2f}", peak_rss_gb()))
    total = sum(float(r[1]) for r in rows if not r[0].startswith("  "))

    vinfo = mesh.metadata["volume"]
    print()
    print(f"# jaxmesh pipeline benchmark, {datetime.date.today().isoformat()}, commit {code}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB, jax {jax.__version__} on "
          f"{jax.default_backend()}, load average {os.getloadavg()[0]:.1f} at the end, compilation cache "
          f"{args.compilation_cache or 'off'}")
    print(f"# RVE: {args.input or 'generated'}, {len(ms.inclusions)} inclusions, volume fraction "
          f"{ms.volume_fraction():.4f}, min gap {args.min_gap}, radius {tuple(args.radius)}, grid "
          f"{tuple(ms.grid_shape)}; preset {args.preset}: iis {args.iis}, nb_el {args.nb_el}, grad {args.grad}, h {args.h}; "
          f"predicted count {predicted:.0f}")
    print("| stage | time (s) | peak RSS so far (GiB) |")
    print("| --- | ---: | ---: |")
    for name, seconds, rss in rows:
        print(f"| {name} | {seconds} | {'' if rss is None else f'{rss:.2f}'} |")
    print(f"| **total** | **{total:.2f}** | {peak_rss_gb():.2f} |")
    print()
    print(f"nodes {mesh.n_points:,}, tets {mesh.n_cells:,}; mean q {q['q_mean']:.3f}, min q {q['q_min']:.3f}, "
          f"tets with q < 0.3: {100 * q['frac_below']:.3f} %, min dihedral {q['min_dihedral_deg']:.2f} deg; "
          f"valid {report.ok}" + ("" if report.ok else f" (failed: {', '.join(report.failed)})"))
    # where the quality deficit sits: tets by their number of surface nodes (fixed: smoothing cannot move them)
    cell_q = cell_quality(mesh.points, mesh.cells)
    on_surface = (mesh.cells < kept_surface.n_points).sum(axis=1)
    print("mean q by surface nodes per tet: " + ", ".join(
        f"{k}: {np.mean(on_surface == k):.1%} of tets, q {cell_q[on_surface == k].mean():.3f}"
        for k in range(5) if np.any(on_surface == k)))
    print("volume: " + ", ".join(f"{k} {vinfo[k]}" for k in ("missing_first", "rounds", "interior_removed",
                                                               "surface_splits", "slivers_before", "slivers_after",
                                                               "inserted", "opt_flips", "opt_moves") if k in vinfo))


def main() -> None:
    args = parse_args()
    if args.table1:
        rest = [a for a in sys.argv[1:] if a != "--table1"]
        for preset in ("coarse", "fine"):
            print(f"## preset {preset}", flush=True)
            subprocess.run([sys.executable, os.path.abspath(__file__), "--preset", preset, *rest], check=False)
        return
    run(args)


if __name__ == "__main__":
    main()
