"""The `jaxmesh` command line: generate RVE inputs, inspect them, mesh them, validate meshes."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from ._compile_cache import enable_compilation_cache
from ._errors import MeshingError
from ._pipeline import MeshConfig


def _box_arg(values: list[float] | None) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)


def _write_json_atomic(path: str | os.PathLike, data: dict) -> None:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2, default=_json_default)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_default(obj):
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def _progress(stage: str, message: str, t0: float) -> None:
    print(f"[jaxmesh] {stage:<12s} {message}  ({time.perf_counter() - t0:.2f} s)", flush=True)


# ---------------------------------------------------------------------------------------------
# generate


_KEPT_FRACTION_NOTE = 0.8  # grf: say why when dropped components take more than a fifth
# sphere/ellipsoid: the mesher refuses inclusions closer than one grid step, so the default gap
# keeps at least that, with a tenth of a step to spare (ellipsoid gaps are solved to a tolerance)
_DEFAULT_MIN_GAP, _DEFAULT_GAP_STEPS = 0.02, 1.1
_DEFAULT_RADIUS = 0.1  # generate: mean radius (largest semi-axis) when --radius is not given


def _cmd_generate(args: argparse.Namespace) -> int:
    from . import _generate as gen

    t0 = time.perf_counter()
    if Path(args.output).suffix.lower() != ".npz":
        raise ValueError(f"generate writes an .npz (phi, box and the inclusions), got {args.output!r}; hint: name it "
                         "*.npz")
    if not Path(args.output).parent.is_dir():
        raise ValueError(f"folder {str(Path(args.output).parent)!r} does not exist; hint: create it first")
    box = _box_arg(args.box) or (1.0,) * args.dim
    if len(box) != args.dim:
        raise ValueError(f"--box has {len(box)} lengths but --dim is {args.dim}; give one length per axis.")
    if not all(math.isfinite(length) and length > 0 for length in box):
        raise ValueError(f"--box: expected positive lengths, got {' '.join(f'{length:g}' for length in box)}")
    if args.grid < 4:
        raise ValueError(f"--grid: expected at least 4 samples along the shortest axis, got {args.grid}")
    grid_shape = _grid_shape(box, args.grid)
    if args.kind == "grf":
        phi = gen.excursion_set(
            box, grid_shape, correlation_length=args.correlation_length,
            volume_fraction=args.volume_fraction or 0.3, seed=args.seed,
        )
        gen.write_input(args.output, None, box, grid_shape, phi=phi)
        _progress("generate", f"excursion set on {grid_shape} grid, node fraction {float((phi < 0).mean()):.4f} "
                              f"-> {args.output}", t0)
        requested, kept = args.volume_fraction or 0.3, float((phi < 0).mean())
        if kept < _KEPT_FRACTION_NOTE * requested:
            steps = args.correlation_length / min(b / n for b, n in zip(box, grid_shape))
            print(f"    note: node fraction {kept:.4f} against the requested {requested:g}: the components the mesher "
                  "would refuse (specks, necks under a grid step, pairs under a quarter step apart) were dropped "
                  "or cut, and no threshold tried came nearer; "
                  f"the correlation length is {steps:.1f} grid steps, so a longer --correlation-length or a finer "
                  "--grid keeps more (or try other --seed values)", flush=True)
        spanning = gen.spanning_components(phi) if args.dim == 2 else []
        if spanning:
            print(f"    note: inclusion(s) {spanning[:10]} reach their own periodic image (the set percolates): "
                  "`jaxmesh mesh` meshes them closed off at the box, their crossings of opposite edges paired; "
                  "a lower --volume-fraction keeps the blobs apart", flush=True)
        return 0
    shape = args.kind
    if args.dim == 2:
        shape = {"sphere": "sphere", "ellipsoid": "ellipsoid"}[shape]
    step = min(box) / args.grid
    min_gap = max(_DEFAULT_MIN_GAP, _DEFAULT_GAP_STEPS * step) if args.min_gap is None else args.min_gap
    if args.n is None and args.volume_fraction is None:
        raise ValueError("give --n, --volume-fraction or both (e.g. --n 30 --volume-fraction 0.3)")
    # --n with --volume-fraction and no --radius: n inclusions at that fraction, sizes scaled to fill it
    fill = args.radius is None and args.n is not None and args.volume_fraction is not None
    radius = _DEFAULT_RADIUS if args.radius is None else args.radius
    if fill:  # refuse at once what the placement would take minutes to draw and the mesher would refuse
        unit_ball = gen.unit_ball_volume(args.dim)
        equal_radius = (args.volume_fraction * math.prod(box) / (args.n * unit_ball)) ** (1.0 / args.dim)
        if equal_radius < 0.75 * step:
            raise ValueError(f"--n {args.n} inclusions filling {args.volume_fraction:g} are about "
                             f"{2 * equal_radius:.3g} across, under the 1.5 grid steps ({1.5 * step:.3g}) that the "
                             "mesher needs; hint: fewer inclusions, a higher fraction or a finer --grid")
    specs = gen.random_inclusions(
        box, n=args.n, volume_fraction=args.volume_fraction, shape=shape,
        radius=(radius, args.radius_std),
        aspect=(1.0, args.max_aspect), min_gap=min_gap, box_gap=args.box_gap, seed=args.seed, scale_to_fraction=fill,
    )
    _check_meshable(specs, box, grid_shape, min_gap, step)
    gen.write_input(args.output, specs, box, grid_shape)
    volume = sum(_spec_volume(s) for s in specs)
    box_volume = math.prod(box)
    _progress(
        "generate",
        f"{len(specs)} {shape}s, volume fraction {volume / box_volume:.4f}, grid {grid_shape} -> {args.output}",
        t0,
    )
    if args.n is not None and args.volume_fraction and volume / box_volume < args.volume_fraction - 0.005:
        print(f"    note: --n {args.n} was reached first (volume fraction {volume / box_volume:.4f}, asked "
              f"{args.volume_fraction}): drop --n, or raise it or --radius, to reach the fraction", flush=True)
    elif args.n is not None and len(specs) < args.n:
        print(f"    note: the volume fraction was reached with {len(specs)} of the --n {args.n} inclusions: drop "
              "--radius to have all of them, their sizes scaled to the fraction", flush=True)
    return 0


def _check_meshable(specs, box, grid_shape, min_gap: float, step: float) -> None:
    """Run the input check of `jaxmesh mesh` on the drawn RVE, so that generate never writes a file
    the mesher refuses (a gap under one grid step, an inclusion too small for the grid)."""
    from ._generate import microstructure_from_specs

    try:
        microstructure_from_specs(specs, box, grid_shape)
    except ValueError as err:
        hint = (f" Here: --min-gap {min_gap:g} is under one grid step ({step:.4g}): give --min-gap "
                f"{_DEFAULT_GAP_STEPS * step:.3g} or more, or a finer --grid." if min_gap < step else
                " Here: a finer --grid, a larger --radius or a smaller --radius-std (radii are drawn down to "
                "a quarter of the mean) resolves small inclusions.")
        raise ValueError(f"the RVE drawn would be refused by `jaxmesh mesh`, so nothing was written: {err}"
                         + hint) from None


def _spec_volume(spec) -> float:
    axes = [float(a) for a in spec.axes]
    return math.prod(axes) * (math.pi if len(axes) == 2 else 4.0 * math.pi / 3.0)


def _grid_shape(box: tuple[float, ...], n_min: int) -> tuple[int, ...]:
    """Isotropic node-centred grid: n_min samples along the shortest axis. Raises ValueError when a
    box length is not a whole number of those steps (`jaxmesh mesh` would refuse the file)."""
    shape = _commensurate_shape(box, n_min)
    if shape is None:
        better = next((n for n in range(n_min + 1, 8 * n_min + 1) if _commensurate_shape(box, n)), None)
        hint = (f"--grid {better} (step {min(box) / better:.6g})" if better else
                f"--box {' '.join(f'{round(length / (min(box) / n_min)) * min(box) / n_min:.6g}' for length in box)}")
        raise ValueError(f"--box {' '.join(f'{length:g}' for length in box)} with --grid {n_min}: the box lengths are "
                         f"not whole numbers of the grid step {min(box) / n_min:.6g}, and a level-set grid needs the "
                         f"same step on every axis. Hint: {hint}.")
    return shape


def _commensurate_shape(box: tuple[float, ...], n_min: int) -> tuple[int, ...] | None:
    step = min(box) / n_min
    shape = tuple(int(round(length / step)) for length in box)
    spacing = [length / n for length, n in zip(box, shape)]
    return shape if max(spacing) - min(spacing) <= 1e-6 * max(spacing) else None


# ---------------------------------------------------------------------------------------------
# info


def _roll_arg(values):
    if values is None or values == ["auto"]:
        return None if values is None else "auto"
    try:
        return tuple(int(v) for v in values)
    except ValueError:
        raise ValueError(f"--roll: expected 'auto' or one integer (grid samples) per axis, got {' '.join(values)}") from None


def _print_worst_cell(quality: dict, periodic: bool) -> None:
    """Where the worst cell is; when it is bad and sits on a box plane beside an interface, the known
    cause (an interface grazing the box leaves a thin wedge of the domain there)."""
    cell = quality.get("worst_cell")
    if not cell:
        return
    where = ", ".join(f"{v:.4g}" for v in cell["centroid"])
    what = "matrix" if cell.get("inclusion_id", 0) == 0 else f"inclusion {cell['inclusion_id']}"
    line = f"    worst cell: q {cell['q']:.2g} at ({where}), {what}"
    if cell.get("on_interface"):
        line += ", a vertex on an interface"
    plane = cell.get("nearest_box_plane")
    if plane:
        name = f"{'xyz'[plane['axis']]} = {plane['at']:g}"
        line += f", {plane['distance']:.2g} from the box plane {name}"
    if "n_dihedral_below_10" in quality:
        line += f"; {quality['n_dihedral_below_10']} tets with a dihedral angle below 10 deg"
    print(line)
    if plane and cell["q"] < 0.1 and cell.get("on_interface") and plane["distance"] == 0.0:
        roll = (" (--roll auto moves the box of a periodic grid off grazing meetings with the interfaces)" if periodic
                else " (--close-box-layers closes the layers along the planes of a plain box thinner than a sixth of "
                     "a grid step: a level-set input's interface then meets the plane at an angle)")
        print(f"    note: an interface meets or grazes the box plane {name} there, leaving a wedge of the domain "
              f"thinner than the elements{roll}")


def _cmd_info(args: argparse.Namespace) -> int:
    from .io._read import load_input

    t0 = time.perf_counter()
    ms = load_input(args.input, box=_box_arg(args.box), periodic=not args.no_periodic)
    info = _microstructure_info(ms)
    for key, value in info.items():
        print(f"{key:>22s}: {value}")
    _progress("info", f"read {args.input}", t0)
    return 0


def _microstructure_info(ms) -> dict:
    import numpy as np

    spacing = min(length / n for length, n in zip(ms.box, ms.grid_shape))
    return {
        "dimension": ms.dim,
        "box": list(ms.box),
        "grid": list(ms.grid_shape),
        "periodic": ms.periodic,
        "inclusions": len(ms.inclusions),
        "volume_fraction": round(float(ms.volume_fraction()), 6),
        "min_gap_on_grid": round(float(np.min(ms.dn2[ms.dn1 < spacing] if np.any(ms.dn1 < spacing) else ms.dn2)), 6),
        **(_box_plane_info(ms) if ms.periodic and ms.inclusions else {}),
        **_slope_info(ms),
    }


def _slope_info(ms) -> dict:
    """A level set's slope spread (`gradient_scale`) and what mesh_rve makes of it."""
    from ._pipeline import _DISTANCE_SPREAD

    spread = ms.inclusions[0].description.get("slope_spread") if ms.inclusions else None
    if spread is None:
        return {}
    far = spread > _DISTANCE_SPREAD and ms.can_redistance
    return {"slope_spread": f"{spread:.3g} (" + ("far from a distance: jaxmesh mesh redistances it after a failed first try"
                                                 if far else "distance-like") + ")"}


