"""load_input: .npy / .npz / .tif / .vti round trips and clear errors for bad files."""

import importlib.util

import numpy as np
import pytest

from jaxmesh.geometry._microstructure import Microstructure
from jaxmesh.io._read import load_input


def _field(n=24, d=3, box=1.0):
    x = np.arange(n) * (box / n)
    X = np.stack(np.meshgrid(*[x] * d, indexing="ij"), axis=-1)
    dd = X - 0.5 * box
    dd -= box * np.round(dd / box)
    return np.linalg.norm(dd, axis=-1) - 0.25 * box


def _same(a: Microstructure, b: Microstructure):
    assert a.box == b.box and a.periodic == b.periodic and len(a.inclusions) == len(b.inclusions)
    np.testing.assert_allclose(a.dn1, b.dn1, atol=1e-12)
    np.testing.assert_array_equal(a.nearest_id, b.nearest_id)


def test_npy_levelset_and_labels(tmp_path):
    phi = _field()
    np.save(tmp_path / "phi.npy", phi)
    ms = load_input(tmp_path / "phi.npy")
    _same(ms, Microstructure.from_levelset(phi))
    assert load_input(str(tmp_path / "phi.npy"), box=(2.0, 2.0, 2.0)).box == (2.0, 2.0, 2.0)
    labels = (phi < 0).astype(np.uint8) * 5
    np.save(tmp_path / "labels.npy", labels)
    ms = load_input(tmp_path / "labels.npy")
    assert ms.inclusions[0].description["label"] == 5
    _same(ms, Microstructure.from_labels(labels))
    np.save(tmp_path / "mask.npy", phi < 0)
    assert len(load_input(tmp_path / "mask.npy").inclusions) == 1


def test_npz_keys_box_and_periodic(tmp_path):
    phi = _field(32, 2, box=2.0)
    np.savez(tmp_path / "a.npz", phi=phi, box=np.array([2.0, 2.0]))
    ms = load_input(tmp_path / "a.npz")
    assert ms.box == (2.0, 2.0) and ms.periodic
    _same(ms, Microstructure.from_levelset(phi, box=(2.0, 2.0)))
    assert load_input(tmp_path / "a.npz", box=(4.0, 4.0)).box == (4.0, 4.0)  # the argument wins
    np.savez(tmp_path / "b.npz", phi=phi, box=np.array([2.0, 2.0]), periodic=np.array(False))
    assert not load_input(tmp_path / "b.npz").periodic
    assert load_input(tmp_path / "b.npz", periodic=True).periodic
    np.savez(tmp_path / "c.npz", labels=(phi < 0).astype(np.int32))
    assert load_input(tmp_path / "c.npz").box == (1.0, 1.0)
    np.savez(tmp_path / "d.npz", phi, box=np.array([2.0, 2.0]))  # unnamed: 'arr_0', read as a .npy
    _same(load_input(tmp_path / "d.npz"), Microstructure.from_levelset(phi, box=(2.0, 2.0)))
    np.savez(tmp_path / "e.npz", (phi < 0).astype(np.int32))
    assert load_input(tmp_path / "e.npz").inclusions[0].description["label"] == 1


@pytest.mark.skipif(importlib.util.find_spec("tifffile") is None, reason="needs tifffile")
def test_tiff_round_trip(tmp_path):
    import tifffile

    phi = _field(24, 3).astype(np.float32)
    tifffile.imwrite(tmp_path / "phi.tif", phi)
    ms = load_input(tmp_path / "phi.tif")
    assert ms.grid_shape == (24, 24, 24) and len(ms.inclusions) == 1
    tifffile.imwrite(tmp_path / "labels.tiff", (phi < 0).astype(np.uint16) * 2)
    assert load_input(tmp_path / "labels.tiff").inclusions[0].description["label"] == 2


@pytest.mark.skipif(importlib.util.find_spec("pyvista") is None, reason="needs pyvista")
def test_vti_round_trip(tmp_path):
    import pyvista

    n = (24, 20, 16)
    x = [np.arange(k) / 24 for k in n]  # spacing 1/24 on every axis: box (1, 5/6, 2/3)
    X = np.stack(np.meshgrid(*x, indexing="ij"), axis=-1)
    phi = np.linalg.norm(X - np.array([0.5, 0.4, 0.33]), axis=-1) - 0.2
    image = pyvista.ImageData(dimensions=n, spacing=(1 / 24,) * 3)
    image.point_data["phi"] = phi.ravel(order="F")  # VTK: x fastest
    image.save(tmp_path / "phi.vti")
    ms = load_input(tmp_path / "phi.vti")
    assert ms.grid_shape == n
    np.testing.assert_allclose(ms.box, (1.0, 20 / 24, 16 / 24))
    assert ms.label(np.array([[0.5, 0.4, 0.33], [0.1, 0.1, 0.1]])).tolist() == [1, 0]


