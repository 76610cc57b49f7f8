"""Inclusions that cross a box plane by a small fraction of a grid step (or miss it by one), end to
end through mesh_rve.

Caps that thin once broke three ways: the surface stage snapped the whole cap onto the plane (a
trace on x = 0 without its translate on x = L); a cap with no node in it was meshed as not crossing
the plane, so the volume recovery projected split points out of the box (the 200-sphere RVE,
inclusion 53, crossed y = 0 by 7e-5 with grid step 1/128); a one-node cap made recovery run away.
"""

import re

import numpy as np
import pytest

from jaxmesh import InclusionSpec, MeshConfig, mesh_rve, microstructure_from_specs, validate


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    "radius, h, steps",
    [
        (0.2, 0.05, 0.005),  # no node in the cap: left out, recovery keeps its points in the box
        (0.25, 0.08, 0.01),  # one node in a cap 0.004 h deep: left out, its node walks back inside
        (0.2, 0.05, 0.05),  # no node in a cap 0.03 h deep: the extreme node is moved into it
        (0.15, 0.06, 0.1),  # a cap shallower than the snap distance: cut, not flattened
        (0.2, 0.05, -0.05),  # misses the plane by 1/20 of a step
    ],
)
def test_sphere_grazing_a_box_plane(radius, h, steps):
    n = 32
    depth = steps / n  # how far the sphere crosses y = 0, in grid steps
    spec = InclusionSpec("sphere", np.array([0.43, radius - depth, 0.57]), np.full(3, radius), np.eye(3))
    ms = microstructure_from_specs([spec], (1.0, 1.0, 1.0), (n,) * 3)
    mesh = mesh_rve(ms, MeshConfig(h=h, seed=0, roll=(0, 0, 0)))  # the frame kept (the default rolls)
    assert np.all((mesh.points >= 0) & (mesh.points <= 1))
    report = validate(mesh, ms)
    assert report.ok, report.summary()


def test_ellipsoid_grazing_two_planes_near_a_box_edge():
    # a tilted ellipsoid crossing x = 0 and y = 0 by a tenth of a grid step each, near their edge
    n, axes, rot = 32, np.array([0.2, 0.12, 0.12]), _rotation(0.5)
    extent = np.sqrt(np.einsum("ij,j,ij->i", rot, axes**2, rot))  # half-widths along x, y, z
    depth = 0.1 / n
    centre = np.array([extent[0] - depth, extent[1] - depth, 0.5])
    ms = microstructure_from_specs([InclusionSpec("ellipsoid", centre, axes, rot)], (1.0, 1.0, 1.0), (n,) * 3)
    mesh = mesh_rve(ms, MeshConfig(h=0.05, seed=0, roll=(0, 0, 0)))
    report = validate(mesh, ms)
    assert report.ok, report.summary()


def test_sphere_trace_passing_just_above_a_box_edge():
    # crosses x = 0 deeply; its trace on x = 0 passes 0.05 grid steps above the edge x = z = 0
    # (a 30-sphere RVE, inclusion 21). Without the box gap in the size function the face meshes
    # there were too coarse for that layer and the surface recovery diverged.
    n, radius, gap, cx = 32, 0.084, 0.0016, 0.03
    centre = np.array([cx, 0.5, np.sqrt((radius + gap) ** 2 - cx**2)])
    ms = microstructure_from_specs([InclusionSpec("sphere", centre, np.full(3, radius), np.eye(3))],
                                   (1.0, 1.0, 1.0), (n,) * 3)
    mesh = mesh_rve(ms, MeshConfig(seed=0, roll=(0, 0, 0)))
    report = validate(mesh, ms)
    assert report.ok, report.summary()


