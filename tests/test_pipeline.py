"""The 3D pipeline end to end (issue 6): canonical RVEs through mesh_rve, checked by the validator."""

import numpy as np
import pytest

from jaxmesh import (
    InclusionSpec,
    MeshingError,
    MeshConfig,
    Microstructure,
    load_input,
    mesh_rve,
    microstructure_from_specs,
    quality_report,
    random_inclusions,
    sample_levelset,
    sphere_sdf,
    validate,
)
from jaxmesh._quality import signed_volumes
from jaxmesh.geometry._shapes import sphere_volume


def _sphere(center, radius):
    return InclusionSpec("sphere", np.asarray(center, float), np.full(3, float(radius)), np.eye(3))


def _levelset_rve(specs, box=(1.0, 1.0, 1.0), n=32):
    shape = tuple(int(round(n * b)) for b in box)
    return Microstructure.from_levelset(sample_levelset(specs, box, shape), box=box)


def _check(mesh, ms, specs=None, volume_tol=0.05):
    report = validate(mesh, ms)
    assert report.ok, report.summary()
    assert mesh.metadata["validation"]["ok"]
    vol = signed_volumes(mesh.points, mesh.cells)
    assert vol.min() > 0
    assert abs(vol.sum() - np.prod(ms.box)) < 1e-9 * np.prod(ms.box)
    if specs is not None:  # wrapped pieces add up to the analytic volume, less the chord error ~ (h / r)^2 / 4
        for k, s in enumerate(specs, start=1):
            exact = sphere_volume(float(s.axes[0])) if s.kind == "sphere" else float(s.volume)
            assert abs(vol[mesh.inclusion_id == k].sum() - exact) < volume_tol * exact
    assert sorted(mesh.periodic_pairs) == [0, 1, 2]
    return report