def _box_plane_info(ms) -> dict:
    """How close the box comes to a grazing meeting with the interface, as given and with --roll auto, and
    whether `jaxmesh mesh` rolls it by default (`_pipeline._as_microstructure`)."""
    from ._pipeline import _grazing_floor, box_plane_clearances

    clear, best = box_plane_clearances(ms)
    as_given = float(clear[(0,) * ms.dim])
    rolls = as_given < _grazing_floor(ms) and any(best) and ms.can_roll
    return {"box_plane_clearance": round(as_given, 6),
            "with_roll_auto": f"{clear[best]:.6g} (samples {list(best)})",
            "default_roll": ("yes: the box as given is under a sixth of a grid step from a grazing meeting, so "
                             "jaxmesh mesh rolls as --roll auto (--roll 0 0 0 keeps the frame)") if rolls else "no"}


# ---------------------------------------------------------------------------------------------
# mesh


_REDISTANCE_HELP = ("level-set inputs: first make the field a first-order signed distance to its zero set (same "
                     "signs at every node, the interface moved within its cells): for fields far from a distance, "
                     "e.g. a thresholded random field, whose nearly flat saddles fold the surfaces. Default: the "
                     "field as given, and once more redistanced when a fold or a node stalled off the level set "
                     "stops the run, or any failure when the field is far from a distance (the report's "
                     "metadata.redistance.after_failure keeps the first error); --no-redistance: never")