def test_clearest_roll_moves_the_box_planes_off_the_inclusion_extremes():
    from jaxmesh import clearest_roll
    from jaxmesh._periodic import plane_clearances

    # bounds along x at 0.0001 (a cap grazing x = 0) and 0.4; along y at 0.05 and 0.95 (wrapping)
    lower, upper = np.array([[0.0001, -0.05, 0.2]]), np.array([[0.4, 0.05, 0.6]])
    clear = plane_clearances(lower, upper, (1.0, 1.0, 1.0), (10, 10, 10))
    np.testing.assert_allclose(clear[0], [0.0001, 0.0999, 0.1999, 0.1, 0.0, 0.1, 0.2, 0.3, 0.2001, 0.1001], atol=1e-12)
    np.testing.assert_allclose(clear[1][[0, 1, 5, 9]], [0.05, 0.05, 0.45, 0.05], atol=1e-12)
    assert clearest_roll(lower, upper, (1.0, 1.0, 1.0), (10, 10, 10)) == (7, 5, 9)  # z: 0.9 is 0.3 from both
    assert clearest_roll(lower[:0], upper[:0], (1.0, 1.0, 1.0), (10, 10, 10)) == (0, 0, 0)


def _sphere_field(n: int, centre, radius: float, dim: int = 3) -> np.ndarray:
    x = np.arange(n) / n
    d = np.stack(np.meshgrid(*[x] * dim, indexing="ij"), axis=-1) - np.asarray(centre)
    d -= np.round(d)
    return np.linalg.norm(d, axis=-1) - radius


def _edge_tangent_sphere(n: int, miss: float) -> tuple[np.ndarray, np.ndarray]:
    """A sphere (radius 0.25) whose trace on the face y = 0 passes miss above the box edge y = z = 0,
    while the sphere's own extremes stay clear of every box plane (z: 0.021 below z = 0)."""
    radius = 0.25
    centre = np.array([0.5, 0.1, np.sqrt(radius**2 - 0.1**2) + miss])
    return _sphere_field(n, centre, radius), centre


def test_frame_clearance_finds_where_the_interface_meets_the_box_at_a_grazing_angle():
    """Tangencies of the sampled interface to grid planes (extremes and saddles), of face traces to box
    edges, and the interface at a corner: a trace 2e-5 above a box edge is found, where the inclusion's
    extent bounds, the score `clearest_roll` uses, see the box 0.02 away."""
    from jaxmesh import clearest_roll
    from jaxmesh._periodic import _contour_critical_heights, clearest_frame, frame_clearance, plane_clearances

    n, step = 32, np.full(3, 1 / 32)
    heights = _contour_critical_heights(_sphere_field(n, [0.5, 0.47, 0.55], 0.2), step)
    for found, pole in zip(heights, [0.5, 0.47, 0.55]):
        np.testing.assert_allclose(np.sort(found), [pole - 0.2, pole + 0.2], atol=1e-3)
    x = np.arange(n) / n - 0.5
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    torus = np.hypot(np.hypot(X, Y) - 0.25, Z) - 0.08  # x-extremes at +-0.33, saddles on the hole at +-0.17
    np.testing.assert_allclose(np.sort(_contour_critical_heights(torus, step)[0]), [0.17, 0.33, 0.67, 0.83], atol=1e-3)
    circle = _contour_critical_heights(_sphere_field(n, [0.5, 0.47], 0.2, dim=2), step[:2])
    np.testing.assert_allclose(np.sort(circle[1]), [0.27, 0.67], atol=1e-3)

    phi, centre = _edge_tangent_sphere(n, 2e-5)
    clearance = frame_clearance(phi, (1.0, 1.0, 1.0))
    bounds = plane_clearances(centre[None] - 0.25, centre[None] + 0.25, (1.0, 1.0, 1.0), (n,) * 3)
    assert clearance[0, 0, 0] < 1e-4 and min(b[0] for b in bounds) > 0.02
    assert frame_clearance(phi, (1.0, 1.0, 1.0), origin_only=True)[0, 0, 0] == clearance[0, 0, 0]
    best = clearest_frame(clearance)
    assert best != (0, 0, 0) and clearance[best] > 0.2
    assert clearest_roll(centre[None] - 0.25, centre[None] + 0.25, (1.0, 1.0, 1.0), (n,) * 3, values=phi) == best
    corner = _sphere_field(n, np.full(3, 0.2 / np.sqrt(3) + 1e-5), 0.2)  # through the box corner, 1e-5 off it
    assert frame_clearance(corner, (1.0, 1.0, 1.0))[0, 0, 0] < 1e-4
    for field in (corner, torus, phi[:, :20]):  # the frame as given alone: the same entry (a non-cubic grid too)
        cell = (1.0, field.shape[1] / n, 1.0)
        origin = frame_clearance(field, cell, origin_only=True)
        assert origin.shape == (1, 1, 1) and origin[0, 0, 0] == frame_clearance(field, cell)[0, 0, 0]
    far = _sphere_field(n, [0.5, 0.5, 0.5], 0.2)
    assert frame_clearance(far, (1.0, 1.0, 1.0))[0, 0, 0] == pytest.approx(0.3, abs=1e-3)
    assert clearest_frame(frame_clearance(far, (1.0, 1.0, 1.0))) == (0, 0, 0)