# centred; cut by a face, an edge (two faces), a corner (three faces)
CASES = {
    "centre": [_sphere((0.5, 0.5, 0.5), 0.3)],
    "face": [_sphere((0.04, 0.5, 0.5), 0.25)],
    "edge": [_sphere((0.03, 0.96, 0.5), 0.25)],
    "corner": [_sphere((0.97, 0.02, 0.03), 0.28)],
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_single_sphere_cases(name):
    specs = CASES[name]
    ms = _levelset_rve(specs)
    mesh = mesh_rve(ms, MeshConfig(iis=0.08, seed=1))
    _check(mesh, ms, specs)
    q = quality_report(mesh)
    assert q["q_min"] > 0.0 and q["q_mean"] > 0.6


def test_sphere_pole_on_a_box_edge():
    # the pole (0, 0, 0.25) lies on the box edge x = y = 0: two cut vertices once met there and
    # merged into a zero-area triangle that no tetrahedralisation holds
    specs = [_sphere((0.0, 0.0, 0.1), 0.15), _sphere((0.5, 0.5, 0.5), 0.25)]
    ms = Microstructure.from_functions([sphere_sdf(s.center, float(s.axes[0])) for s in specs], (1.0, 1.0, 1.0),
                                       (24, 24, 24))
    mesh = mesh_rve(ms, MeshConfig(h=0.12))
    _check(mesh, ms, specs, volume_tol=0.2)  # h / r = 0.8: chords cut ~ (h / r)^2 / 4 = 16 %


def test_two_spheres_one_grid_step_apart():
    n = 48
    specs = [_sphere((0.3, 0.5, 0.5), 0.18), _sphere((0.3 + 0.36 + 1.0 / n, 0.5, 0.5), 0.18)]
    ms = _levelset_rve(specs, n=n)
    assert len(ms.inclusions) == 2
    mesh = mesh_rve(ms, MeshConfig(iis=0.08))
    _check(mesh, ms)
    assert set(np.unique(mesh.inclusion_id).tolist()) == {0, 1, 2}


def test_non_cubic_box():
    box = (1.0, 0.75, 1.25)
    specs = [_sphere((0.1, 0.4, 0.6), 0.25), _sphere((0.6, 0.05, 1.2), 0.2)]
    ms = _levelset_rve(specs, box=box)
    mesh = mesh_rve(ms, MeshConfig(iis=0.08))
    _check(mesh, ms, specs)
    assert np.allclose(mesh.points.max(axis=0), box)


def test_labelled_image_input(tmp_path):
    specs = [_sphere((0.5, 0.5, 0.5), 0.25), _sphere((0.02, 0.05, 0.5), 0.2)]
    phi = sample_levelset(specs, (1.0, 1.0, 1.0), (40, 40, 40))
    labels = np.zeros(phi.shape, np.int32)
    pts = np.stack(np.meshgrid(*[np.arange(40) / 40] * 3, indexing="ij"), -1)
    for k, s in enumerate(specs, start=1):
        d = pts - s.center
        d -= np.round(d)
        labels[(np.linalg.norm(d, axis=-1) < s.axes[0])] = 7 * k  # arbitrary label values
    ms = Microstructure.from_labels(labels)
    assert len(ms.inclusions) == 2
    mesh = mesh_rve(ms, MeshConfig(iis=0.08))
    _check(mesh, ms)
    # the report's inclusion table maps ids back to the image's labels, with each one's meshed volume
    table = mesh.metadata["inclusions"]
    assert [(row["id"], row["label"]) for row in table] == [(1, 7), (2, 14)]
    for row, s in zip(table, specs):
        assert row["meshed_volume"] == pytest.approx(4 / 3 * np.pi * s.axes[0] ** 3, rel=0.1)
    # and each cell carries its label value into the files
    import meshio

    expected = np.array([0, 7, 14])[mesh.inclusion_id]
    back = meshio.read(mesh.write(tmp_path / "labels.vtu"))
    np.testing.assert_array_equal(back.cell_data["label"][0], expected)
    np.testing.assert_array_equal(np.load(mesh.write(tmp_path / "labels.npz"))["label"], expected)


def test_phase_image_input():
    """A segmented image holds phases, not inclusions: label 1 in three regions (one across the box
    corner), label 2 in one. Each region is an inclusion; the cells keep the image value as `label`,
    which homogenize_conductivity(by="label") reads."""
    from jaxmesh import homogenize_conductivity

    n = 32
    pts = (np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1) + 0.5) / n
    labels = np.zeros((n, n, n), np.uint8)
    for value, centre, radius in [(1, (0.03, 0.97, 0.02), 0.2), (1, (0.5, 0.5, 0.5), 0.17),
                                  (1, (0.75, 0.2, 0.7), 0.13), (2, (0.25, 0.3, 0.6), 0.14)]:
        d = pts - np.asarray(centre)
        labels[np.linalg.norm(d - np.round(d), axis=-1) < radius] = value
    ms = Microstructure.from_labels(labels)
    assert sorted((i.description["label"], i.description["part"]) for i in ms.inclusions) == [(1, 1), (1, 2), (1, 3),
                                                                                               (2, 1)]
    mesh = mesh_rve(ms, MeshConfig(iis=0.08))
    _check(mesh, ms)
    label = mesh.cell_arrays()["label"]
    lut = {row["id"]: row["label"] for row in mesh.metadata["inclusions"]}
    np.testing.assert_array_equal(label, [lut.get(int(i), 0) for i in mesh.inclusion_id])
    assert set(np.unique(label).tolist()) == {0, 1, 2}
    by_label = homogenize_conductivity(mesh, {0: 1.0, 1: 10.0, 2: 0.1}, by="label")
    by_id = homogenize_conductivity(mesh, {0: 1.0, **{i: (10.0 if v == 1 else 0.1) for i, v in lut.items()}})
    np.testing.assert_allclose(by_label, by_id, rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("shape, seed", [("sphere", 0), ("sphere", 1), ("ellipsoid", 0), ("ellipsoid", 1)])
def test_random_rve_default_settings(shape, seed):
    specs = random_inclusions((1, 1, 1), volume_fraction=0.35, n=12, shape=shape, radius=(0.14, 0.02),
                              min_gap=0.04, seed=seed)
    ms = _levelset_rve(specs, n=48)
    mesh = mesh_rve(ms, MeshConfig(seed=seed))
    _check(mesh, ms)


def test_float32_run_warns():
    import jax

    from jaxmesh._pipeline import _warn_if_float32

    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.warns(UserWarning, match="jax_enable_x64"):
            _warn_if_float32()
    finally:
        jax.config.update("jax_enable_x64", True)


def test_box_shaped_inclusion_from_a_sampled_level_set():
    # sharp edges and corners (a rectangular block, periodic distance sampled on the grid), sized by
    # curvature: its edges are rounded at grid scale, so curv_alpha 2 keeps the count small
    n = 32
    x = np.arange(n) / n
    d = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1) - [0.45, 0.5, 0.55]
    q = np.abs(d - np.round(d)) - [0.2, 0.15, 0.18]
    phi = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)
    ms = Microstructure.from_levelset(phi, (1.0, 1.0, 1.0))
    mesh = mesh_rve(ms, MeshConfig(curv_alpha=2.0, seed=0))
    report = validate(mesh, ms)
    assert report.ok, report.summary()
    inside = np.abs(signed_volumes(mesh.points, mesh.cells))[mesh.inclusion_id == 1].sum()
    # below the exact block: the interpolated level set rounds edges at grid scale, and chords cut them
    assert 0.95 * 0.4 * 0.3 * 0.36 < inside < 0.4 * 0.3 * 0.36