_CLOSE_LAYERS_HELP = ("plain-box (--no-periodic) level-set inputs: first close the layers along the box planes "
                      "thinner than a sixth of a grid step (an interface grazing a plane from inside moves onto "
                      "it, a sheet of inclusion along it is dropped: the interface moves by at most that much, "
                      "there only). Default: as given, and once more closed when the volume recovery stops where "
                      "an interface grazes a box plane (the report's metadata.close_box_layers.after_failure keeps "
                      "the first error); --no-close-box-layers: never")


def _check_mesh_outputs(args: argparse.Namespace) -> None:
    """Refuse before meshing what would fail only after it, minutes later and with some files already
    written: an unknown mesh format, a plot that is not a PNG, a missing folder, or an output path that
    is the input or another output."""
    from ._plot import check_png_path
    from .io._write import FORMATS, resolve_format

    try:
        resolve_format(Path(args.output), None)
    except ValueError:
        raise ValueError(f"-o {args.output}: the mesh format comes from the extension, one of "
                         f"{', '.join(FORMATS)}") from None
    if args.plot:
        check_png_path(args.plot)
    taken = {Path(args.input).resolve(): "the input"}
    for option, path in (("-o", args.output), ("--report", args.report), ("--plot", args.plot)):
        if path is None:
            continue
        if not Path(path).parent.is_dir():
            raise ValueError(f"{option} {path}: folder {str(Path(path).parent)!r} does not exist; hint: create it "
                             "first")
        if (key := Path(path).resolve()) in taken:
            raise ValueError(f"{option} {path} is also {taken[key]}, which it would overwrite; hint: give each "
                             "output its own file name")
        taken[key] = option