def test_frame_clearance_sees_a_box_plane_crossing_the_interface_at_a_shallow_angle():
    """A slab whose faces wave by 0.01 (z = 0.5 +- 5/32 + 0.01 sin 2 pi x): the grid plane z = 21/32 crosses
    the upper face at 3.6 deg, away from any tangency (the crests are 0.01 from it, a third of a step).
    The score takes the wedge one step from the crossing, step x tan(angle), and the clearest frame puts
    the z planes where the faces cross none."""
    from jaxmesh._periodic import _crossing_slopes, clearest_frame, frame_clearance

    n, amplitude = 32, 0.01
    x = np.arange(n) / n
    X, _, Z = np.meshgrid(x, x, x, indexing="ij")
    slab = np.abs(Z - 0.5 - amplitude * np.sin(2 * np.pi * X)) - 5 / 32
    step = np.full(3, 1 / n)
    planes, lines = _crossing_slopes(slab, step)
    assert planes[2][21] == pytest.approx(2 * np.pi * amplitude, rel=0.1)  # tan of the steepest slope's angle
    assert np.all(planes[0] > 5) and np.all(np.isinf(planes[1]))  # x planes cross the faces at 86 deg, y at 90
    assert lines[0][0, 21] == pytest.approx(planes[2][21], rel=1e-9)  # the trace on y = 0 against the x edge
    clearance = frame_clearance(slab, (1.0, 1.0, 1.0))
    # the corner at x = 1/4 (x = 0 is on the crossing): the crest above it is 0.01 from the plane
    assert clearance[8, 0, 21] == pytest.approx(2 * np.pi * amplitude / n, rel=0.1)
    rolled = np.roll(slab, (-8, -21), axis=(0, 2))  # that corner as the origin: the frame-as-given path
    assert frame_clearance(rolled, (1.0, 1.0, 1.0), origin_only=True)[0, 0, 0] == pytest.approx(clearance[8, 0, 21])
    best = clearest_frame(clearance)
    assert abs(x[best[2]] - 0.5) < 5 / 32 - 2 * amplitude or abs(x[best[2]] - 0.5) > 5 / 32 + 2 * amplitude
    assert np.isinf(planes[2][best[2]])


