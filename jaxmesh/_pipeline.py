"""One call from a microstructure (or an input file) to a validated mesh (periodic by default).

Stages (paper 4.1): size function -> inclusion surfaces and box faces -> octree interior nodes ->
conforming tetrahedralisation, labels, relaxation, sliver removal. 2D inputs go to the 2D mesher.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ._errors import MeshingError
from ._generate import checked_seed


_FIELD_HINTS = {
    "iis": "sizes are in box units, e.g. iis=0.05 for a unit box",
    "h_max": "sizes are in box units, e.g. h_max=0.2 for a unit box",
    "h": "sizes are in box units, e.g. h=0.05 for a unit box",
    "nb_el": "a count of elements across the narrowest gaps, e.g. nb_el=3 (fractions allowed, e.g. 0.5)",
    "curv_alpha": "h = curv_alpha / |curvature|, e.g. curv_alpha=0.5 (smaller: finer on curved interfaces)",
    "grad": "the size function's gradient limit, e.g. grad=0.3 (h grows by at most 0.3 per unit length)",
    "max_elements": "a tetrahedron count, e.g. max_elements=5e6, or None for no limit",
}


DEFAULT_IIS = 0.05  # of the box's mean side: the paper's coarse setting on a unit box


def default_iis(box) -> float:
    """DEFAULT_IIS times the box's mean side (the geometric mean of its sides)."""
    return float(f"{DEFAULT_IIS * math.prod(box) ** (1.0 / len(box)):.12g}")  # 0.5, not 0.49999999999999994


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    """Parameters of :func:`mesh_rve`, validated on construction.

    Attributes:
        iis: initial interface size (largest element size on the interfaces), a length in the box's
            units. None (default): 0.05 times the box's mean side (the geometric mean, (L_1 ... L_d)^(1/d)),
            the paper's coarse setting for a unit box, so the defaults mesh a box in mm as they mesh
            the same box in m (curv_alpha, nb_el and grad are dimensionless).
        nb_el: elements across the narrowest gaps (h_nar = DN2 / nb_el); min(nb_el, 1) across a layer
            the box cuts off (a shallow cap, a trace beside a box edge).
        curv_alpha: curvature sensitivity (h_curv = curv_alpha / |kappa|).
        curv_average: grid steps over which each inclusion's mean and Gaussian curvatures are
            averaged before h_curv; 0: pointwise. A field sampled from voxels (a distance transform
            of an image, a quantised field) has an interpolant that ripples at the grid scale, and
            pointwise every ripple asks for elements a quarter of a grid step; 1.5 steps cancel
            the ripples and keep a curvature the grid resolves (a sphere's exactly). None
            (default): 1.5 on the inclusions whose interfaces ripple (half of the interface with
            radii under two grid steps, most of that cancelled by the average), pointwise elsewhere;
            the size line says which.
        grad: gradient limit of the size function.
        h_max: largest element size (None: 4 * iis).
        h: a uniform element size instead of the size function (None: use the size function).
        periodic: periodic mesh (node pairs on opposite faces).
        seed: seed of every random choice (node jitter, thinning).
        validate: run the validator at the end and store its report in the metadata.
        interior: interior nodes of the volume stage: "bcc" (graded body-centred cubic lattices on h,
            the better quality measured so far, see benchmarks/README.md) or "octree" (paper 4.3).
        max_elements: refuse (ValueError, before the surfaces) a 3D conforming mesh whose size function
            predicts more tetrahedra than this; None: no limit. The estimate is
            _TETS_PER_PREDICTED * c * integral of h^-3 (`cellwise_element_count`).
        roll: None (default: the box as given, unless it comes closer than a sixth of a grid step to a
            grazing meeting with the interface, where flat elements form: then a periodic file input or
            periodic Microstructure that can roll (`Microstructure.can_roll`) is meshed with "auto" and
            metadata['roll']['grazing_as_given'] is True; when the frame as given fails with a
            MeshingError, it is meshed once more with "auto" and metadata['roll']['after_failure']
            keeps the first error), "auto" or d integers (zeros: as given, no second try): mesh a
            periodic grid rolled so that sample roll[a] lies at x_a = 0.
            "auto" takes the sample whose frame keeps the box farthest from every grazing meeting with
            the interface (a box plane near a point where the interface is tangent to it or near an
            inclusion's extreme, in 3D a box edge near a face trace's tangency, a corner near the
            interface, a plane or edge crossed at a shallow angle; `box_plane_clearances`): those leave
            wedges thinner than the elements. The mesh is in the rolled frame;
            metadata['roll'] gives the samples and the offset (mesh x = file x - offset, mod L).
        backend: 3D volume mesher. "conforming" (default): keeps every surface triangle, periodic or not.
            "tetwild": fTetWild (pytetwild) on the marching-cubes surface of the grid at edge length
            h (or iis), robust to damaged surfaces but NOT conforming (interface nodes only near the
            level set), NOT periodic (no node pairs) and labelled by the field at the centroids.
        redistance: True: a level-set input (a file, or a Microstructure from from_levelset) is first
            made a first-order signed distance to its zero set (`Microstructure.redistanced`): for
            fields far from a distance, whose nearly flat zero sets (saddles close to the threshold)
            fold the surfaces; labelled images and analytic inclusions are distances already. None
            (default): the field as given; when that fails with a MeshingError that redistancing
            removes (a fold of a nearly flat level set, a surface node stalled off it), or with any
            MeshingError while the field is far from a distance (its inclusions' slope_spread above
            1.5), a level-set input is meshed once more redistanced and
            metadata['redistance']['after_failure'] keeps the first error. False: as given, no
            second try.
        close_box_layers: plain boxes (periodic=False), level-set inputs: True: first close the layers
            along the box planes thinner than a sixth of a grid step (`Microstructure.with_box_layers_closed`:
            an interface grazing a plane from inside moves onto it, a sheet of inclusion along it is
            dropped; the interface moves by at most that much, there only). None (default): as given;
            when the volume recovery stops where an interface grazes a box plane, meshed once more
            closed and metadata['close_box_layers']['after_failure'] keeps the first error. False: never.
    """

    iis: float | None = None
    nb_el: float = 3.0
    curv_alpha: float = 0.5
    curv_average: float | None = None
    grad: float = 0.3
    h_max: float | None = None
    h: float | None = None
    periodic: bool = True
    seed: int = 0
    validate: bool = True
    interior: str = "bcc"
    max_elements: float | None = 5e6
    backend: str = "conforming"
    roll: str | tuple[int, ...] | None = None
    redistance: bool | None = None
    close_box_layers: bool | None = None

    def __post_init__(self):
        for name in ("iis", "nb_el", "curv_alpha", "grad", "h_max", "h", "max_elements"):
            value = getattr(self, name)
            if value is None and name in ("iis", "h_max", "h", "max_elements"):
                continue
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or value <= 0:
                raise ValueError(
                    f"MeshConfig.{name}: expected a positive finite number, got {value!r}; hint: {_FIELD_HINTS[name]}"
                )
        checked_seed(self.seed, "MeshConfig.seed")
        if self.curv_average is not None:
            from ._sizing import check_curvature_average

            check_curvature_average(self.curv_average, "MeshConfig.curv_average")
        if self.backend not in ("conforming", "tetwild"):
            raise ValueError(f"MeshConfig.backend: expected 'conforming' or 'tetwild', got {self.backend!r}")
        if self.interior not in ("bcc", "octree"):
            raise ValueError(f"MeshConfig.interior: expected 'bcc' or 'octree', got {self.interior!r}")
        if self.roll is not None and self.roll != "auto" and not (
                isinstance(self.roll, tuple) and all(isinstance(k, int) and not isinstance(k, bool) for k in self.roll)):
            raise ValueError(f"MeshConfig.roll: expected None, 'auto' or a tuple of integers, got {self.roll!r}")
        if self.roll is not None and not self.periodic:
            raise ValueError("MeshConfig.roll needs periodic=True: the faces of a plain box are the domain's")
        if self.redistance is not None and not isinstance(self.redistance, bool):
            raise ValueError(f"MeshConfig.redistance: expected None, True or False, got {self.redistance!r}")
        if self.close_box_layers is not None and not isinstance(self.close_box_layers, bool):
            raise ValueError(f"MeshConfig.close_box_layers: expected None, True or False, got {self.close_box_layers!r}")
        if self.close_box_layers and self.periodic:
            raise ValueError("MeshConfig.close_box_layers needs periodic=False: a periodic field's box planes are no "
                             "boundary (roll moves them off the inclusions instead)")
        if self.h_max is not None and self.iis is not None and self.h_max < self.iis:
            raise ValueError(f"MeshConfig.h_max: expected >= iis = {self.iis:g}, got {self.h_max}")

    def for_box(self, box) -> MeshConfig:
        """This configuration with iis set: DEFAULT_IIS times the box's mean side when it is None."""
        if self.iis is not None:
            return self
        iis = default_iis(box)
        if self.h_max is not None and self.h_max < iis:
            raise ValueError(f"MeshConfig.h_max: expected >= iis = {iis:g} (the default, {DEFAULT_IIS} times the box's "
                             f"mean side), got {self.h_max}; hint: pass iis too, or a larger h_max")
        return dataclasses.replace(self, iis=iis)

    def size_kwargs(self) -> dict:
        """The size-function parameters (SizeParams keywords); iis left out while it is None."""
        out = {"iis": self.iis, "nb_el": self.nb_el, "curv_alpha": self.curv_alpha, "grad": self.grad,
               "h_max": self.h_max}
        return {key: value for key, value in out.items() if value is not None}