def _cmd_mesh(args: argparse.Namespace) -> int:
    from ._pipeline import mesh_rve
    from ._quality import quality_report

    t0 = time.perf_counter()
    _check_mesh_outputs(args)
    config = MeshConfig(h=args.h, periodic=not args.no_periodic, seed=args.seed, backend=args.backend,
                        max_elements=args.max_elements if args.max_elements > 0 else None, roll=_roll_arg(args.roll),
                        redistance=args.redistance, close_box_layers=args.close_box_layers, **_size_kwargs(args))
    mesh = mesh_rve(args.input, config, box=_box_arg(args.box), progress=lambda line: print(line, flush=True))
    validation = mesh.metadata["validation"]
    for name, check in validation["checks"].items():
        print(f"    {name:<14s} {'ok' if check['passed'] else 'FAILED'}  {check['detail']}")
    quality = quality_report(mesh)
    worst = (f"min dihedral {quality['min_dihedral_deg']:.1f} deg" if mesh.dim == 3
             else f"min angle {quality['min_angle_deg']:.1f} deg")
    print(f"    quality: mean q {quality['q_mean']:.3f}, min q {quality['q_min']:.3f}, "
          f"q<0.3: {100 * quality['frac_below']:.2f}%, {worst}")
    _print_worst_cell(quality, mesh.periodic)
    mesh.write(args.output)
    _progress("write", f"-> {args.output}", t0)
    if args.report:
        _write_json_atomic(
            args.report,
            {"input": str(args.input), "output": str(args.output), "quality": quality, "metadata": mesh.metadata},
        )
        _progress("report", f"-> {args.report}", t0)
    if args.plot:
        from ._plot import plot_mesh

        plot_mesh(mesh, args.plot, title=f"{Path(args.input).name}: {mesh.n_cells} cells")
        _progress("plot", f"-> {args.plot}", t0)
    failed = {name for name, check in validation["checks"].items() if not check["passed"]}
    near_box = validation["checks"]["volume"]["counts"].get("rel_error", 1.0) <= 1e-4
    if args.backend == "tetwild" and failed <= {"interface", "boundary", "volume"} and near_box:
        print("    (tetwild: not conforming; interface nodes lie near the level set, and a few box nodes may stay "
              "inside fTetWild's envelope, off their plane)")
        return 0
    return 0 if validation["ok"] else 1


