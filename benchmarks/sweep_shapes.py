"""Robustness sweep (not a test): varied shapes meshed with the CLI defaults.

Builds each input in OUT_DIR (tori, rounded cubes, finite cylinders, a labelled image, a
non-cubic box, a sphere near its images, spheres on a box corner / edge, spheres centred beyond
an edge, a corner or a face that reach a fraction of a grid step into the box, spheres whose distance is
not wrapped (plain boxes) passing a fraction of a step from a box edge or corner, Gaussian excursion
sets from `jaxmesh generate --kind grf`, percolating inclusions: endless fibres, a gyroid
network, percolating excursion sets; and fields written as users write them: random spheres
placed with no box clearance, algebraic ellipsoid fields and thresholded random fields that are not
distances, distance transforms of voxel images and a quantised distance; flat-bottomed ellipsoids a
fraction of a step off a plain box's plane, as given and with --close-box-layers), runs `jaxmesh mesh`
on it and prints one line per case. With --no-periodic the same fields are meshed as plain boxes
(`jaxmesh mesh --no-periodic`: the box cuts the inclusions, each piece one inclusion).
    .venv/bin/python benchmarks/sweep_shapes.py [OUT_DIR] [--only NAME ...] [--build-only] [--no-periodic]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from jaxmesh._generate import gaussian_random_field
from jaxmesh._periodic import minimum_image

HERE = Path(__file__).resolve().parent.parent
JAXMESH = HERE / ".venv" / "bin" / "jaxmesh"
TIMEOUT = 1800
GAP = 0.03


# --- signed distances (p: (..., 3) local coordinates, shape centred at the origin) ---------------

def _grid(n: int, box=(1.0, 1.0, 1.0)) -> np.ndarray:
    axes = [np.arange(n) * (L / n) for L in box]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _local(x, center, rot=None, box=(1.0, 1.0, 1.0)):
    """Minimum-image offset x - center, rotated into the shape's frame (rot: local -> world)."""
    d = minimum_image(x - np.asarray(center), np.asarray(box, dtype=float))
    return d if rot is None else d @ rot  # row vectors: (R^T d^T)^T = d R


def sd_sphere(p, r):
    return np.linalg.norm(p, axis=-1) - r


def sd_torus(p, R, r):  # axis z
    q = np.hypot(p[..., 0], p[..., 1]) - R
    return np.hypot(q, p[..., 2]) - r


def sd_round_box(p, half, rr):
    q = np.abs(p) - (np.asarray(half) - rr)
    out = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    return out + np.minimum(q.max(axis=-1), 0.0) - rr


def sd_capsule(p, length, r):  # axis z, total length `length`
    h = length / 2 - r
    z = np.clip(p[..., 2], -h, h)
    return np.linalg.norm(p - np.stack([0 * z, 0 * z, z], axis=-1), axis=-1) - r


def sd_cylinder(p, length, r):  # axis z, flat ends, exact
    d = np.stack([np.hypot(p[..., 0], p[..., 1]) - r, np.abs(p[..., 2]) - length / 2], axis=-1)
    return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)


# --- random non-overlapping placement -----------------------------------------------------------

def _place(rng, make, count: int, gap: float = GAP, tries: int = 20000):
    """Random sequential addition of shapes (sdf(p_local), circumradius, center, rot).

    The gap test is rigorous for exact signed distances: min over a fine sample grid of
    max(sd_a, sd_b) is within h*sqrt(3)/2 of gap/2 (1-Lipschitz), so accept only when it is
    at least gap/2 + h*sqrt(3)/2."""
    shapes = []
    h = 0.006
    for _ in range(tries):
        if len(shapes) == count:
            return shapes
        sd, rho = make(rng)
        c, rot = rng.uniform(0, 1, 3), Rotation.random(random_state=rng).as_matrix()
        near = [s for s in shapes
                if np.linalg.norm(_local(c, s[2])) < rho + s[1] + gap]
        ok = True
        if near:
            ax = np.arange(-rho - gap, rho + gap + h, h)
            pts = c + np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
            mine = sd(_local(pts, c, rot))
            pts = pts[mine < gap]
            mine = mine[mine < gap]
            for sd_b, _, cb, rb in near:
                if np.min(np.maximum(mine, sd_b(_local(pts, cb, rb)))) < gap / 2 + h * np.sqrt(3) / 2:
                    ok = False
                    break
        if ok:
            shapes.append((sd, rho, c, rot))
    raise RuntimeError(f"placed only {len(shapes)} of {count} shapes")