def _check_sizes_against_box(config: MeshConfig, box) -> None:
    shortest = min(box)
    size = config.h if config.h is not None else config.iis
    if size > 0.5 * shortest:
        raise ValueError(
            f"element size {size:g} is larger than half the shortest box side ({shortest:g}); "
            "hint: iis / h are lengths in box units, e.g. 0.05 for a unit box"
        )
    if size < 2e-3 * shortest:
        raise ValueError(
            f"element size {size:g} is below 1/500 of the shortest box side ({shortest:g}): "
            "that is hundreds of millions of elements; hint: use a larger iis / h"
        )


def _as_microstructure(source, box=None, periodic: bool = True, roll=None, redistance: bool = False,
                       close_box_layers: bool = False, may_roll: bool = True):
    """The Microstructure of source, the roll applied ({} when none), and how close the box comes to a
    grazing meeting with the interface when it was kept (roll None, not rolled) or given (d integers);
    None after "auto" and where it does not apply (a plain box, no inclusion). roll None rolls as "auto"
    when the box as given is closer than `_grazing_floor`, the input can roll and may_roll (the
    conforming backend); the roll's info then has "grazing_as_given"."""
    from .geometry._microstructure import Microstructure
    from .io._read import load_input

    if isinstance(source, Microstructure):
        can_roll = source.can_roll
        if roll is not None and not can_roll:
            raise ValueError("MeshConfig.roll needs an input file or a periodic Microstructure built by "
                             "from_levelset, from_labels or from_functions; hint: pass the path")
        ms = source.redistanced() if redistance and source.can_redistance else source
        reread = ms.rolled
        if close_box_layers and ms.can_close_box_layers:  # level sets on a plain box only, as redistance
            ms = ms.with_box_layers_closed()
    elif isinstance(source, (str, Path)):
        ms = load_input(source, box=box, periodic=periodic, redistance=redistance,
                        close_box_layers=close_box_layers and not periodic)
        can_roll = ms.can_roll
        reread = lambda samples: load_input(source, box=box, periodic=periodic, roll=samples,  # noqa: E731
                                            redistance=redistance)
    else:
        raise ValueError(
            f"expected a Microstructure or an input path (.npy/.npz/.tif), got {type(source).__name__}; "
            "hint: jaxmesh.load_input(path) or Microstructure.from_levelset(phi)"
        )
    grazing = None
    if roll is None:
        if not ms.periodic or not ms.inclusions:
            return ms, {}, None
        as_given = float(box_plane_clearances(ms, origin_only=True)[0][(0,) * ms.dim])
        if as_given >= _grazing_floor(ms) or not (may_roll and can_roll):
            return ms, {}, as_given
        roll, grazing = "auto", as_given
    clear, best = box_plane_clearances(ms)
    if grazing is not None and not any(best):
        return ms, {}, grazing
    samples = best if roll == "auto" else tuple(roll)
    if len(samples) != ms.dim:
        raise ValueError(f"MeshConfig.roll: expected {ms.dim} integers for this {ms.dim}D input, got {samples}")
    samples = tuple(k % n for k, n in zip(samples, ms.grid_shape))
    step = np.asarray(ms.box, float) / np.asarray(ms.grid_shape)
    info = {"samples": [int(k) for k in samples], "offset": [float(k * s) for k, s in zip(samples, step)],
            "clearance_before": float(clear[(0,) * ms.dim]), "clearance_after": float(clear[samples])}
    if grazing is not None:
        info["grazing_as_given"] = True
    if any(samples):
        ms = reread(samples)
    return ms, info, None if roll == "auto" else info["clearance_after"]


