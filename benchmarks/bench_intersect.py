"""Benchmark of the self-intersection broad phase (`jaxmesh._intersect.candidate_pairs`).

Usage:
    .venv/bin/python benchmarks/bench_intersect.py [--cluster 15000]

Two surfaces of marching-cubes triangles: `uniform` (30 spheres on a 160^3 grid) and `graded` (the
same plus a speck of about --cluster tiny triangles, a sphere of radius 0.01 on its own fine grid:
the triangles a size function puts on a cap or a trace far thinner than a grid step). Per surface,
the time of the k-d tree broad phase and of the uniform-grid broad phase it replaced (cell twice the mean box
extent, kept here as the reference), and whether they give the same pairs. Ratios within one run.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import numpy as np
from skimage.measure import marching_cubes

from jaxmesh._intersect import candidate_pairs


def uniform_grid_pairs(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The broad phase before f82bb73: a uniform grid of cell 2 x mean box extent, pairs per cell."""
    p = points[tris]
    lo, hi = p.min(axis=1), p.max(axis=1)
    cell = 2.0 * float(np.mean(np.max(hi - lo, axis=1))) + 1e-300
    origin = lo.min(axis=0)
    i0 = np.floor((lo - origin) / cell).astype(np.int64)
    i1 = np.floor((hi - origin) / cell).astype(np.int64)
    span = i1 - i0 + 1
    count = span.prod(axis=1)
    tid = np.repeat(np.arange(len(tris)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sp = span[tid]
    ix = i0[tid, 0] + local % sp[:, 0]
    iy = i0[tid, 1] + (local // sp[:, 0]) % sp[:, 1]
    iz = i0[tid, 2] + local // (sp[:, 0] * sp[:, 1])
    dims = i1.max(axis=0) + 1
    key = (ix * dims[1] + iy) * dims[2] + iz
    order = np.argsort(key, kind="stable")
    key, tid = key[order], tid[order]
    pairs = [np.zeros((0, 2), np.int64)]
    for d in range(1, len(key)):  # one pass per member of the most crowded cell
        same = key[:-d] == key[d:]
        if not same.any():
            break
        pairs.append(np.stack([tid[:-d][same], tid[d:][same]], axis=1))
    pr = np.sort(np.vstack(pairs), axis=1)
    pr = pr[pr[:, 0] != pr[:, 1]]
    t = len(tris)
    key = np.unique(pr[:, 0] * t + pr[:, 1])
    pr = np.stack([key // t, key % t], axis=1)
    ok = np.all((lo[pr[:, 0]] <= hi[pr[:, 1]]) & (lo[pr[:, 1]] <= hi[pr[:, 0]]), axis=1)
    return pr[ok]


def sphere_field(n: int, centres: np.ndarray, radius: float, extent: float = 1.0):
    x = np.linspace(0.0, extent, n)
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    return np.min([np.linalg.norm(X - c, axis=-1) - radius for c in centres], axis=0), x[1]


def surfaces(cluster: int):
    phi, step = sphere_field(160, np.random.default_rng(0).random((30, 3)) * 0.7 + 0.15, 0.12)
    v, f, _, _ = marching_cubes(phi, 0.0, spacing=(step,) * 3)
    steps = np.sqrt(cluster / 37.7)  # marching cubes leaves ~37.7 (r / step)^2 triangles on a sphere
    small, fine = sphere_field(int(np.ceil(2.5 * steps)) + 1, np.full((1, 3), 0.0125), 0.01, 0.025)
    vs, fs, _, _ = marching_cubes(small, 0.0, spacing=(fine,) * 3)
    vs += 0.02  # a speck among the large triangles
    return {"uniform": (v, f), "graded": (np.vstack([v, vs]), np.vstack([f, fs + len(v)]))}


def timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cluster", type=int, default=15000, help="about how many tiny triangles the speck adds")
    args = ap.parse_args()
    print(f"# {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
          f"{os.cpu_count()} cores")
    print("| surface | triangles | pairs | k-d tree s | uniform grid s | grid / tree | same pairs |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name, (v, f) in surfaces(args.cluster).items():
        tree, t_tree = timed(candidate_pairs, v, f)
        grid, t_grid = timed(uniform_grid_pairs, v, f)
        print(f"| {name} | {len(f):,} | {len(tree):,} | {t_tree:.2f} | {t_grid:.2f} | {t_grid / t_tree:.1f} | "
              f"{np.array_equal(tree, grid)} |")


if __name__ == "__main__":
    main()