def _union(shapes, n: int) -> np.ndarray:
    x = _grid(n)
    return np.min([sd(_local(x, c, rot)) for sd, _, c, rot in shapes], axis=0)


def _crossing(shapes) -> int:
    """How many shapes' circumspheres cross a box face (a rough count)."""
    return sum(bool(np.any((c < rho) | (c > 1 - rho))) for _, rho, c, _ in shapes)


# --- cases: each writes its input and returns (path, extra CLI args, note) -------------------------

def case_torus(out: Path, n=48):
    x = _grid(n)
    phi = sd_torus(_local(x, (0.5, 0.5, 0.5)), 0.28, 0.1)
    np.save(p := out / "torus.npy", phi)
    return p, [], "R 0.28 r 0.1 centred"


def case_torus_corner(out: Path, n=48):
    x = _grid(n)
    phi = sd_torus(_local(x, (0.0, 0.0, 0.0)), 0.28, 0.1)
    np.save(p := out / "torus_corner.npy", phi)
    return p, [], "R 0.28 r 0.1 on the corner"


def _rounded_cubes(seed):
    def make(rng):
        half = rng.uniform(0.08, 0.1, 3)
        return (lambda p, half=half: sd_round_box(p, half, 0.02)), float(np.linalg.norm(half))

    def case(out: Path, n=48):
        shapes = _place(np.random.default_rng(seed), make, 8)
        np.save(p := out / f"cubes_s{seed}.npy", _union(shapes, n))
        return p, [], f"8 rounded boxes, {_crossing(shapes)} near faces"
    return case


def _cylinders(seed, flat):
    sd = sd_cylinder if flat else sd_capsule

    def make(rng):
        length, r = rng.uniform(0.36, 0.44), 0.06
        return (lambda p: sd(p, length, r)), float(np.hypot(length / 2, r))

    def case(out: Path, n=48):
        shapes = _place(np.random.default_rng(seed), make, 6)
        name = f"{'flatcyl' if flat else 'capsules'}_s{seed}"
        np.save(p := out / f"{name}.npy", _union(shapes, n))
        return p, [], f"6 {'flat-ended cylinders' if flat else 'capsules'}, {_crossing(shapes)} near faces"
    return case


def case_labels(out: Path, n=64, seed=0):
    rng = np.random.default_rng(seed)

    def make(rng):
        r = rng.uniform(0.08, 0.12)
        return (lambda p: sd_sphere(p, r)), r

    shapes = _place(rng, make, 12)
    x = _grid(n)
    labels = np.zeros((n, n, n), dtype=np.int32)
    for k, (sd, _, c, _) in enumerate(shapes, start=1):
        labels[sd(_local(x, c)) < 0] = k
    np.save(p := out / "labels.npy", labels)
    return p, [], f"64^3 labels 1..12, {_crossing(shapes)} near faces"


def case_ellipsoid_box(out: Path):
    p = out / "ellipsoid_box.npz"
    # --radius keeps the RVE of the earlier sweeps (without it, 16ef31c on, 15 ellipsoids fill 0.25)
    cmd = [str(JAXMESH), "generate", str(p), "--kind", "ellipsoid", "--n", "15", "--radius", "0.1",
           "--volume-fraction", "0.25", "--box", "1.5", "1", "0.8", "--grid", "48", "--seed", "5"]
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=TIMEOUT)
    return p, [], "generate ellipsoid box 1.5x1x0.8 seed 5"


