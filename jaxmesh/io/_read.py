"""Reading microstructure inputs: level-set fields and labelled images (.npy, .npz, .tif, .vti).

Array axis 0 is x (then y, z), samples on the node-centred grid x_i = i * L / n. Every failure
(missing file, unknown format, missing key, bad content) is a ValueError with a hint, raised
before anything is traced.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

_FORMATS = ".npy (level set or labels), .npz (keys phi or labels, or one unnamed array; optional box, periodic), .tif/.tiff, .vti"


def _fail(path, what: str, hint: str):
    raise ValueError(f"load_input({str(path)!r}): {what}. Hint: {hint}")


def _construct(path, kind: str, array, box, periodic, **options):
    """Microstructure.from_<kind>, its ValueError prefixed with the file."""
    from ..geometry._microstructure import Microstructure  # lazy: reading a file needs no jax

    try:
        return getattr(Microstructure, f"from_{kind}")(array, box=box, periodic=periodic, **options)
    except ValueError as err:
        raise ValueError(f"load_input({str(path)!r}): {err}") from None


def _rolled(array: np.ndarray, roll, periodic: bool, path) -> np.ndarray:
    """The periodic grid rolled so that sample roll[a] comes first along each axis a."""
    if roll is None:
        return array
    if not periodic:
        _fail(path, f"roll={tuple(roll)} needs a periodic input (the faces of a plain box are the domain's)",
              "drop the roll, or read the input as periodic")
    if len(roll) != array.ndim or not all(isinstance(k, (int, np.integer)) for k in roll):
        _fail(path, f"expected roll as {array.ndim} integers (grid samples per axis), got {roll!r}",
              "e.g. roll=(32, 0, 0) puts sample 32 along x at x = 0")
    return np.roll(array, [-int(k) for k in roll], axis=tuple(range(array.ndim)))


def _build(array: np.ndarray, box, periodic: bool, path, levelset_options: dict):
    """Level set if real-valued (levelset_options go to from_levelset), labelled image if integer / bool."""
    if array.dtype.kind in "biu":
        return _construct(path, "labels", array, box, periodic)
    if array.dtype.kind == "f":
        return _construct(path, "levelset", array, box, periodic, **levelset_options)
    _fail(path, f"expected a float (level set) or integer/bool (labels) array, got dtype {array.dtype}",
          "save phi as float64 or labels as an integer image")


def _read_npz(path: Path, box, periodic, roll, levelset_options: dict):
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {key: npz[key] for key in npz.files}
    except Exception as err:
        _fail(path, f"could not read it as .npz ({err})", "write it with numpy.savez")
    grids = [key for key in data if key not in ("box", "periodic")]
    single = grids == ["arr_0"]  # np.savez(path, phi): one unnamed grid
    if "phi" not in data and "labels" not in data and not single:
        _fail(path, f"expected a key 'phi' (level set) or 'labels' (labelled image), got keys {sorted(data)}",
              "np.savez(path, phi=phi, box=box) or np.savez(path, labels=labels)")
    if "kind" in data and "box" in data and box is not None and (
            np.shape(box) != np.shape(data["box"]) or not np.allclose(box, data["box"], rtol=1e-12, atol=0)):
        _fail(path, f"box {tuple(float(v) for v in box)} given, but the file's analytic inclusions are placed in its "
                    f"own box {tuple(np.asarray(data['box'], float).tolist())}", "drop --box, or generate the RVE "
                    "with that --box")
    if box is None and "box" in data:
        box = tuple(np.asarray(data["box"], dtype=float).ravel().tolist())
    if periodic is None:
        periodic = bool(np.asarray(data["periodic"]).item()) if "periodic" in data else True
    if single:  # read as a .npy
        return _build(_rolled(np.asarray(data["arr_0"]), roll, periodic, path), box, periodic, path, levelset_options)
    if roll is not None:
        key = "phi" if "phi" in data else "labels"
        shape = np.shape(data[key])
        data[key] = _rolled(np.asarray(data[key]), roll, periodic, path)
        if "centers" in data:  # analytic inclusions move with the grid
            length = np.asarray(box if box is not None else (1.0,) * len(shape), dtype=float)
            data["centers"] = np.mod(np.asarray(data["centers"], float) - np.asarray(roll) * length / shape, length)
    if "kind" in data:  # analytic inclusions written by jaxmesh._generate: rebuild them exactly
        try:
            from .._generate import microstructure_from_npz
        except ImportError:
            microstructure_from_npz = None
        if microstructure_from_npz is not None:
            merged = dict(data, periodic=np.asarray(periodic))
            if box is not None:
                merged["box"] = np.asarray(box, dtype=float)
            built = microstructure_from_npz(merged)
            if built is not None:
                return built
    if "phi" in data:
        phi = np.asarray(data["phi"])
        if phi.dtype.kind not in "f":
            _fail(path, f"expected 'phi' to hold real level-set values, got dtype {phi.dtype}",
                  "store labelled images under the key 'labels'")
        return _construct(path, "levelset", phi, box, periodic, **levelset_options)
    labels = np.asarray(data["labels"])
    if labels.dtype.kind not in "biu":
        _fail(path, f"expected 'labels' to hold integers or bools, got dtype {labels.dtype}",
              "store level sets under the key 'phi', or cast labels with .astype(int)")
    return _build(labels, box, periodic, path, levelset_options)


def _read_vti(path: Path, box, periodic, roll, levelset_options: dict):
    try:
        import pyvista
    except ImportError:
        _fail(path, ".vti needs pyvista, which is not installed", "pip install pyvista, or save as .npy/.npz")
    try:
        image = pyvista.read(str(path))
    except Exception as err:
        _fail(path, f"pyvista could not read it ({err})", "check that it is a VTK ImageData (.vti) file")
    names = list(image.point_data.keys())
    name = next((n for n in ("phi", "labels") if n in names), names[0] if names else None)
    if name is None:
        _fail(path, "expected point data (one value per grid node), got none",
              "store phi or labels as point data on the image")
    dims = [int(n) for n in image.dimensions if n > 1]
    array = np.asarray(image.point_data[name]).reshape(dims[::-1]).transpose()  # VTK: x fastest
    if box is None:
        box = tuple(float(n * h) for n, h in zip(image.dimensions, image.spacing) if n > 1)
    return _build(_rolled(array, roll, periodic, path), box, periodic, path, levelset_options)


def load_input(path, box=None, periodic: bool | None = None, roll=None, redistance: bool = False,
               close_box_layers: bool = False):
    """Read a microstructure from a file.

    Args:
        path: .npy (float: level set; integer/bool: labels), .npz (key 'phi' or 'labels',
            optional 'box' and 'periodic'; a single unnamed grid, 'arr_0', is read as a .npy; analytic inclusions written by jaxmesh.generate are
            rebuilt exactly when that module is available), .tif/.tiff (integer: labels, else
            level set; array axis 0 = x), .vti (pyvista; point data 'phi' or 'labels' or the first).
        box: (d,) cell lengths; overrides the file's (except for a file from `jaxmesh generate` with
            analytic inclusions, placed in its own box: another box is refused); default from the
            file, else the unit cube.
        periodic: overrides the file's 'periodic'; default from the file, else True.
        roll: optional d integers: read the periodic grid rolled so that sample roll[a] lies at
            x_a = 0 (the box faces move to x_a = roll[a] L_a / n_a of the file's frame; the mesh is
            then in the rolled frame). Analytic inclusions move with it. See `clearest_roll`.
        redistance: level sets only (labelled images and analytic inclusions are distances
            already): see `Microstructure.from_levelset`.
        close_box_layers: level sets on a plain box only (periodic False), ignored for labelled
            images and analytic inclusions: see `Microstructure.from_levelset`.

    Returns:
        A Microstructure.

    Raises:
        ValueError: missing file, unknown extension, missing key, or invalid content.

    Example:
        >>> ms = load_input("rve.npz")
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"load_input expected a file path, got {type(path).__name__}. "
                         "Hint: pass a str or pathlib.Path.")
    path = Path(path)
    if not path.is_file():
        _fail(path, "no such file", "check the path (relative paths start from the working directory)")
    ext = "".join(path.suffixes[-1:]).lower()
    levelset_options = {"redistance": redistance, "close_box_layers": close_box_layers}
    if ext == ".npz":
        return _read_npz(path, box, periodic, roll, levelset_options)
    periodic = True if periodic is None else periodic
    if ext == ".npy":
        try:
            array = np.load(path, allow_pickle=False)
        except Exception as err:
            _fail(path, f"could not read it as .npy ({err})", "write it with numpy.save")
        return _build(_rolled(np.asarray(array), roll, periodic, path), box, periodic, path, levelset_options)
    if ext in (".tif", ".tiff"):
        try:
            from skimage import io as skio

            array = np.asarray(skio.imread(str(path)))
        except Exception as err:
            _fail(path, f"could not read the TIFF ({err})", "save a single-channel 2D image or 3D stack")
        return _build(_rolled(array, roll, periodic, path), box, periodic, path, levelset_options)
    if ext == ".vti":
        return _read_vti(path, box, periodic, roll, levelset_options)
    _fail(path, f"unknown extension {ext or '(none)'!r}", f"supported formats: {_FORMATS}")
