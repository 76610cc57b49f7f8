"""Benchmark of the Steiner cavities of the sliver stage (`jaxmesh._slivers.insert_steiner`).

Usage:
    .venv/bin/python benchmarks/bench_steiner.py [--fine 20000] [--bad 300]

A graded tet mesh: the Delaunay tetrahedralisation of 3,000 random points in the unit cube plus
--fine random points in a ball of radius 0.05 (the tiny elements a size function puts at a speck or
a shallow cap). `insert_steiner` is run on --bad of its slivers (dihedral angle below 10 degrees, taken
evenly from the fine ball outwards) twice: with the library's cavity (grown a layer at a time over a
face-neighbour table, circumspheres computed once) and with the depth-first walk it replaced (one Python
step per tet, its circumsphere computed there), kept here as the reference. Times, their ratio
within one run, and whether both give the same points and the same cells.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform

import numpy as np
from bench_intersect import timed  # run as a script: benchmarks/ is on the path
from scipy.spatial import Delaunay

import jaxmesh._slivers as slivers
from jaxmesh._quality import signed_volumes


def walking_cavity(points: np.ndarray, cells: np.ndarray):
    """The cavity before 7075db3, with `_cavity`'s arguments: a depth-first walk over the neighbours,
    each tet's circumsphere computed when the walk reaches it."""
    def cavity(across, centres, radius2, dead, seed, x, member):
        cav, todo, seen = [seed], [seed], {seed}
        while todo:
            for nb in (int(v) for v in across[todo.pop()]):
                if nb < 0 or nb in seen:
                    continue
                seen.add(nb)
                c = slivers._circumcentres_p(points[cells[nb]][None])[0]
                if np.sum((x - c) ** 2) < np.sum((points[cells[nb][0]] - c) ** 2) * (1 - 1e-12):
                    if dead[nb]:
                        return None
                    cav.append(nb)
                    todo.append(nb)
        return np.array(cav)
    return cavity


def graded_mesh(fine: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    direction = rng.standard_normal((fine, 3))
    ball = 0.5 + 0.05 * direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.random((fine, 1)) ** (1 / 3)
    points = np.vstack([rng.random((3000, 3)), ball])
    cells = Delaunay(points).simplices.astype(np.int64)
    negative = signed_volumes(points, cells) < 0
    cells[negative, :2] = cells[negative, 1::-1]
    return points, cells


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fine", type=int, default=20000, help="random points in the fine ball")
    ap.add_argument("--bad", type=int, default=300, help="slivers handed to insert_steiner")
    args = ap.parse_args()
    points, cells = graded_mesh(args.fine)
    slivers_all = np.flatnonzero(slivers.min_dihedral(points, cells) < 10.0)
    centre_distance = np.linalg.norm(points[cells[slivers_all]].mean(axis=1) - 0.5, axis=1)
    ordered = slivers_all[np.argsort(centre_distance, kind="stable")]
    bad = ordered[np.linspace(0, len(ordered) - 1, min(args.bad, len(ordered))).astype(int)]
    protected = np.zeros(0, np.int64)
    print(f"# {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
          f"{os.cpu_count()} cores; {len(points):,} points, {len(cells):,} tets, {len(slivers_all):,} slivers")
    (p1, c1, a1), t_layers = timed(slivers.insert_steiner, points, cells, protected, bad)
    library = slivers._cavity
    slivers._cavity = walking_cavity(points, cells)
    try:
        (p2, c2, a2), t_walk = timed(slivers.insert_steiner, points, cells, protected, bad)
    finally:
        slivers._cavity = library
    same = np.array_equal(p1, p2) and np.array_equal(np.unique(np.sort(c1, axis=1), axis=0),
                                                     np.unique(np.sort(c2, axis=1), axis=0))
    print("| slivers given | points added | layers s | walk s | walk / layers | same points and cells |")
    print("|---:|---:|---:|---:|---:|---|")
    print(f"| {len(bad)} | {len(a1)} | {t_layers:.2f} | {t_walk:.2f} | {t_walk / t_layers:.1f} | {same} |")


if __name__ == "__main__":
    main()