def _excursion(seed, fraction="0.06", length="0.06", grid="64", name="grf", note="irregular blobs"):
    def case(out: Path):
        p = out / f"{name}_s{seed}.npz"
        cmd = [str(JAXMESH), "generate", str(p), "--kind", "grf", "--volume-fraction", fraction,
               "--correlation-length", length, "--grid", grid, "--seed", str(seed)]
        subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=TIMEOUT)
        return p, [], f"generate grf {float(fraction):.0%} l {length} {grid}^3 seed {seed} ({note})"
    return case


def sd_algebraic_ellipsoid(p, axes):
    """Zero on the ellipsoid, a distance only along its shortest axis: a field as users often write it."""
    return min(axes) * (np.linalg.norm(p / np.asarray(axes), axis=-1) - 1.0)


def _needle(options: list[str]):
    def case(out: Path, n=32):
        phi = sd_algebraic_ellipsoid(_local(_grid(n), (0.5, 0.5, 0.5)), (0.3, 0.05, 0.05))
        np.save(p := out / "needle.npy", phi)
        return p, options, "algebraic ellipsoid 0.3 x 0.05 x 0.05, tips a quarter step"
    return case


def _numpy_excursion(seed: int, options: list[str], n: int = 40, length: float = 0.12, fraction: float = 0.25):
    """A Gaussian random field thresholded as users write it (NumPy FFT, no redistancing): not a distance."""
    def case(out: Path):
        field = gaussian_random_field((1.0, 1.0, 1.0), (n,) * 3, length, seed)
        np.save(p := out / f"numpy_grf_s{seed}.npy", field - np.quantile(field, fraction))
        return p, options, f"NumPy Gaussian field below its {fraction:.0%} quantile, l {length}, {n}^3 seed {seed}"
    return case


def _numpy_spheres(seed: int, count: int, n: int):
    """Random spheres placed here (not by `jaxmesh generate`): nothing keeps them off the box planes."""
    def case(out: Path):
        def make(rng):
            r = rng.uniform(0.07, 0.14)
            return (lambda p: sd_sphere(p, r)), r

        shapes = _place(np.random.default_rng(seed), make, count, gap=0.05)
        np.save(p := out / f"numpy_spheres_s{seed}.npy", _union(shapes, n))
        return p, [], f"{count} spheres, {n}^3, {_crossing(shapes)} near faces"
    return case


def case_numpy_spheres_mm(out: Path):
    """numpy_spheres_s1 written in millimetres: the field times 10 over a 10 mm box (an .npz with `box`)."""
    path, extra, note = _numpy_spheres(1, 25, 40)(out)
    np.savez(p := out / "numpy_spheres_mm.npz", phi=10.0 * np.load(path), box=np.full(3, 10.0))
    return p, extra, f"{note}; x 10 in a 10 mm box"


def case_algebraic_ellipsoids(out: Path, n=48, seed=3, count=20):
    def make(rng):
        axes = rng.uniform(0.1, 0.16) * np.array([1.0, rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.9)])
        return (lambda p: sd_algebraic_ellipsoid(p, axes)), float(axes.max())

    shapes = _place(np.random.default_rng(seed), make, count, gap=0.04)
    np.save(p := out / "algebraic_ellipsoids.npy", _union(shapes, n))
    return p, [], f"{count} algebraic ellipsoid fields (not distances), {_crossing(shapes)} near faces"


def case_big_sphere(out: Path, n=48):
    np.save(p := out / "big_sphere.npy", sd_sphere(_local(_grid(n), (0.5, 0.5, 0.5)), 0.45))
    return p, [], "r 0.45 centred, gap 0.1 to images"