def test_an_endless_fibre_meshes_periodic_and_conforming():
    """An endless fibre along x (it reaches its own periodic image: it percolates) beside a ball that
    crosses the box edge y = z = 0. The fibre's surface is closed off beyond the box, cut by x = 0 and
    x = L, and its two traces there made translates: the mesh is valid (periodic, conforming) and the
    fibre's cells fill the cylinder."""
    x = np.arange(24) / 24
    _, y, z = np.meshgrid(x, x, x, indexing="ij")
    fibre = np.hypot(y - 0.5, z - 0.5) - 0.2
    dy, dz = y - 0.05, z - 0.05
    dy, dz = dy - np.round(dy), dz - np.round(dz)
    ball = np.sqrt((x[:, None, None] - 0.5) ** 2 + dy**2 + dz**2) - 0.12
    ms = Microstructure.from_levelset(np.minimum(fibre, ball))
    fibre_id = next(i.id for i in ms.inclusions if i.upper[0] - i.lower[0] > 0.99)
    mesh = mesh_rve(ms, MeshConfig(iis=0.1))
    _check(mesh, ms)
    vol = signed_volumes(mesh.points, mesh.cells)
    assert vol[mesh.inclusion_id == fibre_id].sum() == pytest.approx(np.pi * 0.2**2, rel=0.03)
    # the fibre's nodes on x = 0 and on x = 1 are one node set under the translation
    pairs = mesh.periodic_pairs[0]
    on_fibre = np.isin(np.arange(mesh.n_points), mesh.cells[mesh.inclusion_id == fibre_id])
    np.testing.assert_array_equal(on_fibre[pairs[:, 0]], on_fibre[pairs[:, 1]])
    assert on_fibre[pairs[:, 0]].sum() > 20