def box_plane_clearances(ms, origin_only: bool = False) -> tuple[np.ndarray, tuple[int, ...]]:
    """For a periodic microstructure, the array (grid_shape) of how close the box of the frame whose
    corner is each sample comes to a grazing meeting with the interface (a tangency, an inclusion's
    extreme, or a shallow crossing; `_periodic.frame_clearance` of dn1), and the clearest sample
    (`_periodic.clearest_frame`).
    origin_only: the frame as given only (an array of ones in shape; about a quarter of the cost), the sample zeros."""
    from ._periodic import clearest_frame, frame_clearance

    lower = np.array([inc.lower for inc in ms.inclusions], dtype=float).reshape(-1, ms.dim)
    upper = np.array([inc.upper for inc in ms.inclusions], dtype=float).reshape(-1, ms.dim)
    spans = upper - lower >= np.asarray(ms.box) * (1 - 1e-12)  # percolates along that axis: no extreme there
    lower, upper = np.where(spans, np.nan, lower), np.where(spans, np.nan, upper)
    clear = frame_clearance(np.asarray(ms.dn1), ms.box, lower, upper, origin_only=origin_only)
    return clear, (0,) * ms.dim if origin_only else clearest_frame(clear)


def _inside_out_hint(ms) -> str:
    """A note for the input line when the inclusions fill most of the box: a field negative in the
    matrix (the opposite sign convention) reads as one inclusion around the real ones."""
    fraction = ms.volume_fraction() if ms.inclusions else 0.0
    if fraction <= 0.7:
        return ""
    return (f"; note: the inclusions fill {fraction:.0%} of the box; jaxmesh takes phi < 0 (labels > 0) inside "
            "them: if your field is negative in the matrix, pass -phi")


