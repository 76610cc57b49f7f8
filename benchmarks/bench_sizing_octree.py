"""Size function h(x) and periodic octree: a Fig. 9-like 2D figure and 3D timings (not a test).

1. Figure (paper Fig. 9): a 2D RVE of random circles, its size function h(x) (iis, narrowness,
   curvature, gradient limiting) and the periodic quadtree nodes, written to
   benchmarks/figures/sizing_quadtree.png.
2. Timings (paper Table 1: size function 13.7 s, octree 1.3 s, MATLAB on a 4-core laptop): a 3D
   RVE of 200 random non-overlapping spheres on a 128^3 level-set grid, read as a level set
   (Microstructure.from_levelset, the paper's input). Each stage is run twice, the first call
   includes compilation; block_until_ready on JAX results.

Usage:  .venv/bin/python benchmarks/bench_sizing_octree.py [--n 128] [--count 200] [--skip-figure]
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
import numpy as np  # noqa: E402

from jaxmesh._generate import microstructure_from_specs, random_inclusions, sample_levelset  # noqa: E402
from jaxmesh._octree import periodic_octree_nodes  # noqa: E402
from jaxmesh._sizing import SizeParams, limit_gradient, size_function, size_sources, source_sizes  # noqa: E402
from jaxmesh.geometry._microstructure import Microstructure  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def figure(path: str) -> dict:
    """2D size function and quadtree nodes side by side (paper Fig. 9)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    specs = random_inclusions((1.0, 1.0), n=14, radius=(0.09, 0.04), min_gap=0.008, seed=3)
    ms = microstructure_from_specs(specs, (1.0, 1.0), (256, 256))
    field = size_function(ms, SizeParams(iis=0.03, nb_el=3.0, curv_alpha=0.5, grad=0.3))
    h = np.asarray(field.values)
    nodes = periodic_octree_nodes(h, field.box, interface_phi=ms.dn1)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.6))
    im = a.imshow(h.T, origin="lower", extent=(0, 1, 0, 1), cmap="viridis")
    fig.colorbar(im, ax=a, fraction=0.046, label="h(x)")
    x = np.arange(256) / 256
    for ax in (a, b):
        ax.contour(x, x, ms.dn1.T, levels=[0.0], colors="w" if ax is a else "r", linewidths=0.8)
        ax.set_aspect("equal")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
    a.set_title("h(x): iis 0.03, nb_el 3, alpha 0.5, g 0.3")
    o, s = nodes.cell_origin, nodes.cell_size
    zero = np.zeros(len(s))
    quads = np.stack([o, o + np.c_[s[:, 0], zero], o + s, o + np.c_[zero, s[:, 1]]], axis=1)
    b.add_collection(PolyCollection(quads, facecolors="none", edgecolors="0.7", linewidths=0.3))
    b.plot(nodes.points[:, 0], nodes.points[:, 1], ".", ms=1.5, color="k")
    b.set_title(f"periodic quadtree: {len(nodes.wrapped())} nodes, {nodes.removed} removed")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return {"nodes": len(nodes.wrapped()), "h": (float(h.min()), float(h.max()))}


def timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kw))
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=128)
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--skip-figure", action="store_true")
    args = ap.parse_args()
    if not args.skip_figure:
        path = os.path.join(HERE, "figures", "sizing_quadtree.png")
        info = figure(path)
        print(f"figure: {path} ({info['nodes']} quadtree nodes, h in [{info['h'][0]:.4f}, {info['h'][1]:.4f}])")

    shape = (args.n,) * 3
    t0 = time.perf_counter()
    specs = random_inclusions((1.0, 1.0, 1.0), n=args.count, radius=(0.06, 0.012), min_gap=0.02, seed=0)
    phi = sample_levelset(specs, (1.0, 1.0, 1.0), shape)
    ms = Microstructure.from_levelset(phi, (1.0, 1.0, 1.0))
    t_ms = time.perf_counter() - t0
    params = SizeParams(iis=0.05, nb_el=3.0, curv_alpha=0.5, grad=0.3)
    rows = []
    src, t1 = timed(size_sources, ms)
    _, t2 = timed(size_sources, ms)
    rows.append(("sources + DN2 + curvature", t1, t2))
    iis, nb_el, alpha, g, h_max, h_min = params.resolved()
    h0 = source_sizes(src.points, src.ids, src.dn2, src.kappa, iis, nb_el, alpha, h_min, src.box_gap)
    lg = lambda: limit_gradient(h0, src.points, ms.box, shape, g, h_max)  # noqa: E731
    _, t1 = timed(lg)
    _, t2 = timed(lg)
    rows.append(("gradient limiting (eq. 20)", t1, t2))
    field, t1 = timed(size_function, ms, params)
    _, t2 = timed(size_function, ms, params)
    rows.append(("size function total", t1, t2))
    h = np.asarray(field.values)
    nodes, t1 = timed(periodic_octree_nodes, h, ms.box, interface_phi=ms.dn1)
    _, t2 = timed(periodic_octree_nodes, h, ms.box, interface_phi=ms.dn1)
    rows.append(("octree nodes (balanced, removal)", t1, t2))

    print(f"\n# bench_sizing_octree  {datetime.datetime.now():%Y-%m-%d %H:%M}  {platform.node()}")
    print(f"# {platform.platform()}, {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}, "
          f"jax {jax.__version__} ({jax.default_backend()}), float64")
    print(f"# RVE: {len(ms.inclusions)} spheres (from {len(specs)} specs), grid {shape}, "
          f"from_levelset {t_ms:.1f} s; {src.points.shape[0]} interface sources; "
          f"h in [{h.min():.4f}, {h.max():.4f}]; {len(nodes.wrapped())} octree nodes "
          f"({nodes.removed} removed), {len(nodes.cell_depth)} leaves, depths {np.bincount(nodes.cell_depth)}")
    print(f"{'stage':36s} {'1st call [s]':>12s} {'2nd call [s]':>12s}")
    for name, a, b in rows:
        print(f"{name:36s} {a:12.2f} {b:12.2f}")
    print("paper (MATLAB, i7-6700HQ): size function 13.71 s, octree 1.26 s (coarse mesh)")


if __name__ == "__main__":
    main()
