"""Benchmark of the surface stage (paper 4.4-4.5): mesh_surfaces on a random RVE of spheres/ellipsoids.

Usage:
    .venv/bin/python benchmarks/bench_surface.py --n 200 --h-ratio 4 [--shape ellipsoid] [--png PATH]
    JAXMESH_SMOKE=1 .venv/bin/python benchmarks/bench_surface.py   # tiny run
    .venv/bin/python benchmarks/bench_surface.py --input phi.npz     # a file, with the CLI's size function

Prints a table: inclusions, triangles, nodes, time per sub-stage (interfaces, faces, intersection check),
quality figures, and the machine. Paper reference (MATLAB, 4.8): 17.3 s coarse, 53.1 s fine.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmesh  # noqa: E402
from jaxmesh import MeshConfig, load_input  # noqa: E402
from jaxmesh._faces import mesh_surfaces  # noqa: E402
from jaxmesh._generate import microstructure_from_specs, random_inclusions  # noqa: E402
from jaxmesh._quality import cell_quality, min_angles  # noqa: E402
from jaxmesh._sizing import SizeParams, size_function  # noqa: E402
from jaxmesh._surface_mesh import BOX_FACE, INTERFACE  # noqa: E402


def plot_surface(mesh, path, title=""):
    """Matplotlib 3D view of a SurfaceMesh: inclusions coloured, box faces grey (Fig. 10)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(8, 8))
    ax = fig.add_subplot(111, projection="3d")
    cmap = plt.get_cmap("tab20")
    face = mesh.kind == BOX_FACE
    # box faces: only the three faces at 0 (the back), so the inclusions stay visible
    p = mesh.points[mesh.triangles]
    back = face & np.any([(p[:, :, a] == 0.0).all(axis=1) for a in range(3)], axis=0)
    colors = np.where(mesh.sides[back, 0][:, None] > 0, cmap(mesh.sides[back, 0] % 20), (0.85, 0.85, 0.85, 1.0))
    ax.add_collection3d(Poly3DCollection(p[back], facecolors=colors, edgecolors="k", linewidths=0.1, alpha=0.6))
    iface = mesh.kind == INTERFACE
    ax.add_collection3d(Poly3DCollection(p[iface], facecolors=cmap(mesh.sides[iface, 0] % 20), edgecolors="k",
                                         linewidths=0.1))
    L = mesh.box
    ax.set_xlim(0, L[0]), ax.set_ylim(0, L[1]), ax.set_zlim(0, L[2])
    ax.set_box_aspect(L)
    ax.view_init(elev=25, azim=-60)
    ax.set_title(title)
    tmp = str(path) + ".tmp.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def main():
    smoke = os.environ.get("JAXMESH_SMOKE") == "1"
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4 if smoke else 200)
    ap.add_argument("--radius", type=float, default=0.12 if smoke else 0.06)
    ap.add_argument("--h-ratio", type=float, default=4.0, help="h = radius / h_ratio")
    ap.add_argument("--shape", default="sphere")
    ap.add_argument("--grid", type=int, default=32 if smoke else 96)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--png", default=None)
    ap.add_argument("--input", default=None, help="mesh the surfaces of this input file, with `jaxmesh mesh`'s "
                    "default size function (the options above other than --png are then unused)")
    args = ap.parse_args()
    if args.input:
        ms = load_input(args.input)
        h = size_function(ms, SizeParams(**MeshConfig().size_kwargs()))
        np.asarray(h.values)  # computed before the clock starts
    else:
        specs = random_inclusions((1.0, 1.0, 1.0), n=args.n, shape=args.shape, radius=(args.radius, 0.0),
                                  min_gap=2.0 / args.grid, seed=args.seed)
        ms = microstructure_from_specs(specs, (1.0, 1.0, 1.0), (args.grid,) * 3)
        h = args.radius / args.h_ratio
    t = time.perf_counter()
    mesh = mesh_surfaces(ms, h)
    total = time.perf_counter() - t
    q = cell_quality(mesh.points, mesh.triangles)
    a = min_angles(mesh.points, mesh.triangles)
    md = mesh.metadata
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, jax {jax.__version__} "
          f"({jax.default_backend()}); {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; "
          f"library {os.path.dirname(jaxmesh.__file__)}; input {args.input or 'generated'}")
    print("| inclusions | h | nodes | triangles | interfaces s | faces s | intersections s | total s | q mean | "
          "q min | min angle | 1% angle |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    h_text = f"{h:.4g}" if isinstance(h, float) else f"{float(h.values.min()):.4g}-{float(h.values.max()):.4g}"
    print(f"| {len(ms.inclusions)} | {h_text} | {mesh.n_points} | {mesh.n_triangles} | {md['time_interfaces']:.1f} | "
          f"{md['time_faces']:.1f} | {md.get('time_intersections', 0):.1f} | {total:.1f} | {q.mean():.3f} | "
          f"{q.min():.3f} | {a.min():.1f} | {np.quantile(a, 0.01):.1f} |")
    for kind, name in ((INTERFACE, "interface"), (BOX_FACE, "box face")):
        sel = mesh.kind == kind
        if sel.any():
            print(f"{name} triangles: {int(sel.sum())}, q mean {q[sel].mean():.3f}, min angle {a[sel].min():.1f} deg, "
                  f"{int((a[sel] < 20).sum())} below 20 deg")
    if args.png:
        plot_surface(mesh, args.png, f"{len(ms.inclusions)} inclusions, {mesh.n_triangles} triangles")


if __name__ == "__main__":
    main()