def test_a_laminate_image_meshes_its_layer_with_flat_interfaces(tmp_path):
    """A labelled image whose label 1 is a layer across the box (it percolates along x and z) and
    label 2 a ball beside it: both interfaces conform, the layer keeps its volume and its two faces
    stay at y = 9.5 / 32 and 19.5 / 32 (sample i sits at y = i / 32: the boundaries at the half-sample)."""
    n = 32
    c = (np.arange(n) + 0.5) / n
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    labels = np.zeros((n, n, n), np.int32)
    labels[:, 10:20, :] = 1
    labels[(x - 0.5) ** 2 + (y - 0.8) ** 2 + (z - 0.5) ** 2 < 0.1**2] = 2
    np.save(tmp_path / "laminate.npy", labels)
    ms = load_input(tmp_path / "laminate.npy")
    mesh = mesh_rve(ms, MeshConfig(iis=0.1))
    _check(mesh, ms)
    layer = mesh.cells[mesh.inclusion_id == 1]
    vol = signed_volumes(mesh.points, mesh.cells)
    assert vol[mesh.inclusion_id == 1].sum() == pytest.approx(10 / 32, rel=0.01)
    ys = mesh.points[np.unique(layer), 1]
    assert ys.min() == pytest.approx(9.5 / 32, abs=0.01) and ys.max() == pytest.approx(19.5 / 32, abs=0.01)


def test_a_field_negative_in_the_matrix_meshes_its_matrix_and_says_so(tmp_path):
    """Three spheres given with the opposite sign: the 'inclusion' is the matrix around them, which
    percolates along every axis. It meshes (valid, periodic), and the input line says that the
    inclusions fill most of the box and names the sign convention."""
    x = np.arange(24) / 24
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    phi = np.full((24,) * 3, np.inf)
    for centre in ([0.3, 0.4, 0.5], [0.75, 0.7, 0.2], [0.05, 0.9, 0.95]):
        d = X - np.array(centre)
        d -= np.round(d)
        phi = np.minimum(phi, np.linalg.norm(d, axis=-1) - 0.17)
    np.save(tmp_path / "inside_out.npy", -phi)
    lines = []
    mesh = mesh_rve(tmp_path / "inside_out.npy", MeshConfig(iis=0.1), progress=lines.append)
    assert "fill 9" in lines[0] and "pass -phi" in lines[0]
    assert mesh.metadata["validation"]["ok"]
    vol = signed_volumes(mesh.points, mesh.cells)
    assert vol[mesh.inclusion_id == 1].sum() == pytest.approx(1 - 3 * sphere_volume(0.17), rel=0.01)
    np.save(tmp_path / "right.npy", phi)
    with_sign = []
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(tmp_path / "right.npy", MeshConfig(iis=0.1, max_elements=10), progress=with_sign.append)
    assert "note" not in with_sign[0]


@pytest.mark.parametrize("dim, n", [(2, 64), (3, 20)])
def test_default_sizes_follow_the_box(tmp_path, dim, n):
    """With no sizes given, iis is 0.05 of the box's mean side: the same geometry in a box of 10 (a
    field in mm) meshes as in a unit box, scaled, where an absolute 0.05 asked for about 1000 times
    the elements and was refused by max_elements. The scaled file goes through the CLI's reader."""
    x = np.arange(n) / n
    t = np.stack(np.meshgrid(*[x] * dim, indexing="ij"), axis=-1) - 0.3
    t -= np.round(t)
    phi = np.linalg.norm(t, axis=-1) - 0.22
    np.savez(tmp_path / "mm.npz", phi=10.0 * phi, box=np.full(dim, 10.0))
    unit = mesh_rve(Microstructure.from_levelset(phi), MeshConfig())
    scaled = mesh_rve(tmp_path / "mm.npz", MeshConfig())
    assert unit.metadata["parameters"]["iis"] == 0.05 and scaled.metadata["parameters"]["iis"] == 0.5
    assert scaled.metadata["validation"]["ok"] and abs(scaled.n_cells / unit.n_cells - 1) < 1e-3
    vol = signed_volumes(scaled.points, scaled.cells)
    assert abs(vol.sum() - 10.0**dim) < 1e-9 * 10.0**dim
    assert MeshConfig().for_box((2.0, 1.0, 0.5)).iis == 0.05 and MeshConfig(iis=0.02).for_box((10.0,) * 3).iis == 0.02
    if dim == 2:  # mesh_2d called directly takes the same default
        from jaxmesh import mesh_2d

        direct = mesh_2d(Microstructure.from_levelset(10.0 * phi, box=(10.0, 10.0)))
        assert abs(direct.n_cells / unit.n_cells - 1) < 1e-3
    with pytest.raises(ValueError, match=r"MeshConfig.h_max: expected >= iis = 0.5 \(the default"):
        mesh_rve(tmp_path / "mm.npz", MeshConfig(h_max=0.2))