def test_the_input_line_notes_a_face_trace_grazing_a_box_edge(tmp_path, capsys):
    """The sphere whose trace on y = 0 passes 2e-5 above the edge y = z = 0 (its extremes are 0.02 from
    the planes, which the score did not see before): by default the grid is rolled off that grazing
    meeting and the input line says why; with the frame kept (roll zeros) it notes the meeting; and
    `jaxmesh info` gives the clearance as given and rolled."""
    from jaxmesh._cli import main

    phi, _ = _edge_tangent_sphere(32, 2e-5)
    np.save(tmp_path / "edge.npy", phi)
    lines = []
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(tmp_path / "edge.npy", MeshConfig(max_elements=10), progress=lines.append)
    rolled = re.search(r"rolled by .* ([\d.e-]+) unrolled: under a sixth of a grid step, .* the default rolled it",
                       lines[0])
    assert rolled and float(rolled.group(1)) < 1e-4 and "note:" not in lines[0]
    lines.clear()
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(tmp_path / "edge.npy", MeshConfig(max_elements=10, roll=(0, 0, 0)), progress=lines.append)
    note = re.search(r"the box passes ([\d.e-]+) from a grazing meeting", lines[0])
    assert note and float(note.group(1)) < 1e-4 and "the box is kept: the roll was given" in lines[0]
    capsys.readouterr()
    assert main(["info", str(tmp_path / "edge.npy")]) == 0
    printed = capsys.readouterr().out
    info = re.search(r"box_plane_clearance: ([\d.e-]+)\n\s+with_roll_auto: ([\d.e-]+) \(samples", printed)
    assert float(info.group(1)) < 1e-4 < 0.2 < float(info.group(2)) and "default_roll: yes" in printed


def test_roll_auto_meshes_a_grid_sphere_grazing_a_box_plane_without_slivers(tmp_path):
    """A sphere 2e-6 across x = 0 (a 0.05 deg tet in an ellipsoid RVE like it): with roll 'auto' the box
    planes move to the grid planes farthest from its extremes, the mesh is valid in the rolled frame,
    its tets keep 10 deg, and the metadata gives the offset. The default (roll None) rolls it so too;
    with the frame kept (roll zeros) the input line warns."""
    from jaxmesh import quality_report

    n, radius = 32, 0.2
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    centre = np.array([radius - 2e-6, 0.47, 0.55])
    d = X - centre
    d -= np.round(d)
    np.save(tmp_path / "graze.npy", np.linalg.norm(d, axis=-1) - radius)
    lines = []  # as given, the input line warns (the size stage then stops: max_elements)
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(tmp_path / "graze.npy", MeshConfig(max_elements=10, roll=(0, 0, 0)), progress=lines.append)
    assert "the box passes" in lines[0] and "the box is kept" in lines[0]
    lines.clear()
    mesh = mesh_rve(tmp_path / "graze.npy", MeshConfig(roll="auto", seed=0), progress=lines.append)
    assert "rolled by" in lines[0] and "note:" not in lines[0]
    roll = mesh.metadata["roll"]
    assert roll["samples"][0] != 0 and roll["clearance_before"] < 1e-3 < 0.02 < roll["clearance_after"]
    assert roll["offset"][0] == pytest.approx(roll["samples"][0] / n) and "grazing_as_given" not in roll
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]
    assert quality_report(mesh)["min_dihedral_deg"] >= 10.0
    lines.clear()
    with pytest.raises(ValueError, match="max_elements"):
        mesh_rve(tmp_path / "graze.npy", MeshConfig(max_elements=10), progress=lines.append)
    assert f"rolled by {tuple(roll['samples'])} samples" in lines[0] and "the default rolled it" in lines[0]
    with pytest.raises(ValueError, match="periodic"):
        MeshConfig(roll="auto", periodic=False)
    spec = InclusionSpec("sphere", centre, np.full(3, radius), np.eye(3))  # the same sphere, analytic
    analytic = mesh_rve(microstructure_from_specs([spec], (1.0, 1.0, 1.0), (n,) * 3), MeshConfig(roll="auto", h=0.08))
    assert analytic.metadata["roll"]["samples"] == roll["samples"] and analytic.metadata["validation"]["ok"]


_HALF_STEP_CLEAR = 0.2 + 0.5 / 24  # a sphere of radius 0.2 half a step (of 24) clear of x = 0


