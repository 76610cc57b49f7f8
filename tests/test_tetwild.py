"""The optional fTetWild backend: a valid, non-periodic, approximately conforming mesh of the box."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxmesh import MeshConfig, Microstructure, mesh_rve, sphere_sdf, validate
from jaxmesh._cli import main
from jaxmesh._tetwild import levelset_surface, tetwild_mesh


@pytest.fixture(scope="module")
def cut_sphere():
    """A sphere of radius 0.3 crossing the face x = 0 (centre x = 0.1)."""
    return Microstructure.from_functions([sphere_sdf(jnp.array([0.1, 0.5, 0.5]), 0.3)], (1.0, 1.0, 1.0), (32,) * 3)


def test_levelset_surface_reaches_the_box_and_points_outwards(cut_sphere):
    v, f = levelset_surface(np.asarray(cut_sphere.dn1), cut_sphere.box)
    assert v.min() >= 0 and v.max() <= 1 and np.isclose(v[:, 0].min(), 0) and np.isclose(v[:, 0].max(), 1)
    p = v[f]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    centre = np.array([0.1, 0.5, 0.5])
    away = p.mean(axis=1) - centre
    away[:, 0] -= np.round(away[:, 0])  # the periodic copy across x = 0
    assert np.mean(np.einsum("ij,ij->i", normal, away) > 0) > 0.99
    empty = levelset_surface(np.ones((8, 8, 8)), (1, 1, 1))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)


def test_tetwild_mesh_is_valid_but_neither_periodic_nor_conforming(cut_sphere, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    mesh = tetwild_mesh(cut_sphere, 0.08)
    assert not list(tmp_path.iterdir())  # fTetWild's scratch file stays out of the working directory
    assert not mesh.periodic and mesh.metadata["backend"] == "tetwild"
    report = validate(mesh, cut_sphere)
    # by design the interface is off the level set; fTetWild may leave a few box nodes inside its envelope
    assert set(report.failed) <= {"interface", "boundary", "volume"}, report.summary()
    assert "interface" in report.failed
    assert report.checks["volume"].counts["rel_error"] < 1e-4
    assert report.checks["boundary"].counts["off_box"] <= 0.01 * report.checks["boundary"].counts["boundary_facets"]
    p = mesh.points[mesh.cells]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6
    inside = vol[mesh.inclusion_id == 1].sum()
    assert inside == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.05)  # both pieces, across x = 0


def test_cli_backend_tetwild(tmp_path, cut_sphere):
    phi = tmp_path / "phi.npy"
    np.save(phi, np.asarray(cut_sphere.dn1))
    out, report = tmp_path / "m.vtu", tmp_path / "r.json"
    assert main(["mesh", str(phi), "-o", str(out), "--backend", "tetwild", "--h", "0.1", "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["metadata"]["backend"] == "tetwild" and data["quality"]["n_cells"] > 1000
    assert out.stat().st_size > 0


def test_backend_is_validated():
    with pytest.raises(ValueError, match="backend"):
        MeshConfig(backend="tetgen")
    ms2 = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5]), 0.2)], (1.0, 1.0), (32, 32))
    with pytest.raises(ValueError, match="3D inputs only"):
        mesh_rve(ms2, MeshConfig(backend="tetwild"))


def test_non_periodic_field_meshes_with_tetwild(tmp_path):
    """A field that is not periodic (a sphere cut by x = 0 whose other half is not at x = 1): tetwild
    meshes it without a wrapped copy (the conforming mesher's non-periodic path: tests/test_nonperiodic.py)."""
    n = 24
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    phi = np.linalg.norm(X - np.array([0.05, 0.5, 0.5]), axis=-1) - 0.3
    with pytest.raises(ValueError, match="periodic"):
        Microstructure.from_levelset(phi)
    ms = Microstructure.from_levelset(phi, periodic=False)
    v, _ = levelset_surface(np.asarray(ms.dn1), ms.box, periodic=False)
    assert v[:, 0].max() < 0.4  # no copy of the cap near x = 1
    mesh = mesh_rve(ms, MeshConfig(backend="tetwild", h=0.1, periodic=False))
    failed = {name for name, check in mesh.metadata["validation"]["checks"].items() if not check["passed"]}
    assert not mesh.periodic and failed <= {"interface", "boundary", "volume"}
    p = mesh.points[mesh.cells]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6
    # the part of the ball inside the box: a ball less the cap beyond x = 0 (height 0.25)
    assert vol[mesh.inclusion_id == 1].sum() == pytest.approx(4 / 3 * np.pi * 0.3**3 - np.pi * 0.25**2 * (0.9 - 0.25) / 3,
                                                              rel=0.06)