def _closed_layers_note(ms) -> str:
    closed = ms.inclusions[0].description.get("box_layers_closed") if ms.inclusions else None
    return "" if closed is None else (f"; layers along the box planes thinner than a sixth of a step closed "
                                      f"({closed} box-plane samples changed)")


def _parts_note(ms) -> str:
    """A note for the input line when a label of an image came in several regions (a phase image):
    each region is its own inclusion, and the cell data `label` keeps the image value."""
    parts = Counter(inc.description["label"] for inc in ms.inclusions if "part" in inc.description)
    split = sorted((label, count) for label, count in parts.items() if count > 1)
    if not split:
        return ""
    listed = ", ".join(f"label {label}: {count}" for label, count in split[:8])
    more = f" and {len(split) - 8} more" if len(split) > 8 else ""
    return (f"; image labels in several regions, one inclusion per region ({listed}{more}); cell data 'label' "
            "keeps the image value")


def _grazing_floor(ms) -> float:
    """The size function's box-gap floor, a sixth of a grid step: a periodic box closer than this to a
    grazing meeting with the interface (`box_plane_clearances`) leaves a wedge of flat elements."""
    return min(ms.spacing) / 6


_GRAZING_ROLL = (": under a sixth of a grid step, where flat elements form, so the default rolled it; "
                 "roll=(0, 0, 0) / --roll 0 0 0 keeps the frame")


def _grazing_hint(ms, clear: float | None) -> str:
    """A note for the input line when the periodic box, kept as given or as the roll gave it, comes closer
    than `_grazing_floor` to a grazing meeting with the interface (clear: `_as_microstructure`'s)."""
    if clear is None or clear >= _grazing_floor(ms):
        return ""
    return (f"; note: the box passes {clear:.2g} from a grazing meeting with the interface (the interface "
            "tangent to a box plane or crossing one at under 9.5 deg, a face's trace likewise with a box edge, or "
            "the interface at a box corner), under a sixth of a grid step: expect flat tets there (the box is "
            "kept: the roll was given, no frame of the grid is clearer, or this input cannot roll)")