def _sphere_file(path):
    """The grid (24^3) of that sphere: a frame the default keeps (clearer than a sixth of a step) that
    rolling clears further."""
    x = np.arange(24) / 24
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    d = X - np.array([_HALF_STEP_CLEAR, 0.47, 0.55])
    d -= np.round(d)
    np.save(path, np.linalg.norm(d, axis=-1) - 0.2)
    return path


def test_a_failure_in_the_files_frame_is_meshed_again_rolled(tmp_path, monkeypatch):
    """roll None: a MeshingError in the file's own frame (one the default keeps: half a step clear of the
    sphere) gets one more try with roll 'auto' (a valid
    mesh whose metadata keeps the first error); an explicit roll, zeros included, gets none. The same
    grid given in memory (`Microstructure.from_levelset`) is rolled the same way, and the same sphere as
    an analytic inclusion in memory (`microstructure_from_specs`) by its function shifted."""
    from jaxmesh import Microstructure, MeshingError, _pipeline

    path = _sphere_file(tmp_path / "clear_half_step.npy")
    real = _pipeline._mesh_3d
    calls = []

    def fails_unrolled(ms, config, stage, t):
        calls.append(config.roll)
        if config.roll is None or config.roll == (0, 0, 0):
            raise MeshingError("surfaces", "a cap thinner than its elements", inclusion=0)
        return real(ms, config, stage, t)

    monkeypatch.setattr(_pipeline, "_mesh_3d", fails_unrolled)
    lines = []
    mesh = mesh_rve(path, MeshConfig(h=0.08, seed=0), progress=lines.append)
    assert calls == [None, "auto"]
    assert any("retry" in line and "roll='auto'" in line for line in lines)
    roll = mesh.metadata["roll"]
    assert roll["samples"][0] != 0 and "a cap thinner than its elements" in roll["after_failure"]
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]
    assert mesh.metadata["parameters"]["roll"] == "auto"
    with pytest.raises(MeshingError, match="thinner"):
        mesh_rve(path, MeshConfig(h=0.08, roll=(0, 0, 0)))
    with pytest.warns(UserWarning, match="rolled frame"):  # no progress callback: a warning says it
        mesh_rve(path, MeshConfig(h=0.08, seed=0, validate=False))
    calls.clear()
    in_memory = mesh_rve(Microstructure.from_levelset(np.load(path)), MeshConfig(h=0.08, seed=0), progress=lines.append)
    assert calls == [None, "auto"] and in_memory.metadata["roll"]["samples"] == roll["samples"]
    assert in_memory.metadata["validation"]["ok"] and len(in_memory.cells) == len(mesh.cells)
    calls.clear()  # analytic inclusions in memory: their functions shifted
    spec = InclusionSpec("sphere", np.array([_HALF_STEP_CLEAR, 0.47, 0.55]), np.full(3, 0.2), np.eye(3))
    analytic = mesh_rve(microstructure_from_specs([spec], (1.0, 1.0, 1.0), (24,) * 3), MeshConfig(h=0.08, seed=0))
    assert calls == [None, "auto"] and analytic.metadata["roll"]["samples"] == roll["samples"]
    assert analytic.metadata["validation"]["ok"], analytic.metadata["validation"]


def test_a_failure_no_frame_can_remove_is_not_meshed_again(tmp_path, monkeypatch):
    """A MeshingError marked frame_dependent=False (a fold of a flat level set: the field is the same in
    any frame) is raised at once, without the rolled retry."""
    from jaxmesh import MeshingError, _pipeline

    path = _sphere_file(tmp_path / "clear_half_step.npy")
    calls = []

    def fails_in_any_frame(ms, config, stage, t):
        calls.append(config.roll)
        raise MeshingError("surfaces", "the level set is nearly flat there", frame_dependent=False)

    monkeypatch.setattr(_pipeline, "_mesh_3d", fails_in_any_frame)
    lines = []
    with pytest.raises(MeshingError, match="nearly flat"):
        mesh_rve(path, MeshConfig(h=0.08), progress=lines.append)
    assert calls == [None] and not any("retry" in line for line in lines)