def test_bad_files(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_input(tmp_path / "missing.npy")
    (tmp_path / "x.csv").write_text("1,2\n")
    with pytest.raises(ValueError, match="unknown extension '.csv'.*supported"):
        load_input(tmp_path / "x.csv")
    np.savez(tmp_path / "k.npz", values=np.zeros((8, 8)))
    with pytest.raises(ValueError, match="'phi'.*'labels'.*got keys \\['values'\\]"):
        load_input(tmp_path / "k.npz")
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    with pytest.raises(ValueError, match="could not read"):
        load_input(tmp_path / "bad.npy")
    np.save(tmp_path / "empty.npy", np.ones((16, 16)))
    with pytest.raises(ValueError, match="empty.npy.*no negative values"):
        load_input(tmp_path / "empty.npy")
    np.save(tmp_path / "c.npy", np.zeros((8, 8), complex))
    with pytest.raises(ValueError, match="dtype complex"):
        load_input(tmp_path / "c.npy")
    with pytest.raises(ValueError, match="file path"):
        load_input(42)
    # an integer array is a label image; one with negative values is most likely a level set in whole numbers
    x = np.arange(16) - 7.5
    np.save(tmp_path / "int_phi.npy", np.round(np.hypot(*np.meshgrid(x, x, indexing="ij")) - 4).astype(np.int32))
    with pytest.raises(ValueError, match=r"labels >= 0.*got minimum -3.*phi\.astype\(float\)"):
        load_input(tmp_path / "int_phi.npy")


def test_npz_with_analytic_inclusions_uses_the_generator_hook(tmp_path, monkeypatch):
    import sys
    import types

    phi = _field(24, 2)
    np.savez(tmp_path / "g.npz", phi=phi, box=np.array([1.0, 1.0]), kind=np.array(["sphere"]),
             centers=np.array([[0.5, 0.5]]), axes=np.array([[0.25, 0.25]]), rotations=np.eye(2)[None])
    seen = {}

    def hook(data):
        seen.update(data)
        return "analytic" if seen.get("use") is None else None

    fake = types.ModuleType("jaxmesh._generate")
    fake.microstructure_from_npz = hook
    monkeypatch.setitem(sys.modules, "jaxmesh._generate", fake)
    assert load_input(tmp_path / "g.npz", box=(1.0, 1.0), periodic=False) == "analytic"
    np.testing.assert_array_equal(seen["box"], [1.0, 1.0])
    assert not seen["periodic"] and "centers" in seen  # the argument overrides the file
    with pytest.raises(ValueError, match="analytic inclusions are placed in its own box"):
        load_input(tmp_path / "g.npz", box=(2.0, 2.0))  # it would not move them
    seen["use"] = "fallback"  # the hook declines: the level set is used
    ms = load_input(tmp_path / "g.npz")
    assert isinstance(ms, Microstructure) and len(ms.inclusions) == 1
    monkeypatch.setitem(sys.modules, "jaxmesh._generate", types.ModuleType("jaxmesh._generate"))
    assert isinstance(load_input(tmp_path / "g.npz"), Microstructure)  # no hook at all


def test_roll_reads_the_periodic_grid_shifted(tmp_path):
    """roll=(k, ...) puts sample k at x = 0: the same as reading np.roll(phi, -k); analytic inclusions
    written by the generator move with the grid; a plain box or a wrong length is refused."""
    from jaxmesh import InclusionSpec, write_input

    phi = _field()
    np.save(tmp_path / "phi.npy", phi)
    _same(load_input(tmp_path / "phi.npy", roll=(5, 0, 3)),
          Microstructure.from_levelset(np.roll(phi, (-5, 0, -3), axis=(0, 1, 2))))
    spec = InclusionSpec("sphere", np.array([0.5, 0.5, 0.5]), np.full(3, 0.25), np.eye(3))
    write_input(tmp_path / "g.npz", [spec], (1.0, 1.0, 1.0), (24, 24, 24))
    rolled = load_input(tmp_path / "g.npz", roll=(6, 0, 0))
    inc = rolled.inclusions[0]
    np.testing.assert_allclose((inc.lower + inc.upper) / 2, [0.25, 0.5, 0.5], atol=1e-9)  # 0.5 - 6/24
    with pytest.raises(ValueError, match="periodic"):
        load_input(tmp_path / "phi.npy", periodic=False, roll=(1, 0, 0))
    with pytest.raises(ValueError, match="3 integers"):
        load_input(tmp_path / "phi.npy", roll=(1, 0))