def mesh_rve(source, config: MeshConfig | None = None, *, box=None, progress: Callable[[str], None] | None = None):
    """Periodic, conforming, labelled mesh of an RVE (tetrahedra in 3D, triangles in 2D).

    Args:
        source: a ``Microstructure`` or a path to an input file (see ``load_input``).
        config: :class:`MeshConfig` (defaults: the paper's coarse setting).
        box: box lengths for a bare ``.npy`` input.
        progress: called with one line per finished stage (e.g. ``print``).
    Returns:
        ``Mesh`` with ``inclusion_id`` per cell, ``periodic_pairs`` and metadata (per-stage
        ``timings`` in seconds, ``counts``, ``parameters``, and ``validation`` when
        ``config.validate``).
    Raises:
        ValueError: bad input or parameters. MeshingError: a stage failed (names the stage).

    Example:
        >>> mesh = mesh_rve("rve.npz", MeshConfig(iis=0.05))
        >>> mesh.write("rve.vtu")
    """
    config = MeshConfig() if config is None else config
    say = progress or (lambda line: None)
    retries = []  # (the MeshConfig field changed, the failure that made it change)
    while True:
        try:
            mesh = _mesh_rve(source, config, box, say)
            break
        except MeshingError as failure:
            retry = _retry_config(source, config, box, failure)
            if retry is None and not retries:
                raise
            if retry is None:
                first = retries[0][1]
                tried = ", then ".join(f"with {key}={getattr(config, key)!r}" for key, _ in retries)
                raise MeshingError(first.stage, f"{first.message}; meshed again {tried}, it failed too: {failure}",
                                   first.inclusion) from first
            config, key, how = retry
            retries.append((key, failure))
            line = f"{failure}; meshing again {how}"
            say(f"[jaxmesh] retry      {line}")
            if progress is None:  # the frame or the field changes: say so where no progress line shows it
                warnings.warn(line, stacklevel=2)
    for key, failure in retries:
        mesh.metadata.setdefault(key, {})["after_failure"] = str(failure)
    roll = mesh.metadata.get("roll", {})
    if roll.get("grazing_as_given") and progress is None:  # the frame changed: say so where no input line shows it
        warnings.warn(f"the box as given passes {roll['clearance_before']:.2g} from a grazing meeting with the "
                      f"interface{_GRAZING_ROLL}. The mesh is in the rolled frame, metadata['roll'] gives the "
                      "offset", stacklevel=2)
    return mesh


_DISTANCE_SPREAD = 1.5  # a level set's slope_spread above this: far from even a first-order distance


def _retry_config(source, config: MeshConfig, box, failure: MeshingError) -> tuple[MeshConfig, str, str] | None:
    """The next try after a MeshingError: (its configuration, the MeshConfig field it changes, what it
    does, for the progress line), or None when no other try can remove the failure. A level set as
    given is redistanced first when the failure is one that redistancing removes or the field is far
    from a distance (its surfaces fold and its recovery stalls where the slope varies); then a
    plain-box level set whose recovery stopped at a box plane is meshed with its box layers closed,
    and a failure that depends on the frame is meshed rolled."""
    from .geometry._microstructure import Microstructure
    from .io._read import load_input

    if isinstance(source, (str, Path)):  # read once, as the failed try read it
        source = load_input(source, box=box, periodic=config.periodic, redistance=bool(config.redistance))
    if not isinstance(source, Microstructure):
        return None
    if config.redistance is None and source.can_redistance and (
            failure.redistance_helps or source.inclusions[0].description["slope_spread"] > _DISTANCE_SPREAD):
        return dataclasses.replace(config, redistance=True), "redistance", (
            "with the field made a first-order signed distance to its zero set (redistance=True: the same "
            "signs at every sample, the interface moved within its grid cells; validate with --redistance)")
    if (config.close_box_layers is None and failure.at_box_plane and not config.periodic
            and source.can_close_box_layers):
        return dataclasses.replace(config, close_box_layers=True), "close_box_layers", (
            "with the layers along the box planes thinner than a sixth of a grid step closed (close_box_layers="
            "True: the interface there moves onto the plane, or a sheet of inclusion along it is dropped; "
            "validate with --close-box-layers)")
    if failure.frame_dependent and _rolling_helps(source, config):
        return dataclasses.replace(config, roll="auto"), "roll", (
            "with the box moved off grazing meetings with the interface (roll='auto'; the mesh is in the rolled "
            "frame, metadata['roll'] gives the offset; validate with --roll auto)")
    return None