def _size_kwargs(args: argparse.Namespace) -> dict:
    return {
        key: value
        for key, value in {
            "iis": args.iis, "nb_el": args.nb_el, "curv_alpha": args.curv_alpha,
            "grad": args.grad, "h_max": args.h_max, "curv_average": args.curv_average,
        }.items()
        if value is not None
    }


# ---------------------------------------------------------------------------------------------
# validate


def _cmd_validate(args: argparse.Namespace) -> int:
    from ._pipeline import _as_microstructure
    from ._validate import validate
    from .io._read_mesh import read_mesh

    t0 = time.perf_counter()
    mesh = read_mesh(args.mesh, box=_box_arg(args.box), periodic=not args.no_periodic)
    ms = None
    if args.geometry:
        _read_as_meshed(args, mesh.metadata.get("input_reading", {}))
        ms, _, _ = _as_microstructure(args.geometry, box=_box_arg(args.box) or tuple(mesh.box),
                                      periodic=mesh.periodic, roll=_roll_arg(args.roll), redistance=args.redistance,
                                      close_box_layers=args.close_box_layers)
    report = validate(mesh, ms)
    print(report.summary())
    if ms is not None and not report.ok and set(report.failed) <= _GEOMETRY_CHECKS:
        hint = _another_reading(mesh, args, ms)
        if hint:
            print(f"    hint: {hint}")
    _progress("validate", ("valid" if report.ok else "INVALID") + f": {args.mesh}", t0)
    if args.report:
        _write_json_atomic(args.report, report.to_dict())
    return 0 if report.ok else 1


_GEOMETRY_CHECKS = {"interface", "labels", "connectivity"}  # the checks that read the input


def _read_as_meshed(args: argparse.Namespace, reading: dict) -> None:
    """Fill --roll / --redistance / --close-box-layers, where not given, from the input reading the mesh
    file carries."""
    taken = []
    if args.roll is None and reading.get("roll_samples"):
        args.roll = [str(k) for k in reading["roll_samples"]]
        taken.append("--roll " + " ".join(args.roll))
    if not args.redistance and reading.get("redistanced"):
        args.redistance = True
        taken.append("--redistance")
    if not args.close_box_layers and reading.get("box_layers_closed"):
        args.close_box_layers = True
        taken.append("--close-box-layers")
    if taken:
        print(f"    reading the input as the mesh file says it was meshed: {' '.join(taken)}")


