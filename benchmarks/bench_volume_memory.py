"""Peak resident memory and time per sub-stage of the volume step, validation and quality report.

A sampling thread reads the resident set size every 10 ms; each wrapped function records the
highest value seen while it ran (its peak) and that peak minus the RSS when it started (delta).
Nested functions are listed under their own names (conforming_delaunay holds delaunay_tets, ...).

    python benchmarks/bench_volume_memory.py --graded 0.02 0.06 --spheres 5     # synthetic, ~1M tets
    python benchmarks/bench_volume_memory.py --surface /tmp/surf_fine.npz        # a cached RVE surface
                                              # (bench_pipeline.py --surface-cache, with its size grid)
Linux only (/proc/self/statm). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
import threading
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class Tracker:
    """Per-function calls, seconds, peak RSS and peak-minus-entry RSS, sampled by a daemon thread."""

    def __init__(self, period: float = 0.01):
        self.active: list[list[int]] = []  # [rss at entry, peak] per running call
        self.stats: dict[str, list] = {}
        self.lock = threading.Lock()
        threading.Thread(target=self._sample, args=(period,), daemon=True).start()

    def _sample(self, period):
        while True:
            r = rss_bytes()
            with self.lock:
                for frame in self.active:
                    frame[1] = max(frame[1], r)
            time.sleep(period)

    def measure(self, label: str, fn, *args, **kwargs):
        r0 = rss_bytes()
        frame = [r0, r0]
        with self.lock:
            self.active.append(frame)
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            dt = time.perf_counter() - t
            with self.lock:
                self.active = [f for f in self.active if f is not frame]
            s = self.stats.setdefault(label, [0, 0.0, 0, 0])
            s[0] += 1
            s[1] += dt
            s[2] = max(s[2], frame[1])
            s[3] = max(s[3], frame[1] - r0)

    def wrap(self, module, name: str) -> None:
        fn = getattr(module, name)
        setattr(module, name, functools.wraps(fn)(lambda *a, **k: self.measure(name, fn, *a, **k)))


def graded_surface(h_fine: float, h_box: float, per_axis: int):
    """Box faces at h_box and per_axis^3 spheres at h_fine (bench_volume's synthetic pieces), and a
    size function growing from h_fine at the spheres with slope 0.3 up to h_box."""
    from scipy.spatial import cKDTree

    from bench_volume import synthetic_surface
    from jaxmesh._mesh import make_periodic_pairs
    from jaxmesh._surface_mesh import BOX_FACE, SurfaceMesh

    fine, coarse = synthetic_surface(h_fine, per_axis), synthetic_surface(h_box, 1)
    cb, fb = coarse.kind == BOX_FACE, fine.kind == BOX_FACE
    nb, nfb = coarse.triangles[cb].max() + 1, fine.triangles[fb].max() + 1  # box nodes come first
    pts = np.concatenate([coarse.points[:nb], fine.points[nfb:]])
    box = (1.0, 1.0, 1.0)
    surface = SurfaceMesh(pts, np.concatenate([coarse.triangles[cb], fine.triangles[~fb] - nfb + nb]),
                          np.concatenate([coarse.sides[cb], fine.sides[~fb]]),
                          np.concatenate([coarse.kind[cb], fine.kind[~fb]]),
                          np.concatenate([coarse.node_inclusion[:nb], fine.node_inclusion[nfb:]]), box,
                          make_periodic_pairs(pts, box))
    centres = np.stack(np.meshgrid(*[(np.arange(per_axis) + 0.5) / per_axis] * 3, indexing="ij"), -1).reshape(-1, 3)
    tree, radius = cKDTree(centres), 0.3 / per_axis

    def h_fn(p):
        d, _ = tree.query(p)
        return np.minimum(h_box, h_fine + 0.3 * np.abs(d - radius))

    return surface, h_fn


def cached_surface(path: str):
    """The SurfaceMesh and a NumPy size function (periodic linear on the stored grid) of a bench_pipeline cache."""
    from scipy.interpolate import RegularGridInterpolator

    from bench_pipeline import load_surface

    surface, _ = load_surface(path)
    values = np.load(path)["h_values"]
    box = np.asarray(surface.box)
    axes = [np.arange(k + 1) * (L / k) for k, L in zip(values.shape, box)]
    interp = RegularGridInterpolator(axes, np.pad(values, ((0, 1),) * 3, mode="wrap"))
    return surface, lambda p: interp(np.mod(p, box))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--surface", help="bench_pipeline.py --surface-cache file")
    ap.add_argument("--graded", nargs=2, type=float, metavar=("H_SPHERES", "H_BOX"), default=(0.02, 0.06))
    ap.add_argument("--spheres", type=int, default=5, help="spheres per axis of the synthetic surface")
    ap.add_argument("--no-relax", action="store_true")
    args = ap.parse_args()

    from jaxmesh import _quality, _validate, _volume, _volume_relax

    tracker = Tracker()
    for name in ("interior_nodes", "distance_to_surface", "conforming_delaunay", "delaunay_tets", "missing_triangles",
                 "encroached_free_nodes", "split_edges", "label_cells"):
        tracker.wrap(_volume, name)
    for name in ("relax_volume", "remove_slivers", "optimise_mesh", "improve_topology", "smooth_vertices",
                 "insert_steiner", "min_dihedral", "cell_quality"):
        tracker.wrap(_volume_relax, name)
    if args.surface:
        surface, h_fn = cached_surface(args.surface)
    else:
        surface, h_fn = graded_surface(*args.graded, args.spheres)
    start = rss_bytes()
    mesh = tracker.measure("tetrahedralize (all)", _volume.tetrahedralize, surface, h_fn=h_fn,
                           config=_volume.VolumeConfig(relax=not args.no_relax))
    report = tracker.measure("validate (no microstructure)", _validate.validate, mesh)
    q = tracker.measure("quality_report", _quality.quality_report, mesh)

    print(f"# {platform.node()}, {os.cpu_count()} CPUs, python {platform.python_version()}, load average "
          f"{os.getloadavg()[0]:.1f} at the end")
    print(f"# input: {args.surface or f'graded synthetic {args.graded}, {args.spheres}^3 spheres'}; surface "
          f"{surface.n_points:,} nodes, {surface.n_triangles:,} triangles; mesh {mesh.n_points:,} nodes, "
          f"{mesh.n_cells:,} tets; RSS before the volume step {start / 2**30:.2f} GiB")
    print(f"# mean q {q['q_mean']:.3f}, q < 0.3: {100 * q['frac_below']:.3f} %, min dihedral "
          f"{q['min_dihedral_deg']:.2f} deg, valid {report.ok}")
    print("| function | calls | seconds | peak RSS (GiB) | peak - entry (GiB) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, (calls, seconds, peak, delta) in tracker.stats.items():
        print(f"| {name} | {calls} | {seconds:.1f} | {peak / 2**30:.2f} | {delta / 2**30:.2f} |")


if __name__ == "__main__":
    main()