def _rolling_helps(ms, config: MeshConfig) -> bool:
    """Whether a periodic microstructure meshed in its own frame (roll None, its box clear of grazing
    meetings, which the default rolls off; an explicit roll, zeros included, is kept) can roll and rolling
    moves its box farther from grazing meetings with the interface."""
    if config.roll is not None or not config.periodic or config.backend != "conforming" or not ms.can_roll:
        return False
    clear, best = box_plane_clearances(ms)
    as_given = clear[(0,) * ms.dim]
    return _grazing_floor(ms) <= as_given < clear[best]


def _mesh_rve(source, config: MeshConfig, box, say: Callable[[str], None]):
    _warn_if_float32()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}

    def stage(name: str, t0: float, message: str) -> float:
        now = time.perf_counter()
        timings[name] = now - t0
        say(f"[jaxmesh] {name:<10s} {message} ({now - t0:.2f} s)")
        return now

    t = time.perf_counter()
    ms, roll, as_given = _as_microstructure(source, box=box, periodic=config.periodic, roll=config.roll,
                                            redistance=bool(config.redistance),
                                            close_box_layers=bool(config.close_box_layers),
                                            may_roll=config.backend == "conforming")
    config = config.for_box(ms.box)
    if config.backend == "conforming" and ms.periodic != config.periodic:
        raise ValueError(f"MeshConfig.periodic is {config.periodic} but the microstructure has periodic={ms.periodic} "
                         "(its inclusions are connected across the faces only when periodic); hint: build it with "
                         "the same flag (from_levelset(..., periodic=...)) or set MeshConfig(periodic=...) to match")
    _check_sizes_against_box(config, ms.box)
    rolled = (f"; rolled by {tuple(roll['samples'])} samples (the mesh's origin is the file's "
              f"{tuple(round(v, 6) for v in roll['offset'])}; the box {roll['clearance_after']:.3g} from a "
              f"grazing meeting with the interface, {roll['clearance_before']:.3g} unrolled"
              f"{_GRAZING_ROLL if roll.get('grazing_as_given') else ''})") if roll else ""
    t = stage("input", t, f"{ms.dim}D, {len(ms.inclusions)} inclusions, grid {tuple(ms.grid_shape)}{rolled}"
                          f"{_parts_note(ms)}{_grazing_hint(ms, as_given)}"
                          f"{_inside_out_hint(ms)}{_closed_layers_note(ms)}")

    if ms.dim == 2 and config.backend != "conforming":
        raise ValueError(f"backend {config.backend!r} meshes 3D inputs only; hint: 2D inputs use the default backend")
    if ms.dim == 2:
        from ._mesh2d import mesh_2d

        if config.h is not None:
            mesh = mesh_2d(ms, h=config.h, seed=config.seed)
        else:
            mesh = mesh_2d(ms, seed=config.seed, curvature_average=config.curv_average, **config.size_kwargs())
        t = stage("mesh2d", t, f"{mesh.n_points} points, {mesh.n_cells} triangles")
    elif config.backend == "tetwild":
        from ._tetwild import tetwild_mesh

        mesh = tetwild_mesh(ms, config.h if config.h is not None else config.iis)
        t = stage("tetwild", t, f"{mesh.n_points} points, {mesh.n_cells} tetrahedra (not conforming, not periodic)")
    else:
        mesh, t = _mesh_3d(ms, config, stage, t)
    if config.backend == "conforming":
        _refuse_flat_cells(mesh, "mesh2d" if ms.dim == 2 else "volume")

    if config.validate:
        from ._validate import validate

        report = validate(mesh, ms)
        mesh.metadata["validation"] = report.to_dict()
        t = stage("validate", t, "valid" if report.ok else "INVALID: " + ", ".join(report.failed))
    timings["total"] = time.perf_counter() - t_start
    mesh.metadata["inclusions"] = inclusion_table(ms, mesh)
    mesh.metadata["timings"] = timings
    mesh.metadata["parameters"] = dataclasses.asdict(config)
    if roll:
        mesh.metadata["roll"] = roll
    return mesh