def case_sphere_corner(out: Path, n=48):
    np.save(p := out / "sphere_corner.npy", sd_sphere(_local(_grid(n), (0.0, 0.0, 0.0)), 0.3))
    return p, [], "r 0.3 on the corner"


def case_sphere_edge(out: Path, n=48):
    np.save(p := out / "sphere_edge.npy", sd_sphere(_local(_grid(n), (0.5, 0.0, 0.0)), 0.3))
    return p, [], "r 0.3 on an edge midpoint"


def case_trace_by_edge(out: Path, n=64):
    """r 0.2 crossing x = 0 and z = 0; its trace on x = 0 passes 0.006 (0.38 steps) above the edge
    x = z = 0. Read with --no-periodic, its wrapped pieces at x ~ 1 and z ~ 1 are inclusions too."""
    r, cx, offset = 0.2, 0.1, 0.006
    centre = (cx, 0.5, float(np.sqrt(r * r - cx * cx)) + offset)
    np.save(p := out / "trace_by_edge.npy", sd_sphere(_local(_grid(n), centre), r))
    return p, [], "r 0.2, its trace on x = 0 0.38 steps from the edge x = z = 0"


def _beyond_the_box(name: str, centre, r: float, depth: float, note: str, n: int = 32):
    """A sphere centred outside the box that reaches `depth` grid steps into it (plain boxes: a sliver
    along an edge, a corner piece or a shallow cap; periodic: the wrapped side of a sphere that
    crosses the far planes), beside a sphere r 0.2 in the middle."""
    def case(out: Path):
        x = _grid(n)
        sliver = sd_sphere(_local(x, centre), r + depth / n)
        np.save(p := out / f"{name}.npy", np.minimum(sliver, sd_sphere(_local(x, (0.55, 0.55, 0.55)), 0.2)))
        return p, [], f"{note}, {depth:g} grid steps into the box, {n}^3"
    return case


def _flat_bottom(name: str, offset: float, extra: list[str], n: int = 24):
    """An oblate ellipsoid (semi-axes 0.32, 0.32, 0.1) whose flat bottom lies `offset` grid steps above
    z = 0 (a matrix layer that thin along the plane) or below it (the interface crosses the plane at a
    shallow angle), about a distance near its surface; not periodic: run with --no-periodic."""
    def case(out: Path):
        axes = np.array([0.32, 0.32, 0.1])
        u = (_grid(n) - np.array([0.5, 0.5, 0.1 + offset / n])) / axes
        r = np.linalg.norm(u, axis=-1)
        np.save(p := out / f"{name}.npy", (r - 1) * r / np.linalg.norm(u / axes, axis=-1).clip(1e-9))
        where = "above" if offset > 0 else "below"
        return p, extra, f"flat bottom {abs(offset):g} steps {where} z = 0, {n}^3{', ' + ' '.join(extra) if extra else ''}"
    return case


def _unwrapped_sphere(name: str, centre, r: float, note: str, n: int = 48):
    """A sphere's distance sampled as users write it, with no wrapping: not periodic, so it is meshed
    as a plain box whatever the sweep's mode (cut by the planes it crosses)."""
    def case(out: Path):
        np.save(p := out / f"{name}.npy", sd_sphere(_grid(n) - np.asarray(centre), r))
        return p, ["--no-periodic"], f"{note}, its distance not wrapped (a plain box), {n}^3"
    return case


def _beside_the_far_edge(steps: float, r: float = 0.1, n: int = 48):
    a = (r + steps / n) / np.sqrt(2)
    return _unwrapped_sphere(f"edge_layer_{str(steps).replace('.', '')}", (1 - a, 0.5, 1 - a), r,
                             f"r {r}, cut by x = L and z = L, {steps:g} grid steps from their edge", n)


def _beside_the_far_corner(steps: float, r: float = 0.1, n: int = 48):
    b = (r + steps / n) / np.sqrt(3)
    return _unwrapped_sphere(f"corner_layer_{str(steps).replace('.', '')}", (1 - b, b, 1 - b), r,
                             f"r {r}, cut by x = L, y = 0 and z = L, {steps:g} grid steps from their corner", n)


