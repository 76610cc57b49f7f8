"""Benchmark of the volume step: interior nodes, Delaunay + recovery, labels, quality optimisation
(flips + smoothing; the truss only with --truss), slivers.

Input: a synthetic periodic surface (jittered periodic box-face triangulation + icospheres on a
jittered lattice, fully inside the box), sized for about --tets tetrahedra.

    .venv/bin/python benchmarks/bench_volume.py --tets 300000          # the issue's coarse size
    .venv/bin/python benchmarks/bench_volume.py --tets 30000 --no-relax
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
from scipy.spatial import Delaunay

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from jaxmesh._mesh import make_periodic_pairs  # noqa: E402
from jaxmesh._quality import quality_report  # noqa: E402
from jaxmesh._surface_mesh import BOX_FACE, INTERFACE, OUTSIDE, SurfaceMesh  # noqa: E402
from jaxmesh._volume import VolumeConfig, tetrahedralize  # noqa: E402


def _box_faces(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    idx = np.stack(np.meshgrid(*[np.arange(n + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    idx = idx[((idx == 0) | (idx == n)).any(axis=1)]
    on = (idx == 0) | (idx == n)
    wrapped = idx % n
    table = rng.uniform(-0.2, 0.2, (n, n, n, 3, 4)) / n  # jitter by wrapped index: periodic
    pts = idx / n
    for a in range(3):
        free = ~on[:, a]
        w = wrapped[free]
        pts[free, a] += table[w[:, 0], w[:, 1], w[:, 2], a, on[free].sum(axis=1)]
    tris = []
    lookup = {tuple(i): k for k, i in enumerate(idx)}
    for a in range(3):
        ax = [b for b in range(3) if b != a]
        lo = np.flatnonzero(idx[:, a] == 0)
        hi = np.array([lookup[tuple(idx[i] + n * np.eye(3, dtype=int)[a])] for i in lo])
        tr = np.asarray(Delaunay(pts[lo][:, ax]).simplices)
        for face, sgn in ((lo, -1.0), (hi, 1.0)):
            t = face[tr]
            p = pts[t]
            flip = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, a] * sgn < 0
            t[flip] = t[flip][:, [0, 2, 1]]
            tris.append(t)
    return pts, np.concatenate(tris)


def _icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(level):
        cache, verts, faces = {}, list(v), []

        def mid(i, j):
            k = (min(i, j), max(i, j))
            if k not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[k] = len(verts) - 1
            return cache[k]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            faces += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        v, f = np.array(verts), np.array(faces)
    nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    out = np.einsum("ij,ij->i", nrm, v[f].mean(axis=1)) > 0
    f[~out] = f[~out][:, [0, 2, 1]]
    return v, f


def synthetic_surface(h: float, per_axis: int, seed: int = 0) -> SurfaceMesh:
    """Box faces at ~h and per_axis^3 spheres (radius 0.3 / per_axis) with edges ~h, inside the box."""
    rng = np.random.default_rng(seed)
    pts, tris = _box_faces(max(2, round(1 / h)), rng)
    parts_p, parts_t, sides, kinds, inc = [pts], [tris], [np.tile([0, OUTSIDE], (len(tris), 1))], \
        [np.full(len(tris), BOX_FACE)], [np.zeros(len(pts), np.int64)]
    r = 0.3 / per_axis
    level = int(np.clip(np.round(np.log2(1.05 * r / h)), 0, 5))
    v, f = _icosphere(level)
    off, k = len(pts), 0
    for c in np.stack(np.meshgrid(*[(np.arange(per_axis) + 0.5) / per_axis] * 3, indexing="ij"), -1).reshape(-1, 3):
        k += 1
        c = c + rng.uniform(-0.05, 0.05, 3) / per_axis
        parts_p.append(c + r * v)
        parts_t.append(f + off)
        sides.append(np.tile([k, 0], (len(f), 1)))
        kinds.append(np.full(len(f), INTERFACE))
        inc.append(np.full(len(v), k))
        off += len(v)
    points = np.concatenate(parts_p)
    box = (1.0, 1.0, 1.0)
    return SurfaceMesh(points, np.concatenate(parts_t), np.concatenate(sides), np.concatenate(kinds),
                       np.concatenate(inc), box, make_periodic_pairs(points, box))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tets", type=int, default=300_000, help="approximate number of tets")
    ap.add_argument("--spheres", type=int, default=4, help="spheres per axis")
    ap.add_argument("--no-relax", action="store_true", help="skip the optimisation and sliver removal")
    ap.add_argument("--truss", action="store_true", help="relax with the truss first (VolumeConfig.truss)")
    args = ap.parse_args()
    h = (6 * np.sqrt(2) / args.tets) ** (1 / 3) * 1.1  # regular tets of edge h: 6 sqrt(2) / h^3 per unit volume
    t = time.perf_counter()
    surface = synthetic_surface(h, args.spheres)
    t_surf = time.perf_counter() - t
    truss = None
    if args.truss:
        from jaxmesh._truss import TrussConfig

        truss = TrussConfig(dt=0.2, fscale=1.0, alpha_ramp_iterations=0, alpha_start=1.0, max_iterations=40,
                            max_retriangulations=6, retriangulate_tol=0.3, max_dt_retries=0, ball_vertex_stiffness=1.0,
                            ball_vertex_quality=0.3, final_triangulation=False)
    cfg = VolumeConfig(relax=not args.no_relax, truss=truss)
    h_fn = lambda p: np.full(len(p), h)  # noqa: E731
    if cfg.truss is not None:  # warm-up: compile the truss scan on a tiny case
        tetrahedralize(synthetic_surface(0.25, 1), h_fn=lambda p: np.full(len(p), 0.25), config=cfg)
    t = time.perf_counter()
    mesh = tetrahedralize(surface, h_fn=h_fn, config=cfg)
    total = time.perf_counter() - t
    rep = quality_report(mesh)
    vol = mesh.metadata["volume"]
    print(f"machine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} CPUs, "
          f"python {platform.python_version()}")
    print(f"h = {h:.4f}, surface: {surface.n_points} nodes, {surface.n_triangles} triangles (built in {t_surf:.2f} s)")
    print(f"mesh: {mesh.n_points} nodes, {mesh.n_cells} tets")
    print(f"{'stage':<22}{'seconds':>10}")
    for k, v in mesh.metadata["times"].items():
        print(f"{k:<22}{v:>10.2f}")
    print(f"{'total (measured)':<22}{total:>10.2f}")
    print(f"recovery: first missing {vol['missing_first']}, rounds {vol['rounds']}, removed {vol['interior_removed']}, "
          f"splits {vol['surface_splits']}")
    keys = ("q_mean", "q_min", "frac_below", "min_dihedral_deg")  # frac_below: share of tets with q < 0.3
    print("quality: " + ", ".join(f"{k} {rep[k]:.4g}" for k in keys if k in rep))
    for k in ("relax_stop", "relax_iterations", "slivers_before", "slivers_after", "opt_flips", "opt_moves", "inserted"):
        if k in vol:
            print(f"  {k}: {vol[k]}")


if __name__ == "__main__":
    main()