def test_a_mesh_larger_than_max_elements_is_refused_before_the_surfaces():
    """The size function's estimate (2.5 c * integral of h^-3) is checked against max_elements: a
    clear error before any surface is meshed, for the size function and for a uniform h."""
    specs = [_sphere((0.5, 0.5, 0.5), 0.3)]
    ms = _levelset_rve(specs, n=24)
    stages = []
    with pytest.raises(ValueError, match=r"about [\d.e+]+ tetrahedra .*more than max_elements = 1e\+03"):
        mesh_rve(ms, MeshConfig(iis=0.08, max_elements=1e3), progress=stages.append)
    assert any("] size" in s for s in stages) and not any("] surfaces" in s for s in stages)
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(ms, MeshConfig(h=0.01, max_elements=1e6))  # 8.5e6 regular tets, 2.1e7 expected
    with pytest.raises(ValueError, match="MeshConfig.max_elements"):
        MeshConfig(max_elements=-1)


@pytest.mark.parametrize("name, bad, hint", [
    ("iis", -1.0, "box units, e.g. iis=0.05"),
    ("h_max", 0.0, "box units, e.g. h_max=0.2"),
    ("nb_el", 0.0, "elements across the narrowest gaps, e.g. nb_el=3"),
    ("curv_alpha", float("nan"), "e.g. curv_alpha=0.5"),
    ("grad", -0.3, "gradient limit, e.g. grad=0.3"),
])  # fmt: skip
def test_a_bad_parameter_gets_a_hint_about_that_parameter(name, bad, hint):
    with pytest.raises(ValueError, match=rf"MeshConfig\.{name}: expected a positive finite number, got .*hint: .*{hint}"):
        MeshConfig(**{name: bad})


@pytest.mark.parametrize("bad", [-5, 1.5, True, "0"])
def test_a_bad_seed_is_named(bad):
    """`jaxmesh mesh --seed -5` ended in NumPy's bare 'expected non-negative integer' after the input stage."""
    with pytest.raises(ValueError, match=r"MeshConfig\.seed: expected an integer >= 0"):
        MeshConfig(seed=bad)


def test_a_tip_sharper_than_the_grid_is_refused_by_place_and_meshed_redistanced(tmp_path):
    """An algebraic (not distance) prolate ellipsoid field, aspect 6 on 32^3: its tips (radius of
    curvature a quarter of a grid step) leave the interpolated field a ripple just inside each tip,
    where the projection of the tip node stalls at |phi| ~ 3e-3. That is a clear error naming the
    place and --redistance (no invalid mesh); with the default redistance=None, the file's field is
    meshed once more redistanced, and that mesh is valid."""
    n = 32
    x = np.arange(n) / n
    t = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - 0.5
    t -= np.round(t)
    phi = 0.05 * np.sqrt(((t / np.array([0.3, 0.05, 0.05])) ** 2).sum(-1)) - 0.05
    np.save(tmp_path / "needle.npy", phi)
    with pytest.raises(MeshingError, match=r"stay off the level set .* near x = \((0.2|0.7)\d*, 0.5, 0.5\).*--redistance") as err:
        mesh_rve(Microstructure.from_levelset(phi), MeshConfig(seed=0, redistance=False))
    assert err.value.stage == "surfaces" and err.value.inclusion == 1 and not err.value.frame_dependent
    assert err.value.redistance_helps
    with pytest.warns(UserWarning, match=r"stay off the level set .*meshing again with the field made a first-order"):
        mesh = mesh_rve(tmp_path / "needle.npy", MeshConfig(seed=0))
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]
    assert mesh.metadata["parameters"]["redistance"] is True
    assert "stay off the level set" in mesh.metadata["redistance"]["after_failure"]


