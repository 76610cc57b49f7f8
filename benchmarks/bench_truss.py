"""Benchmark of the truss engine kernels on CPU (not a test; timings are printed, never asserted).

Mesh: a jittered 47^3 Kuhn (Freudenthal) lattice of the unit cube: 103,823 nodes and 700,534 bars
(the 7 edge directions of the 6-tet cube split), box-face nodes paired periodically with the
face-normal axis locked. Measured, after a warm-up call and with block_until_ready:
  - force kernel: -grad of the bar energy (jit(truss_forces));
  - scan step: one full constrained Euler step inside lax.scan (target lengths from h_fn, forces,
    periodic averaging, constraint filter, re-imposed translations), per step over a 20-step scan;
  - scan step + surface: the same with 10% of the nodes on a level set (reaction, normal filter,
    two Newton projections);
  - grad of scan + surface: jax.grad of a scalar of the final points w.r.t. the level set's radius,
    reverse mode through the whole scan.
in float32 and float64. Runs in about a minute on 2 cores.

Usage:  .venv/bin/python benchmarks/bench_truss.py [--n 47] [--steps 20] [--repeat 3]
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

from jaxmesh._truss import TrussConfig, make_constraints, relax_fixed_topology, truss_forces  # noqa: E402

DIRECTIONS = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)]


def kuhn_lattice(n: int, seed: int = 0):
    """Points (n^3, 3) of a jittered lattice of [0, 1]^3, bars (m, 2), constraints with periodic faces."""
    h = 1.0 / (n - 1)
    idx = np.arange(n**3).reshape(n, n, n)
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = g * h
    bars = []
    for dx, dy, dz in DIRECTIONS:
        a = idx[: n - dx, : n - dy, : n - dz].ravel()
        b = idx[dx:, dy:, dz:].ravel()
        bars.append(np.stack([a, b], 1))
    bars = np.concatenate(bars)
    on_face = (g == 0) | (g == n - 1)
    rng = np.random.default_rng(seed)
    pts = pts + np.where(on_face, 0.0, rng.uniform(-0.1 * h, 0.1 * h, pts.shape))  # faces stay exact
    pairs = []
    for ax in range(3):
        lo = np.flatnonzero(g[:, ax] == 0)
        off = np.zeros(3)
        off[ax] = 1.0
        hi = lo + (n - 1) * n ** (2 - ax)  # same lattice row on the opposite face
        pairs += [(int(i), int(j), off) for i, j in zip(lo, hi)]
    cons = make_constraints(len(pts), 3, locked_axes=on_face, periodic_pairs=pairs)
    return pts, bars, cons


def timed(fn, *args, repeat: int):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))  # warm-up: compile + first run
    compile_s = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best, compile_s


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=47, help="lattice points per axis (47 -> 103,823 nodes, 700,534 bars)")
    ap.add_argument("--steps", type=int, default=20, help="Euler steps per scan")
    ap.add_argument("--repeat", type=int, default=3, help="timed repetitions (best is reported)")
    args = ap.parse_args()

    pts, bars_np, cons64 = kuhn_lattice(args.n)
    # surface nodes: the lattice nodes in a shell around the sphere |x - 0.5| = 0.3 (about 5%)
    surface = np.abs(np.linalg.norm(pts - 0.5, axis=1) - 0.3) < 1.0 / (args.n - 1)
    print(f"# truss benchmark  {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# machine: {platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}")  # fmt: skip
    print(f"# nodes {len(pts):,}  bars {len(bars_np):,}  surface nodes {surface.sum():,}  scan {args.steps} steps  "
          f"best of {args.repeat}")
    print(f"{'kernel':<24}{'dtype':<9}{'ms/call':>10}{'ms/step':>10}{'compile s':>11}")

    for dtype in (jnp.float32, jnp.float64):
        p = jnp.asarray(pts, dtype)
        cons = jax.tree_util.tree_map(lambda x: x.astype(dtype) if x.dtype == jnp.float64 else x, cons64)
        cons_s = make_constraints(len(pts), 3, locked_axes=np.asarray(cons64.locked_axes), on_surface=surface, dtype=dtype)
        bars, mask = jnp.asarray(bars_np, jnp.int32), jnp.ones(len(bars_np), bool)
        l0 = jnp.full(len(bars_np), 1.2 / (args.n - 1), dtype)

        def h_fn(x):
            return jnp.full(x.shape[:1], 1.0 / (args.n - 1), x.dtype) * (1.0 + 0.2 * x[:, 0])

        def phi_fn(x):
            return jnp.sqrt(jnp.sum((x - 0.5) ** 2, axis=1)) - 0.3

        # everything is an argument (not a closure constant), as in the driver: no constant folding
        forces = jax.jit(lambda q, b, m, t: truss_forces(q, b, m, t, 1.0))
        cfg = TrussConfig(dt=0.05)
        scan = jax.jit(lambda q, b, m, c: relax_fixed_topology(q, b, m, h_fn, c, args.steps, config=cfg))
        scan_s = jax.jit(lambda q, b, m, c: relax_fixed_topology(q, b, m, h_fn, c, args.steps, config=cfg,
                                                                 surface_phi_fn=phi_fn))  # fmt: skip
        def phi_r(x, radius):
            return jnp.sqrt(jnp.sum((x - 0.5) ** 2, axis=1)) - radius

        def loss(radius, q, b, m, c):  # reverse mode through the whole scan, w.r.t. the level set's radius
            out = relax_fixed_topology(q, b, m, h_fn, c, args.steps, config=cfg, surface_phi_fn=phi_r,
                                       phi_params=radius)
            return jnp.mean(jnp.sum((out - 0.5) ** 2, axis=1))

        grad_s = jax.jit(jax.grad(loss))
        name = jnp.dtype(dtype).name
        t, c = timed(forces, p, bars, mask, l0, repeat=args.repeat)
        print(f"{'force kernel':<24}{name:<9}{t * 1e3:>10.1f}{t * 1e3:>10.1f}{c:>11.2f}")
        for label, fn, cc in (("scan step", scan, cons), ("scan step + surface", scan_s, cons_s)):
            t, c = timed(fn, p, bars, mask, cc, repeat=args.repeat)
            out = fn(p, bars, mask, cc)
            assert out.dtype == dtype, out.dtype
            assert bool(jnp.all(jnp.isfinite(out)))
            print(f"{label:<24}{name:<9}{t * 1e3:>10.1f}{t * 1e3 / args.steps:>10.1f}{c:>11.2f}")
        radius = jnp.asarray(0.3, dtype)
        t, c = timed(grad_s, radius, p, bars, mask, cons_s, repeat=args.repeat)
        g = grad_s(radius, p, bars, mask, cons_s)
        assert bool(jnp.isfinite(g)), g
        print(f"{'grad of scan + surface':<24}{name:<9}{t * 1e3:>10.1f}{t * 1e3 / args.steps:>10.1f}{c:>11.2f}")

if __name__ == "__main__":
    main()
