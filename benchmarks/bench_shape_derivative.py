"""Cost of a shape derivative through a mesh: `move_interface_nodes` and jax.grad of a phase volume
with respect to every grid value, against meshing the same RVE.

Usage:
    python benchmarks/bench_shape_derivative.py                       # 20 spheres, 48^3 grid, iis 0.05
    python benchmarks/bench_shape_derivative.py --n 40 --grid 64

One process: the RVE is meshed once (`mesh_rve`, its seconds for scale), then the moved points (nodes
following the level of the grid's global cubic B-spline through them, `reference=` the mesh's values;
also how far the zero set of that B-spline lies from the mesh's interface nodes) and the gradient are each
compiled once (the first call) and timed over --repeat further calls, and the
gradient is checked along a random direction against central differences; the same for the mean effective
conductivity (`effective_conductivity`, JAX) and its gradient, with `homogenize_conductivity` (scipy) for
the value and its time, and its gradient with respect to the phase conductivities. Not a test.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--volume-fraction", type=float, default=0.25)
    parser.add_argument("--grid", type=int, default=48)
    parser.add_argument("--iis", type=float, default=0.05)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from bench_pipeline import commit
    from jaxmesh import (MeshConfig, Microstructure, effective_conductivity, homogenize_conductivity, interpolate,
                         make_levelset_grid, mesh_rve, move_interface_nodes, phase_volume, random_inclusions,
                         sample_levelset)

    box = (1.0, 1.0, 1.0)
    specs = random_inclusions(box, n=args.n, volume_fraction=args.volume_fraction, radius=(0.1, 0.02),
                              min_gap=0.03, seed=0)
    values = sample_levelset(specs, box, (args.grid,) * 3)
    t0 = time.perf_counter()
    mesh = mesh_rve(Microstructure.from_levelset(values), MeshConfig(iis=args.iis, seed=0))
    mesh_s = time.perf_counter() - t0
    nodes = len(mesh.interface_nodes())

    def phi(points, v):
        return interpolate(make_levelset_grid(v, box), points, order="cubic")

    inside = mesh.phase == 1
    v0 = jnp.asarray(values)
    zero_set = jax.jit(lambda v: move_interface_nodes(mesh, phi, v))
    moved = jax.jit(lambda v: move_interface_nodes(mesh, phi, v, reference=v0))
    volume = jax.jit(lambda v: phase_volume(move_interface_nodes(mesh, phi, v, reference=v0), mesh.cells, inside))
    gradient = jax.jit(jax.grad(lambda v: phase_volume(move_interface_nodes(mesh, phi, v, reference=v0), mesh.cells,
                                                       inside)))

    def timed(fn, x=v0):
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        first = time.perf_counter() - t
        t = time.perf_counter()
        for _ in range(args.repeat):
            out = jax.block_until_ready(fn(x))
        return first, (time.perf_counter() - t) / args.repeat, out

    move_first, move_s, points = timed(moved)
    grad_first, grad_s, grad = timed(gradient)
    direction = 0.01 * np.random.default_rng(0).standard_normal(values.shape)
    eps = 1e-4
    fd = float(volume(v0 + eps * direction) - volume(v0 - eps * direction)) / (2 * eps)
    ad = float(jnp.sum(grad * direction))
    print(f"# bench_shape_derivative, {datetime.date.today().isoformat()}, commit {commit()}, {platform.machine()}, "
          f"jax {jax.__version__} on {jax.default_backend()}")
    print(f"RVE: {len(specs)} spheres, grid {args.grid}^3, iis {args.iis}: {mesh.n_cells} cells, {nodes} interface "
          f"nodes, meshed in {mesh_s:.1f} s")
    step = 1.0 / args.grid
    offset = float(jnp.abs(zero_set(v0) - mesh.points).max())
    print(f"moved points (reference = the mesh's values): first call {move_first:.2f} s, then {move_s:.3f} s; max "
          f"|moved - mesh| at the mesh's values {float(jnp.abs(points - mesh.points).max()):.1e}; onto the zero set "
          f"of the global B-spline instead (no reference): {offset:.1e} = {offset / step:.3f} grid steps")
    print(f"grad of the inclusion volume w.r.t. {values.size} grid values: first call {grad_first:.2f} s, then "
          f"{grad_s:.3f} s ({grad_s / max(move_s, 1e-12):.1f}x the moved points)")
    print(f"directional derivative: autodiff {ad:.9e}, central differences {fd:.9e}, relative difference "
          f"{abs(ad - fd) / abs(fd):.1e}")

    conductivity = {0: 1.0, 1: 10.0}
    t = time.perf_counter()
    reference = homogenize_conductivity(mesh, conductivity, by="phase")
    scipy_s = time.perf_counter() - t
    k_mean = jax.jit(lambda v: jnp.trace(effective_conductivity(mesh, move_interface_nodes(mesh, phi, v, reference=v0),
                                                                conductivity, by="phase")) / 3)
    tensor = effective_conductivity(mesh, mesh.points, conductivity, by="phase")
    k_first, k_s, k0 = timed(k_mean)
    k_grad = jax.jit(jax.grad(lambda v: jnp.trace(effective_conductivity(
        mesh, move_interface_nodes(mesh, phi, v, reference=v0), conductivity, by="phase")) / 3))
    kg_first, kg_s, kg = timed(k_grad)
    kfd = float(k_mean(v0 + eps * direction) - k_mean(v0 - eps * direction)) / (2 * eps)
    kad = float(jnp.sum(kg * direction))
    print(f"effective conductivity (matrix 1, inclusions 10): mean {float(k0):.6f}; JAX tensor - "
          f"homogenize_conductivity {float(np.abs(np.asarray(tensor) - reference).max()):.1e} (scipy cg {scipy_s:.2f} s); "
          f"JAX: first call {k_first:.2f} s, then {k_s:.2f} s")
    print(f"its gradient w.r.t. the grid values: first call {kg_first:.2f} s, then {kg_s:.2f} s; along the random "
          f"direction autodiff {kad:.9e}, central differences {kfd:.9e}, relative difference {abs(kad - kfd) / abs(kfd):.1e}")
    ks = jnp.array([conductivity[0], conductivity[1]])
    by_phase = jax.jit(jax.grad(lambda ks: jnp.trace(effective_conductivity(mesh, mesh.points, {0: ks[0], 1: ks[1]},
                                                                            by="phase")) / 3))
    kc_first, kc_s, dk = timed(by_phase, ks)
    print(f"its gradient w.r.t. the two phase conductivities: {np.asarray(dk)}, first call {kc_first:.2f} s, then "
          f"{kc_s:.2f} s; k . grad = {float(dk @ ks):.9f} against the mean {float(k0):.9f} (k_eff is homogeneous "
          "of degree one in k)")


if __name__ == "__main__":
    main()