def _another_reading(mesh, args: argparse.Namespace, ms) -> str:
    """When a mesh fails only the checks against its input: the options (--redistance, --roll auto,
    --close-box-layers) under which the input reads as the mesh follows it, as `jaxmesh mesh` reads it
    after a failed first try."""
    from ._pipeline import _as_microstructure
    from ._validate import validate

    options = []
    if not args.redistance and ms.can_redistance:
        options.append(["--redistance"])
    if args.roll is None and ms.can_roll:
        options.append(["--roll", "auto"])
    if not args.close_box_layers and ms.can_close_box_layers:
        options.append(["--close-box-layers"])
    if len(options) == 2:
        options.append(options[0] + options[1])
    for flags in options:
        other, _, _ = _as_microstructure(args.geometry, box=_box_arg(args.box) or tuple(mesh.box),
                                         periodic=mesh.periodic,
                                         roll="auto" if "--roll" in flags else _roll_arg(args.roll),
                                         redistance=args.redistance or "--redistance" in flags,
                                         close_box_layers=args.close_box_layers or "--close-box-layers" in flags)
        if validate(mesh, other).ok:
            return (f"valid with {' '.join(flags)}: the input read so is what the mesh follows (jaxmesh mesh "
                    "reads it so when asked or after a failed first try; its report's metadata says which)")
    return ""