def test_a_failed_level_set_is_meshed_again_redistanced_then_rolled(
        tmp_path, monkeypatch):
    """The redistanced retry: a level set (a file, or from_levelset in memory) with redistance=None is
    meshed once more with redistance=True after a failure that redistancing removes, or after any
    failure when the field is far from a distance (then rolled after a failure in that frame);
    redistance=False, a labelled image and analytic inclusions raise the first error; a failure of
    the last try names every try."""
    from jaxmesh import _pipeline

    calls = []

    def fails_unless_redistanced(ms, config, stage, t):
        calls.append(config.redistance)
        raise MeshingError("surfaces", f"nearly flat (redistance {config.redistance})", frame_dependent=False,
                           redistance_helps=True)

    monkeypatch.setattr(_pipeline, "_mesh_3d", fails_unless_redistanced)
    x = np.arange(16) / 16
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    phi = np.linalg.norm(X - 0.5, axis=-1) - 0.25
    np.save(tmp_path / "phi.npy", phi)
    np.save(tmp_path / "labels.npy", (phi < 0).astype(np.uint8))
    for source in (tmp_path / "phi.npy", Microstructure.from_levelset(phi)):
        calls.clear()
        lines = []
        with pytest.raises(MeshingError, match=r"redistance None\); meshed again with redistance=True, it failed "
                                               r"too: .*redistance True"):
            mesh_rve(source, MeshConfig(h=0.1), progress=lines.append)
        assert calls == [None, True] and any("retry" in line and "--redistance" in line for line in lines)
    spec = InclusionSpec("sphere", np.array([0.5, 0.5, 0.5]), np.full(3, 0.25), np.eye(3))
    for source, config in ((tmp_path / "phi.npy", MeshConfig(h=0.1, redistance=False)),
                           (tmp_path / "labels.npy", MeshConfig(h=0.1)),
                           (microstructure_from_specs([spec], (1.0, 1.0, 1.0), (16,) * 3), MeshConfig(h=0.1))):
        calls.clear()
        with pytest.raises(MeshingError, match=r"^stage 'surfaces': nearly flat \(redistance (None|False)\)$"):
            mesh_rve(source, config)
        assert calls == [config.redistance]

    def fails_in_every_frame(ms, config, stage, t):
        calls.append((config.redistance, config.roll))
        raise MeshingError("volume", f"recovery stopped (redistance {config.redistance}, roll {config.roll})")

    monkeypatch.setattr(_pipeline, "_mesh_3d", fails_in_every_frame)
    t = X - np.array([0.1, 0.5, 0.5])
    r = np.linalg.norm(t - np.round(t), axis=-1)  # a sphere across x = 0 whose field's slope varies
    np.save(tmp_path / "varying.npy", (r**2 - 0.25**2) * (1 + 0.8 * np.sin(2 * np.pi * X[..., 1])))
    calls.clear()
    with pytest.raises(MeshingError, match=r"redistance None, roll None\); meshed again with redistance=True, then "
                                           r"with roll='auto', it failed too: .*redistance True, roll auto"):
        mesh_rve(tmp_path / "varying.npy", MeshConfig(h=0.1))
    assert calls == [(None, None), (True, None), (True, "auto")]  # far from a distance: redistanced first
    calls.clear()
    with pytest.raises(MeshingError, match=r"^stage 'volume': recovery stopped \(redistance None, roll None\)$"):
        mesh_rve(tmp_path / "phi.npy", MeshConfig(h=0.1))  # a distance: not redistanced (nor rolled: centred)
    assert calls == [(None, None)]
    with pytest.raises(ValueError, match="MeshConfig.redistance: expected None, True or False"):
        MeshConfig(redistance="yes")