def test_a_failure_that_rolling_cannot_help_is_raised_as_it_is(tmp_path, monkeypatch):
    from jaxmesh import MeshingError, _pipeline

    def always_fails(ms, config, stage, t):
        raise MeshingError("volume", f"recovery stopped (roll {config.roll})")

    monkeypatch.setattr(_pipeline, "_mesh_3d", always_fails)
    path = _sphere_file(tmp_path / "clear_half_step.npy")
    with pytest.raises(MeshingError, match=r"roll None.*meshed again with roll='auto', it failed too.*roll auto"):
        mesh_rve(path, MeshConfig(h=0.08))
    x = np.arange(24) / 24
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    np.save(tmp_path / "clear.npy", np.linalg.norm(X - 0.5, axis=-1) - 0.2)  # box planes already clearest
    with pytest.raises(MeshingError, match=r"^stage 'volume': recovery stopped \(roll None\)$"):
        mesh_rve(tmp_path / "clear.npy", MeshConfig(h=0.08))
    spec = InclusionSpec("sphere", np.array([_HALF_STEP_CLEAR, 0.5, 0.5]), np.full(3, 0.2), np.eye(3))
    with pytest.raises(MeshingError, match=r"roll None.*meshed again with roll='auto', it failed too.*roll auto"):
        mesh_rve(microstructure_from_specs([spec], (1.0, 1.0, 1.0), (24,) * 3), MeshConfig(h=0.08))
    with pytest.raises(MeshingError, match=r"\(roll None\)$"):  # a plain box's faces are the domain's: no retry
        mesh_rve(microstructure_from_specs([spec], (1.0, 1.0, 1.0), (24,) * 3, periodic=False),
                 MeshConfig(h=0.08, periodic=False))


def test_a_sphere_touching_a_box_plane_is_meshed_rolled(tmp_path):
    """A sphere tangent to z = 0 at a grid node (phi exactly 0 there): in the file's frame (roll=(0, 0, 0),
    kept) the matrix between sphere and plane thins to nothing and tets there stay flat (|V| <= 1e-6
    l_max^3 or a dihedral angle below 0.01 deg), so the volume stage stops with a frame-dependent error
    that says the remedy; by default the file is meshed rolled (its box as given grazes the sphere),
    with a warning where no progress line says it, and `jaxmesh validate` of a legacy .vtk of it (no roll
    in the file) reads the input by the same default."""
    from jaxmesh import Microstructure, MeshingError, quality_report

    n, radius = 16, 0.25
    x = np.arange(n) / n
    d = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - np.array([0.5, 0.5, radius])
    d -= np.round(d)
    phi = np.linalg.norm(d, axis=-1) - radius
    assert phi[n // 2, n // 2, 0] == 0.0
    with pytest.raises(MeshingError, match="stays? flat .* touches the box plane z = 0 .* roll='auto'") as failure:
        mesh_rve(Microstructure.from_levelset(phi, periodic=True), MeshConfig(seed=0, roll=(0, 0, 0)))
    assert failure.value.stage == "volume" and failure.value.frame_dependent
    np.save(tmp_path / "tangent.npy", phi)
    with pytest.warns(UserWarning, match="rolled frame"):
        mesh = mesh_rve(tmp_path / "tangent.npy", MeshConfig(seed=0))
    roll = mesh.metadata["roll"]
    assert roll["samples"][2] != 0 and roll["grazing_as_given"] and "after_failure" not in roll
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]
    assert quality_report(mesh)["min_dihedral_deg"] >= 10.0
    from jaxmesh._cli import main  # a legacy .vtk carries no roll: validate reads the input by the same default
    from jaxmesh.io import write_mesh

    legacy = write_mesh(mesh, tmp_path / "m.vtk")
    assert main(["validate", str(legacy), "--geometry", str(tmp_path / "tangent.npy")]) == 0
    assert main(["validate", str(legacy), "--geometry", str(tmp_path / "tangent.npy"), "--roll", "0", "0", "0"]) == 1