def _averaged_note(ids: tuple[int, ...], total: int) -> str:
    if not ids:
        return ""
    which = "the inclusion's interface ripples" if total == 1 else (
        f"{len(ids)} of {total} inclusions' interfaces ripple" if len(ids) > 1 else f"inclusion {ids[0]}'s interface ripples")
    from ._sizing import AUTO_CURVATURE_AVERAGE

    return (f"; curvature averaged over {AUTO_CURVATURE_AVERAGE:g} grid steps: {which} at the grid scale (a field "
            "sampled from voxels, e.g. a distance transform of an image; --curv-average 0 sizes the ripples)")


def _refuse_flat_cells(mesh, stage: str) -> None:
    """MeshingError when a cell is still flat after the quality stages (`_quality.flat_cells`: |V| <=
    FLAT_REL_VOLUME l_max^d, or an angle below FLAT_ANGLE_DEG).

    Seen where an interface touches a box plane (the field is zero there, e.g. a sphere tangent to it
    at a grid node): the matrix between them thins to nothing, so the cells of that cusp stay flat
    however the nodes move. Moving the box planes removes the contact, hence frame_dependent.
    """
    from ._quality import FLAT_ANGLE_DEG, FLAT_REL_VOLUME, flat_cells, worst_cell

    flat, rel, angles = flat_cells(mesh.points, mesh.cells)
    flat &= rel > 0  # an inverted cell is the validator's to report
    if not flat.any():
        return
    # the flattest: the smaller of the two ratios to their bounds
    flatness = np.where(flat, np.minimum(np.abs(rel) / FLAT_REL_VOLUME, angles / FLAT_ANGLE_DEG), np.inf)
    cell = worst_cell(mesh.points, mesh.cells, flatness, mesh.inclusion_id, mesh.box)
    k = cell["index"]
    plane = cell["nearest_box_plane"]
    on_plane = plane["distance"] == 0.0 and cell["on_interface"]
    cause = (f"an interface touches the box plane {'xyz'[plane['axis']]} = {plane['at']:g} there: the domain between "
             "them thins to nothing, thinner than any element; hint: move the box plane off it (a periodic "
             "grid: roll='auto' / --roll auto; a plain box: close_box_layers=True / "
             "--close-box-layers, or move the plane by a grid layer)" if on_plane else
             "the domain there is thinner than any element (interfaces nearly meet there); hint: sample the field "
             "finer or move the interfaces apart")
    name = "tet" if mesh.dim == 3 else "triangle"
    count = f"{int(flat.sum())} {name}s stay" if flat.sum() > 1 else f"a {name} stays"
    raise MeshingError(stage, f"{count} flat after the quality stages (|V| <= {FLAT_REL_VOLUME:g} l_max^{mesh.dim} "
                       f"or an angle below {FLAT_ANGLE_DEG:g} deg; the flattest: V / l_max^{mesh.dim} = {rel[k]:.2g}, "
                       f"angle {angles[k]:.2g} deg) near x = {tuple(round(v, 4) for v in cell['centroid'])}: "
                       f"{cause}", frame_dependent=on_plane, at_box_plane=on_plane)


def inclusion_table(ms, mesh) -> list[dict]:
    """Per inclusion id: its description (a labelled image's original label, an analytic shape's
    kind / centre / axes), its unwrapped bounds, the analytic volume when known, and the volume of
    its cells in the mesh, so that ids map back to the input."""
    from ._quality import signed_volumes

    meshed = np.bincount(mesh.inclusion_id, np.abs(signed_volumes(mesh.points, mesh.cells)),
                         minlength=len(ms.inclusions) + 1)
    return [{"id": inc.id, **inc.description, "lower": np.asarray(inc.lower, float).tolist(),
             "upper": np.asarray(inc.upper, float).tolist(), "volume": inc.volume,
             "meshed_volume": float(meshed[inc.id])} for inc in ms.inclusions]


def _warn_if_float32() -> None:
    import jax

    if not jax.config.jax_enable_x64:
        warnings.warn("jaxmesh.mesh_rve runs in float32 because jax_enable_x64 is off: interface nodes sit on "
                      "the level set to ~1e-7 and the meshes differ from the CLI's (float64); hint: call "
                      "jax.config.update('jax_enable_x64', True) before building the microstructure",
                      stacklevel=3)