# --- percolating inclusions: each reaches its own periodic image ----------------------------------

def _periodic_min(dist, x, box=(1.0, 1.0, 1.0)) -> np.ndarray:
    """min over the 27 lattice shifts of dist(x + shift): exact for shapes that are not min-image local."""
    shifts = np.stack(np.meshgrid(*[(-L, 0.0, L) for L in box], indexing="ij"), -1).reshape(-1, 3)
    return np.min([dist(x + s) for s in shifts], axis=0)


def _line_distance(x, point, direction) -> np.ndarray:
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    d = x - np.asarray(point, float)
    return np.linalg.norm(d - (d @ u)[..., None] * u, axis=-1)


def _straight_fibre(name, point, direction, r, n, note):
    def case(out: Path):
        phi = _periodic_min(lambda x: _line_distance(x, point, direction) - r, _grid(n))
        np.save(p := out / f"{name}.npy", phi)
        return p, [], note
    return case


def case_fibre_edge(out: Path, n=40):
    """A wavy fibre along the box edge x = y = 0: cut by four box faces along its whole length."""
    x = _grid(n)
    wave = 0.05 * np.sin(2 * np.pi * x[..., 2])
    d = minimum_image(x[..., :2] - np.stack([wave, 0 * wave], -1), np.ones(2))
    np.save(p := out / "fibre_edge.npy", np.linalg.norm(d, axis=-1) - 0.15)
    return p, [], "endless wavy fibre on the edge x = y = 0, r 0.15"


def case_fibres_crossing(out: Path, n=40):
    x = _grid(n)
    along_z = _periodic_min(lambda x: _line_distance(x, (0.25, 0.25, 0.0), (0, 0, 1)) - 0.12, x)
    along_x = _periodic_min(lambda x: _line_distance(x, (0.0, 0.75, 0.5), (1, 0, 0)) - 0.12, x)
    np.save(p := out / "fibres_crossing.npy", np.minimum(along_z, along_x))
    return p, [], "two endless fibres, along z and along x, r 0.12"


def _voxel_distance(inside: np.ndarray) -> np.ndarray:
    """The signed Euclidean distance transform of a periodic voxel set, in box units (unit box), as
    users make a level set from an image: scipy's transform of the image tiled 3 x 3 x 3, the middle kept."""
    n = inside.shape[0]
    tiled = np.tile(inside, (3, 3, 3))
    signed = ndimage.distance_transform_edt(~tiled) - ndimage.distance_transform_edt(tiled)
    return signed[n:2 * n, n:2 * n, n:2 * n] / n


def _voxel_sphere(name: str, options: list[str], quantise: bool = False, n: int = 48, r: float = 0.3):
    def case(out: Path):
        dist = sd_sphere(_local(_grid(n), (0.5, 0.5, 0.5)), r)
        phi = (np.round(dist * n) + 0.5) / n if quantise else _voxel_distance(dist < 0)
        np.save(p := out / f"{name}.npy", phi)
        how = "its distance rounded to whole grid steps" if quantise else "the distance transform of its voxels"
        return p, options, f"sphere r {r}, {n}^3, {how}"
    return case


def case_voxel_spheres(out: Path, n=64, seed=7, count=12):
    def make(rng):
        r = rng.uniform(0.08, 0.13)
        return (lambda p: sd_sphere(p, r)), r

    shapes = _place(np.random.default_rng(seed), make, count, gap=0.06)
    np.save(p := out / "voxel_spheres.npy", _voxel_distance(_union(shapes, n) < 0))
    return p, [], f"{count} spheres, {n}^3, the distance transform of their voxels"