def test_a_recovery_that_chases_a_sphere_past_a_box_edge_stops_early_and_is_meshed_rolled():
    """A sphere passing 3e-5 (1e-3 grid steps) from the box edge y = z = 0 crosses both planes and leaves
    a strip of face that thin between its traces and the edge: the recovery splits the strip's triangles
    round after round (a periodic excursion set at 64^3 did so until Qhull merged two nodes, reported as
    duplicates). It stops once an edge to split is under VolumeConfig.min_split_edge of the median surface
    edge, naming the edge. By default mesh_rve meshes the microstructure rolled (its box grazes the sphere)."""
    from jaxmesh import MeshingError
    from jaxmesh.geometry._microstructure import Microstructure
    from jaxmesh.geometry._shapes import sphere_sdf

    radius, gap = 0.2, 3e-5
    c = (radius + gap) / np.sqrt(2.0)
    ms = Microstructure.from_functions([sphere_sdf(np.array([0.5, c, c]), radius)], (1.0, 1.0, 1.0), (32,) * 3)
    with pytest.raises(MeshingError, match=r"recovery stalled: .* under 0.003 of the median surface edge near "
                                           r"x = .* from a box edge .* --roll auto") as failure:
        mesh_rve(ms, MeshConfig(seed=0, roll=(0, 0, 0)))
    assert failure.value.stage == "volume" and failure.value.frame_dependent
    with pytest.warns(UserWarning, match="rolled frame"):
        mesh = mesh_rve(ms, MeshConfig(seed=0))
    assert mesh.metadata["roll"]["grazing_as_given"] and "after_failure" not in mesh.metadata["roll"]
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]


def test_a_circle_touching_a_box_edge_is_meshed_rolled(tmp_path):
    """The 2D case: a circle tangent to y = 0 at a grid node. In the file's frame the triangles in the
    cusp keep a fair area ratio (V / l_max^2 above 1e-6, a cap's area goes with its small angles, not
    their product) but angles near 1e-3 deg, so the angle bound (0.01 deg) is what refuses them; by
    default the file is meshed rolled with no angle below 20 deg."""
    from jaxmesh import Microstructure, MeshingError, quality_report

    n, radius = 64, 0.25
    x = np.arange(n) / n
    d = np.stack(np.meshgrid(x, x, indexing="ij"), axis=-1) - np.array([0.5, radius])
    d -= np.round(d)
    phi = np.linalg.norm(d, axis=-1) - radius
    assert phi[n // 2, 0] == 0.0
    with pytest.raises(MeshingError, match=r"stays? flat .*V / l_max\^2 = [0-9.e-]+, angle .* touches the box "
                                           r"plane y = 0") as failure:
        mesh_rve(Microstructure.from_levelset(phi, periodic=True), MeshConfig(seed=0, roll=(0, 0)))
    assert failure.value.stage == "mesh2d" and failure.value.frame_dependent
    assert float(re.search(r"V / l_max\^2 = ([0-9.e-]+)", str(failure.value)).group(1)) > 1e-6
    np.save(tmp_path / "tangent2d.npy", phi)
    with pytest.warns(UserWarning, match="rolled frame"):
        mesh = mesh_rve(tmp_path / "tangent2d.npy", MeshConfig(seed=0))
    assert mesh.metadata["roll"]["samples"][1] != 0 and mesh.metadata["roll"]["grazing_as_given"]
    assert mesh.metadata["validation"]["ok"], mesh.metadata["validation"]
    assert quality_report(mesh)["min_angle_deg"] >= 20.0