def _mesh_3d(ms, config: MeshConfig, stage, t):
    from ._faces import mesh_surfaces
    from ._surface import as_size_fn, evaluate_size
    from ._volume import tetrahedralize
    from ._volume_recover import levelset_projector

    if config.h is not None:
        h_jax = float(config.h)
        h_np = lambda p: np.full(len(p), float(config.h))  # noqa: E731
        t = stage("size", t, f"uniform h = {config.h:g}")
        from ._sizing import _SIMPLEX_DENSITY

        _check_element_budget(config, _SIMPLEX_DENSITY[3] * math.prod(ms.box) / config.h**3, config.h)
    else:
        from ._sizing import SizeParams, cellwise_element_count, size_function

        field = size_function(ms, SizeParams(**config.size_kwargs()), curvature_average=config.curv_average)
        h_jax = field
        h_box = field if ms.periodic else as_size_fn(field, ms.box, periodic=False)  # clamped at the far faces
        h_np = lambda p: evaluate_size(h_box, p)  # noqa: E731  (compiled once per size bucket, not op by op)
        values = np.asarray(field.values)
        predicted = cellwise_element_count(values, ms.box)
        t = stage("size", t, f"h in [{values.min():.4f}, {values.max():.4f}], "
                             f"~{_TETS_PER_PREDICTED * predicted:.3g} tetrahedra expected"
                             + (_averaged_note(field.curvature_averaged, len(ms.inclusions))
                                if config.curv_average is None else ""))
        _check_element_budget(config, predicted, float(values.min()))

    surface = mesh_surfaces(ms, h_jax)
    resampled = surface.metadata.get("resampled_inclusions") or {}
    note = (f"; inclusions {sorted(resampled)} sampled again (their triangles crossed or folded, or their traces "
            "did not fit a box face)" if resampled else "")
    t = stage("surfaces", t, f"{surface.n_points} nodes, {surface.n_triangles} triangles{note}")

    interior = _interior_nodes(ms, h_np, config)
    if interior is not None:
        t = stage("octree", t, f"{len(interior)} interior nodes")

    mesh = tetrahedralize(surface, interior, h_fn=h_np, project_fn=levelset_projector(ms.inclusion_phi),
                          label_fn=ms.label, phi_fn=ms.phi)
    t = stage("volume", t, f"{mesh.n_points} points, {mesh.n_cells} tetrahedra")
    mesh.metadata.setdefault("counts", {}).update(
        {"surface_points": surface.n_points, "surface_triangles": surface.n_triangles}
    )
    return mesh, t


# tetrahedra per element of c * integral of h^-3 (c = 6 sqrt(2)): the Table-1 meshes of
# benchmarks/README.md come out 1.8x (coarse) to 2.4x (fine) that (measured with the node sum
# `predicted_element_count`, which the cellwise count matches where h varies little within a cell);
# the boundary layers and the grading add to the regular-simplex count
_TETS_PER_PREDICTED = 2.5


def _check_element_budget(config: MeshConfig, predicted: float, h_min: float) -> None:
    expected = _TETS_PER_PREDICTED * predicted
    if config.max_elements is not None and expected > config.max_elements:
        raise ValueError(
            f"the size function asks for about {expected:.3g} tetrahedra (h down to {h_min:.3g}), more than "
            f"max_elements = {config.max_elements:.3g}. Hint: coarsen with a larger iis, a smaller nb_el "
            "(elements across narrow gaps), a larger curv_alpha or grad, or a larger h; or raise max_elements "
            "(--max-elements) when the machine has the memory and time for it"
        )


def _interior_nodes(ms, h_np, config: MeshConfig):
    """Octree nodes on h (paper 4.3), or None to let the volume stage fill with graded BCC lattices."""
    if config.interior == "bcc":
        return None
    from ._octree import periodic_octree_nodes

    coords = ms.coordinates().reshape(-1, ms.dim)
    h_grid = h_np(coords).reshape(tuple(ms.grid_shape))
    nodes = periodic_octree_nodes(h_grid, ms.box, interface_phi=np.asarray(ms.dn1))
    return np.asarray(nodes.points, dtype=np.float64)