def _gyroid(name: str, level: float, n: int):
    def build(out: Path):
        t = 2 * np.pi * _grid(n)
        s, c = np.sin(t), np.cos(t)
        g = s[..., 0] * c[..., 1] + s[..., 1] * c[..., 2] + s[..., 2] * c[..., 0]
        np.save(p := out / f"{name}.npy", (g - level) / (2 * np.pi))
        return p, [], f"gyroid network g < {level}, {n}^3, one inclusion percolating along x, y, z"
    return build


CASES = {
    "torus": case_torus,
    "torus_corner": case_torus_corner,
    "cubes_s0": _rounded_cubes(0),
    "cubes_s1": _rounded_cubes(1),
    "capsules_s0": _cylinders(0, flat=False),
    "capsules_s1": _cylinders(1, flat=False),
    "flatcyl_s0": _cylinders(0, flat=True),
    "flatcyl_s1": _cylinders(1, flat=True),
    "labels": case_labels,
    "ellipsoid_box": case_ellipsoid_box,
    "big_sphere": case_big_sphere,
    "sphere_corner": case_sphere_corner,
    "sphere_edge": case_sphere_edge,
    "trace_by_edge": case_trace_by_edge,
    "sliver_edge": _beyond_the_box("sliver_edge", (0.5, -0.1, -0.1), float(np.hypot(0.1, 0.1)), 0.3,
                                   "sphere centred beyond the edge y = z = 0"),
    "sliver_edge_015": _beyond_the_box("sliver_edge_015", (0.5, -0.1, -0.1), float(np.hypot(0.1, 0.1)), 0.15,
                                       "sphere centred beyond the edge y = z = 0"),
    "sliver_corner": _beyond_the_box("sliver_corner", (-0.08, -0.08, -0.08), float(np.sqrt(3.0) * 0.08), 0.3,
                                     "sphere centred beyond the corner 0"),
    "cap_shallow": _beyond_the_box("cap_shallow", (0.5, 0.5, -0.1), 0.1, 0.3, "sphere centred beyond the face z = 0"),
    "edge_layer_03": _beside_the_far_edge(0.3),
    "edge_layer_015": _beside_the_far_edge(0.15),
    "corner_layer_02": _beside_the_far_corner(0.2),
    "grf_s1": _excursion(1),
    "grf_s2": _excursion(2),
    "fibre": _straight_fibre("fibre", (0.5, 0.5, 0.0), (0, 0, 1), 0.2, 32, "endless straight fibre along z, r 0.2"),
    "fibre_edge": case_fibre_edge,
    "fibre_diagonal": _straight_fibre("fibre_diagonal", (0.5, 0.5, 0.5), (1, 0, 1), 0.15, 40,
                                      "endless fibre along (1, 0, 1), r 0.15: percolates along x and z"),
    "fibres_crossing": case_fibres_crossing,
    "gyroid": _gyroid("gyroid", 0.4, 40),
    "gyroid_03": _gyroid("gyroid_03", 0.3, 48),
    "grf_perc_s1": _excursion(1, "0.2", "0.15", "48", "grf_perc", "percolating blobs"),
    "grf_perc_s2": _excursion(2, "0.2", "0.15", "48", "grf_perc", "percolating blobs"),
    "needle": _needle([]),  # as given, then redistanced after the stalled-node error
    "needle_as_given": _needle(["--no-redistance"]),
    "needle_redistanced": _needle(["--redistance"]),
    "numpy_grf_s301": _numpy_excursion(301, []),
    "numpy_grf_s301_as_given": _numpy_excursion(301, ["--no-redistance"]),
    "numpy_grf_s302": _numpy_excursion(302, []),
    "numpy_grf_s303": _numpy_excursion(303, []),
    "numpy_spheres_s1": _numpy_spheres(1, 25, 40),
    "numpy_spheres_s2": _numpy_spheres(2, 40, 48),
    "numpy_spheres_s3": _numpy_spheres(3, 30, 48),
    "numpy_spheres_s4": _numpy_spheres(4, 30, 48),
    "numpy_spheres_s5": _numpy_spheres(5, 30, 48),
    "algebraic_ellipsoids": case_algebraic_ellipsoids,
    "numpy_spheres_mm": case_numpy_spheres_mm,
    "voxel_sphere": _voxel_sphere("voxel_sphere", []),
    "voxel_sphere_pointwise": _voxel_sphere("voxel_sphere", ["--curv-average", "0"]),
    "quantised_sphere": _voxel_sphere("quantised_sphere", [], quantise=True),
    "voxel_spheres": case_voxel_spheres,
    "layer_matrix": _flat_bottom("layer_matrix", 0.02, []),
    "layer_matrix_closed": _flat_bottom("layer_matrix", 0.02, ["--close-box-layers"]),
    "layer_cross": _flat_bottom("layer_cross", -0.02, []),
    "layer_cross_closed": _flat_bottom("layer_cross", -0.02, ["--close-box-layers"]),
}