# ---------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxmesh",
        description="Periodic, conforming meshes of implicit microstructures (level sets, labelled images).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="write a random RVE input file (.npz) the mesher reads")
    g.add_argument("output", help="output .npz")
    g.add_argument("--dim", type=int, choices=(2, 3), default=3)
    g.add_argument("--kind", choices=("sphere", "ellipsoid", "grf"), default="sphere",
                   help="sphere/ellipsoid (circle/ellipse in 2D) by random sequential addition, or grf: "
                        "excursion set of a periodic Gaussian random field")
    g.add_argument("--n", type=int, default=None,
                   help="number of inclusions (with --volume-fraction and no --radius: n inclusions at that "
                        "fraction, their sizes scaled to fill it)")
    g.add_argument("--volume-fraction", type=float, default=None)
    g.add_argument("--radius", type=float, default=None,
                   help=f"mean radius (largest semi-axis for ellipsoids; default {_DEFAULT_RADIUS}); given with --n "
                        "and --volume-fraction, the generator stops at whichever of the two it reaches first")
    g.add_argument("--radius-std", type=float, default=0.02,
                   help="spread of the radii (scaled with them when they are fitted to --n and --volume-fraction)")
    g.add_argument("--max-aspect", type=float, default=2.0, help="largest aspect ratio for ellipsoids")
    g.add_argument("--min-gap", type=float, default=None,
                   help="guaranteed minimum gap between inclusions (default: 0.02, or 1.1 grid steps when larger; "
                        "jaxmesh mesh refuses inclusions closer than one grid step)")
    g.add_argument("--box-gap", type=float, default=None,
                   help="clearance of caps, traces and box-edge crossings from the box planes, edges and corners "
                        "(default: --min-gap; 0 places inclusions anywhere)")
    g.add_argument("--correlation-length", type=float, default=0.1, help="grf only")
    g.add_argument("--grid", type=int, default=64, help="grid samples along the shortest box axis")
    g.add_argument("--box", type=float, nargs="+", default=None, help="box lengths (default: unit)")
    g.add_argument("--seed", type=int, default=0)
    g.set_defaults(func=_cmd_generate)

    i = sub.add_parser("info", help="read an input and describe the microstructure")
    i.add_argument("input")
    i.add_argument("--box", type=float, nargs="+", default=None)
    i.add_argument("--no-periodic", action="store_true")
    i.set_defaults(func=_cmd_info)

    m = sub.add_parser("mesh", help="mesh an input (.npy/.npz level set or labelled image)")
    m.add_argument("input")
    m.add_argument("-o", "--output", required=True, help="mesh file: .vtu .msh .xdmf .inp .vtk .npz")
    m.add_argument("--box", type=float, nargs="+", default=None)
    m.add_argument("--h", type=float, default=None, help="uniform element size (overrides the size function)")
    m.add_argument("--iis", type=float, default=None,
                   help="initial interface size, a length in the box's units (default: 0.05 times the box's "
                        "mean side, the geometric mean of its sides)")
    m.add_argument("--nb-el", type=float, default=None,
                   help="elements across the narrowest gaps between inclusions "
                        "(min(nb_el, 1) across layers the box cuts off)")
    m.add_argument("--curv-alpha", type=float, default=None, help="curvature sensitivity: h = alpha / |kappa|")
    m.add_argument("--curv-average", type=float, default=None, metavar="STEPS",
                   help="average each inclusion's curvature over STEPS grid steps before sizing; 0: pointwise. "
                        "Default: 1.5 on inclusions whose interfaces ripple at the grid scale (a field sampled "
                        "from voxels, e.g. a distance transform of an image: pointwise, each ripple asks for "
                        "elements a quarter of a step), pointwise elsewhere; the size line says which")
    m.add_argument("--grad", type=float, default=None, help="gradient limit of the size function")
    m.add_argument("--h-max", type=float, default=None)
    m.add_argument("--no-periodic", action="store_true",
                   help="the input is not periodic: inclusions are cut by the box, each face meshed on its own, "
                        "no node pairs")
    m.add_argument("--max-elements", type=float, default=MeshConfig.max_elements,
                   help="stop before the surfaces when the size function asks for more tetrahedra than this "
                        "(default %(default).3g; 0: no limit)")
    m.add_argument("--backend", choices=("conforming", "tetwild"), default="conforming",
                   help="3D volume mesher: conforming (default: exact surfaces, periodic or not) or tetwild (fTetWild: "
                        "robust to damaged surfaces, not conforming, not periodic; edge length --h or --iis)")
    m.add_argument("--roll", nargs="+", default=None, metavar="auto|K",
                   help="periodic grid inputs: mesh the grid rolled so that sample K_a lies at x_a = 0; 'auto' "
                        "takes the sample whose box is farthest from grazing meetings with the interfaces (box "
                        "planes, edges or corners grazing an interface leave thin wedges of bad elements). The "
                        "mesh is in the rolled frame; the report's metadata.roll gives the offset. Without "
                        "--roll, a periodic grid whose box as given comes under a sixth of a grid step from "
                        "such a meeting is meshed with 'auto', and one whose meshing fails is meshed once more "
                        "with 'auto' (--roll 0 0 0: the frame as given, always)")
    m.add_argument("--redistance", action=argparse.BooleanOptionalAction, default=None, help=_REDISTANCE_HELP)
    m.add_argument("--close-box-layers", action=argparse.BooleanOptionalAction, default=None, help=_CLOSE_LAYERS_HELP)
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--report", default=None, help="JSON report path")
    m.add_argument("--plot", default=None, help="PNG path: mesh coloured by phase + quality histogram")
    m.set_defaults(func=_cmd_mesh)

    v = sub.add_parser("validate", help="check a mesh file (and its conformity to an input)")
    v.add_argument("mesh")
    v.add_argument("--geometry", default=None, help="the input the mesh was made from")
    v.add_argument("--box", type=float, nargs="+", default=None)
    v.add_argument("--report", default=None, help="JSON report path")
    v.add_argument("--no-periodic", action="store_true", help="a plain box mesh: no periodic node pairs to check")
    v.add_argument("--roll", nargs="+", default=None, metavar="auto|K",
                   help="the --roll the mesh was made with (the geometry is read rolled the same way; default: "
                        "what a .vtu, .msh, .xdmf, .inp or .npz written by jaxmesh says)")
    v.add_argument("--redistance", action="store_true",
                   help="the mesh was made with --redistance (default: what the mesh file says, as for --roll)")
    v.add_argument("--close-box-layers", action="store_true",
                   help="the mesh was made with --close-box-layers (default: what the mesh file says)")
    v.set_defaults(func=_cmd_validate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # interface nodes on the level set to 1e-12, not 1e-7
    enable_compilation_cache()  # a second run skips ~10 s of compiling
    try:
        return int(args.func(args) or 0)
    except (ValueError, MeshingError, FileNotFoundError) as exc:
        print(f"jaxmesh {args.command}: error: {exc}", file=sys.stderr)
        if isinstance(exc, MeshingError) and getattr(args, "backend", None) == "conforming" and \
                exc.stage in ("surfaces", "volume"):
            print("jaxmesh mesh: hint: --backend tetwild gives a valid but non-conforming, non-periodic mesh "
                  "of such inputs", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