def _last_line(text: str) -> str:
    """The last error line of stderr (a hint may follow it), else its last line."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    return (errors or lines or ["(no stderr)"])[-1]


def run_case(name: str, out: Path, build_only: bool, periodic: bool = True) -> str:
    try:
        path, extra, note = CASES[name](out)
    except Exception as err:  # noqa: BLE001 - a sweep reports and goes on
        return f"{name:14s} build failed: {type(err).__name__}: {err}"
    if build_only:
        return f"{name:14s} built {path.name} ({note})"
    vtu, rep = out / f"{name}.vtu", out / f"{name}.json"
    for f in (vtu, rep):
        f.unlink(missing_ok=True)
    cmd = [str(JAXMESH), "mesh", str(path), "-o", str(vtu), "--report", str(rep), *extra]
    if not periodic:
        cmd.append("--no-periodic")
    start = time.perf_counter()
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT)
        rc, stdout, stderr = res.returncode, res.stdout, res.stderr
    except subprocess.TimeoutExpired as err:
        rc, stdout, stderr = "timeout", err.stdout or "", f"timed out after {TIMEOUT} s"
        stdout = stdout.decode() if isinstance(stdout, bytes) else stdout
    secs = time.perf_counter() - start
    (out / f"{name}.mesh.log").write_text(f"$ {' '.join(cmd)}\n{stdout}\n--- stderr ---\n{stderr}")
    head = f"{name:14s} rc {rc!s:>3} {secs:6.1f} s"
    if rc != 0 or not rep.exists():
        return f"{head}  FAILED: {_last_line(stderr)}  [{note}]"
    r = json.loads(rep.read_text())
    q, ok = r["quality"], r["metadata"]["validation"]["ok"]
    return (f"{head} {q['n_cells']:8d} tets  q_mean {q['q_mean']:.3f}  "
            f"{100 * q['frac_below']:6.3f} % <0.3  min dihedral {q['min_dihedral_deg']:5.1f} deg  "
            f"{'valid' if ok else 'INVALID'}  [{note}]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", nargs="?", default="/tmp/jaxmesh_shapes")
    parser.add_argument("--only", nargs="+", choices=sorted(CASES), help="run these cases only")
    parser.add_argument("--build-only", action="store_true", help="write the inputs, mesh nothing")
    parser.add_argument("--no-periodic", action="store_true", help="mesh the fields as plain (non-periodic) boxes")
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    git = ["git", "-C", str(HERE)]
    commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run([*git, "diff", "--quiet", "HEAD", "--", "jaxmesh"]).returncode != 0
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    print(f"# {now} UTC, {len(os.sched_getaffinity(0))} cores, commit {commit}{'+modified' if dirty else ''}, "
          f"out {out}{', --no-periodic' if args.no_periodic else ''}", flush=True)
    for name in args.only or CASES:
        print(run_case(name, out, args.build_only, not args.no_periodic), flush=True)


if __name__ == "__main__":
    main()
