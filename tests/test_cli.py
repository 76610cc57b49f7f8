"""The command line, end to end through main(argv)."""

import json
import re

import numpy as np
import pytest

from jaxmesh._cli import main
from jaxmesh.io import read_mesh, write_mesh


def test_generate_info_mesh_validate_2d(tmp_path, capsys):
    rve = tmp_path / "rve2d.npz"
    assert main(["generate", str(rve), "--dim", "2", "--kind", "sphere", "--n", "4", "--radius", "0.12",
                 "--radius-std", "0.01", "--min-gap", "0.05", "--grid", "128", "--seed", "3"]) == 0
    assert main(["info", str(rve)]) == 0
    info = capsys.readouterr().out
    assert "inclusions: 4" in info.replace("  ", " ").replace("  ", " ")
    assert re.search(r"box_plane_clearance: [\d.e-]+\n\s+with_roll_auto: [\d.e-]+ \(samples \[\d+, \d+\]\)\n\s+"
                     r"default_roll: no\n", info)
    out, report, plot = tmp_path / "m.vtu", tmp_path / "r.json", tmp_path / "m.png"
    assert main(["mesh", str(rve), "-o", str(out), "--h", "0.03", "--report", str(report), "--plot", str(plot)]) == 0
    data = json.loads(report.read_text())
    assert data["metadata"]["validation"]["ok"] is True
    assert data["quality"]["n_cells"] > 500
    assert plot.stat().st_size > 10_000
    assert main(["validate", str(out), "--geometry", str(rve)]) == 0


def test_mesh_3d_sphere(tmp_path, capsys):
    import jax.numpy as jnp

    from jaxmesh import Microstructure, sphere_sdf

    ms = Microstructure.from_functions([sphere_sdf(jnp.array([0.5, 0.5, 0.5]), 0.3)], (1.0, 1.0, 1.0), (24, 24, 24))
    phi = ms.dn1
    path = tmp_path / "sphere.npy"
    np.save(path, phi)
    out = tmp_path / "sphere.msh"
    assert main(["mesh", str(path), "-o", str(out), "--h", "0.12", "--report", str(tmp_path / "r.json")]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["metadata"]["validation"]["ok"] is True
    assert report["quality"]["n_cells"] > 100
    (sphere,) = report["metadata"]["inclusions"]
    assert sphere["id"] == 1 and sphere["kind"] == "levelset"
    assert sphere["meshed_volume"] == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.08)  # coarse h: the facets cut inside
    worst = report["quality"]["worst_cell"]
    assert re.search(rf"worst cell: q {worst['q']:.2g} at \(.*\), (matrix|inclusion 1).* from the box plane [xyz] = ",
                     capsys.readouterr().out)
    assert main(["validate", str(out), "--geometry", str(path)]) == 0


@pytest.mark.parametrize(
    "array, message",
    [
        (np.full((16, 16), np.nan), "NaN"),
        (np.ones((8,)), "2D or 3D"),
        (np.ones((16, 16)), "no"),
    ],
)
def test_bad_input_gives_a_clear_error_and_no_file(tmp_path, capsys, array, message):
    path = tmp_path / "bad.npy"
    np.save(path, array)
    out = tmp_path / "never.vtu"
    assert main(["mesh", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "error" in err and message.lower() in err.lower()
    assert "Traceback" not in err
    assert not out.exists()
    assert not list(tmp_path.glob("*.vtu*"))


def test_absurd_sizes_are_rejected(tmp_path, capsys):
    rve = tmp_path / "rve.npz"
    assert main(["generate", str(rve), "--dim", "2", "--n", "2", "--radius", "0.1", "--grid", "64"]) == 0
    assert main(["mesh", str(rve), "-o", str(tmp_path / "x.vtu"), "--h", "5"]) == 2
    assert "larger than half" in capsys.readouterr().err
    assert main(["mesh", str(rve), "-o", str(tmp_path / "x.vtu"), "--iis", "1e-6"]) == 2
    assert "1/500" in capsys.readouterr().err
    sphere = tmp_path / "sphere.npz"
    assert main(["generate", str(sphere), "--n", "1", "--radius", "0.2", "--grid", "24"]) == 0
    assert main(["mesh", str(sphere), "-o", str(tmp_path / "x.vtu"), "--max-elements", "1000"]) == 2
    assert "more than max_elements" in capsys.readouterr().err
    assert not list(tmp_path.glob("x.vtu*"))


@pytest.mark.parametrize("box_gap", [None, "0.08"])
def test_generate_keeps_inclusions_clear_of_the_box(tmp_path, box_gap):
    from jaxmesh._generate import _box_clearance, _shape_matrices

    rve = tmp_path / "rve.npz"
    extra = [] if box_gap is None else ["--box-gap", box_gap]
    assert main(["generate", str(rve), "--dim", "3", "--kind", "ellipsoid", "--n", "12", "--radius", "0.12",
                 "--min-gap", "0.035", "--grid", "32", "--seed", "4", *extra]) == 0
    data = np.load(rve)
    dist = _box_clearance(data["centers"], _shape_matrices(data["axes"], data["rotations"]), data["box"])[0]
    assert dist.min() >= (0.035 if box_gap is None else 0.08) - 1e-9


def test_generate_never_writes_a_file_that_mesh_refuses(tmp_path, capsys):
    """The mesher refuses inclusions closer than one grid step. At --grid 40 (step 0.025) the default
    gap follows the grid and the file loads; a --min-gap under one step that gives such pairs is
    refused before anything is written, with the step and a gap that works; so are radii drawn too
    small for the grid."""
    from jaxmesh import load_input

    out = tmp_path / "b.npz"
    args = ["generate", str(out), "--kind", "sphere", "--volume-fraction", "0.3", "--radius", "0.12",
            "--box", "1", "1", "1.5", "--grid", "40", "--seed", "81"]
    assert main([*args, "--min-gap", "0.02"]) == 2
    err = capsys.readouterr().err
    assert "would be refused by `jaxmesh mesh`" in err and "under one grid step (0.025)" in err
    assert "--min-gap 0.0275" in err and not list(tmp_path.iterdir())
    assert main(args) == 0
    data = np.load(out)
    centers, radii = data["centers"], data["axes"][:, 0]
    delta = centers[:, None] - centers[None]
    delta -= np.round(delta / data["box"]) * data["box"]
    gaps = np.linalg.norm(delta, axis=-1) - radii[:, None] - radii[None]
    assert gaps[~np.eye(len(radii), dtype=bool)].min() >= 1.1 * 0.025 - 1e-9
    assert load_input(out).grid_shape == (40, 40, 60)
    # radii spread wider than their mean: the smallest drawn spans no grid node
    spread = ["generate", str(tmp_path / "s.npz"), "--kind", "sphere", "--n", "60", "--volume-fraction", "0.4",
              "--radius-std", "0.5", "--grid", "64", "--seed", "51"]
    assert main(spread) == 2
    err = capsys.readouterr().err
    assert "smaller than a grid step" in err and "a smaller --radius-std" in err
    assert not (tmp_path / "s.npz").exists()


def test_generate_says_when_the_count_stops_it_short_of_the_fraction(tmp_path, capsys):
    args = ["generate", str(tmp_path / "g.npz"), "--dim", "2", "--radius", "0.05", "--grid", "32", "--seed", "1"]
    assert main([*args, "--n", "3", "--volume-fraction", "0.3"]) == 0
    assert "note: --n 3 was reached first" in capsys.readouterr().out
    assert main([*args, "--n", "3"]) == 0
    assert "note:" not in capsys.readouterr().out


def test_generate_says_when_each_inclusion_steps_the_fraction_past_its_tolerance(tmp_path, capsys):
    # 8 long ellipses drawn, each 5-27 % of a 1 x 0.5 box: two reach 0.191, a third overshoots 0.2 +- 0.005
    out = tmp_path / "f.npz"
    args = ["generate", str(out), "--dim", "2", "--kind", "ellipsoid", "--n", "8", "--volume-fraction", "0.2",
            "--max-aspect", "8", "--radius", "0.23", "--radius-std", "0.005", "--box", "1", "0.5", "--grid", "128",
            "--seed", "71"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "with 2 inclusions" in err and "steps coarser than +- 0.005" in err and "smaller radii" in err
    assert not out.exists()


def test_generate_with_count_and_fraction_gives_both(tmp_path, capsys):
    """`--n 40 --volume-fraction 0.4` (no --radius) gave 9 circles of the default radius; now 40 at 0.4."""
    args = ["generate", str(tmp_path / "c.npz"), "--dim", "2", "--n", "40", "--volume-fraction", "0.4", "--grid", "128",
            "--seed", "83"]
    assert main(args) == 0
    assert "40 spheres, volume fraction 0.4000" in capsys.readouterr().out
    data = np.load(tmp_path / "c.npz")
    assert len(data["centers"]) == 40 and abs(np.pi * np.sum(data["axes"][:, 0] ** 2) - 0.4) < 1e-9
    assert main([*args, "--radius", "0.1"]) == 0
    assert "note: the volume fraction was reached with 9 of the --n 40 inclusions" in capsys.readouterr().out


@pytest.mark.parametrize("options, message", [
    (["--n", "3", "--grid", "0"], "--grid: expected at least 4 samples"),  # was a ZeroDivisionError
    (["--n", "3", "--box", "0", "1", "1"], "--box: expected positive lengths, got 0 1 1"),  # the same
    (["--n", "100000", "--volume-fraction", "0.3"], "are about 0.0179 across, under the 1.5 grid steps"),
    (["--seed", "3"], "give --n, --volume-fraction or both"),
])
def test_generate_refuses_bad_options_at_once(tmp_path, capsys, options, message):
    assert main(["generate", str(tmp_path / "g.npz"), *options]) == 2
    assert message in capsys.readouterr().err and not list(tmp_path.iterdir())


@pytest.mark.parametrize("output, message", [
    ("g.vtu", "generate writes an .npz"),  # it wrote an .npz under that name, which `jaxmesh mesh` refused
    ("missing/g.npz", "folder 'missing' does not exist"),  # an OSError naming a temporary file
])
def test_generate_refuses_a_bad_output_at_once(tmp_path, capsys, monkeypatch, output, message):
    monkeypatch.chdir(tmp_path)
    assert main(["generate", output, "--n", "3"]) == 2
    assert message in capsys.readouterr().err and not list(tmp_path.iterdir())


def test_compilation_cache_folder_from_the_environment(monkeypatch, tmp_path):
    from jaxmesh._compile_cache import CACHE_ENV, default_cache_dir

    monkeypatch.setenv(CACHE_ENV, "")
    assert default_cache_dir() is None
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "jaxmesh" / "xla"


def test_cli_keeps_compilations_for_the_next_run(tmp_path):
    import os
    import subprocess
    import sys

    cache = tmp_path / "xla"
    env = dict(os.environ, JAXMESH_CACHE_DIR=str(cache))
    rve = tmp_path / "rve.npz"
    cli = [sys.executable, "-m", "jaxmesh._cli"]
    for args in (["generate", str(rve), "--dim", "2", "--n", "2", "--radius", "0.15", "--grid", "64"],
                 ["mesh", str(rve), "-o", str(tmp_path / "m.vtu"), "--h", "0.1"]):
        run = subprocess.run(cli + args, env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
    assert len(list(cache.iterdir())) > 5  # one entry per compiled kernel


def test_generate_grf_names_the_inclusions_that_percolate(tmp_path, capsys):
    """generate names the inclusions that reach their own periodic image, and mesh takes them."""
    from jaxmesh import load_input

    def generate(fraction):
        out = tmp_path / f"g{fraction}.npz"
        assert main(["generate", str(out), "--dim", "2", "--kind", "grf", "--volume-fraction", str(fraction),
                     "--correlation-length", "0.08", "--grid", "64", "--seed", "1"]) == 0
        return out, capsys.readouterr().out

    out, text = generate(0.7)
    listed = re.search(r"inclusion\(s\) \[([\d, ]+)\] reach their own periodic image", text)
    assert listed is not None
    spanning = [inc.id for inc in load_input(out).inclusions if (np.asarray(inc.upper) - inc.lower >= 0.999).any()]
    assert [int(i) for i in listed.group(1).split(",")] == spanning
    assert main(["mesh", str(out), "-o", str(tmp_path / "g.vtu")]) == 0
    assert re.search(r"\] validate\s+valid", capsys.readouterr().out)
    assert "periodic image" not in generate(0.2)[1]


def test_generate_grf_says_when_dropped_components_take_the_fraction_down(tmp_path, capsys):
    """At l = one grid step (16^3) and 0.3 % the components are specks of a few nodes, and after dropping them
    no threshold the generator tries keeps 0.8 of the fraction: generate says so and why;
    l = 0.08 on a 64^2 grid keeps the fraction and says nothing."""

    def generate(*args):
        out = tmp_path / "g.npz"
        assert main(["generate", str(out), "--kind", "grf", "--seed", "1", *args]) == 0
        with np.load(out) as z:
            return float((z["phi"] < 0).mean()), capsys.readouterr().out

    kept, text = generate("--volume-fraction", "0.003", "--correlation-length", "0.0625", "--grid", "16")
    assert kept < 0.8 * 0.003
    assert f"node fraction {kept:.4f} against the requested 0.003" in text
    assert "1.0 grid steps" in text and "--correlation-length" in text
    kept, text = generate("--dim", "2", "--volume-fraction", "0.3", "--correlation-length", "0.08", "--grid", "64")
    assert kept > 0.8 * 0.3 and "against the requested" not in text


def test_generate_refuses_a_box_that_is_not_whole_grid_steps(tmp_path, capsys):
    """1.4 x 1 x 0.7 at 48 samples on the shortest side has no common step: generate refuses before
    writing (the file would not load) and names a --grid that works, which then loads."""
    from jaxmesh import load_input

    out = tmp_path / "b.npz"
    args = ["generate", str(out), "--kind", "sphere", "--n", "2", "--radius", "0.1", "--volume-fraction", "0.01",
            "--box", "1.4", "1", "0.7"]
    assert main([*args, "--grid", "48"]) == 2
    err = capsys.readouterr().err
    assert "not whole numbers of the grid step" in err and "Hint: --grid 49" in err
    assert not out.exists()
    assert main([*args, "--grid", "49"]) == 0
    assert load_input(out).grid_shape == (98, 70, 49)


@pytest.mark.parametrize("roll, extra, message", [(["1", "x"], [], "one integer"),
                                                  (["auto"], ["--no-periodic"], "periodic=True")])
def test_mesh_refuses_a_bad_roll_before_meshing(tmp_path, capsys, roll, extra, message):
    path, out = tmp_path / "phi.npy", tmp_path / "never.vtu"
    np.save(path, np.ones((16, 16, 16)))
    assert main(["mesh", str(path), "-o", str(out), "--roll", *roll, *extra]) == 2
    assert message in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("outputs, message", [
    (["-o", "m.xyz"], "-o m.xyz: the mesh format comes from the extension, one of .vtu, .msh"),
    (["-o", "m.vtu", "--plot", "m.jpg"], "plots are written as PNG"),
    (["-o", "phi.npz"], "-o phi.npz is also the input, which it would overwrite"),
    (["-o", "m.vtu", "--report", "m.vtu"], "--report m.vtu is also -o"),
    (["-o", "missing/m.vtu"], "folder 'missing' does not exist"),
])
def test_mesh_refuses_bad_outputs_before_meshing(tmp_path, capsys, monkeypatch, outputs, message):
    """Each of these failed only after the whole run (a JPEG plot after the mesh and report were
    written), or overwrote the input."""
    monkeypatch.chdir(tmp_path)
    np.savez("phi.npz", phi=np.ones((16, 16, 16)))  # no inclusion: meshing would stop at once, with another message
    assert main(["mesh", "phi.npz", *outputs]) == 2
    assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["phi.npz"] and np.all(np.load("phi.npz")["phi"] == 1)


def test_mesh_and_validate_with_roll_auto(tmp_path, capsys):
    """A rolled mesh conforms to the geometry read with the same --roll, and not to the file's frame (the
    sphere half a step clear of x = 0: a frame the default keeps, so a legacy file read without --roll
    fails and the hint names the roll)."""
    n, radius = 24, 0.25
    x = np.arange(n) / n
    d = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - np.array([radius + 0.02, 0.5, 0.45])
    d -= np.round(d)
    phi, out = tmp_path / "phi.npy", tmp_path / "m.vtu"
    np.save(phi, np.linalg.norm(d, axis=-1) - radius)
    assert main(["mesh", str(phi), "-o", str(out), "--h", "0.1", "--roll", "auto"]) == 0
    assert re.search(r"rolled by \(\d+, \d+, \d+\) samples", capsys.readouterr().out)
    assert main(["validate", str(out), "--geometry", str(phi), "--roll", "auto"]) == 0
    capsys.readouterr()
    assert main(["validate", str(out), "--geometry", str(phi)]) == 0  # the .vtu says how it was read
    assert re.search(r"as the mesh file says it was meshed: --roll \d+ \d+ \d+\n", capsys.readouterr().out)
    legacy = write_mesh(read_mesh(out), tmp_path / "m.vtk")  # legacy VTK carries no field data
    assert main(["validate", str(legacy), "--geometry", str(phi)]) == 1
    assert "hint: valid with --roll auto: the input read so" in capsys.readouterr().out


def test_mesh_of_a_distance_transform_averages_its_curvature(tmp_path, capsys):
    """A sphere's field made from its voxels (scipy's signed distance transform) meshes valid with the
    size line saying that its rippling curvature was averaged (pointwise it asked for elements a quarter
    of a step all over the interface)."""
    from scipy import ndimage

    n = 24
    x = np.arange(n) / n
    inside = np.linalg.norm(np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1) - 0.5, axis=-1) < 0.3
    phi, out = tmp_path / "edt.npy", tmp_path / "m.vtu"
    np.save(phi, (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)) / n)
    assert main(["mesh", str(phi), "-o", str(out), "--iis", "0.1"]) == 0
    said = capsys.readouterr().out
    assert "curvature averaged over 1.5 grid steps: the inclusion's interface ripples at the grid scale" in said
    assert re.search(r"validate +valid", said)


def test_mesh_and_validate_with_redistance(tmp_path, capsys):
    """--redistance meshes a field far from a distance as its first-order distance: valid, recorded in
    the report's parameters, and `validate --redistance` reads the geometry the same way; without it
    the interface is off the field as given, and validate says which option reads the input so."""
    n, radius = 24, 0.3
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    r = np.linalg.norm(x - 0.5, axis=-1)
    phi, out, report = tmp_path / "phi.npy", tmp_path / "m.vtu", tmp_path / "r.json"
    np.save(phi, (r**2 - radius**2) * (1 + 0.8 * np.sin(2 * np.pi * x[..., 0])))
    assert main(["info", str(phi)]) == 0
    assert re.search(r"slope_spread: [\d.]+ \(far from a distance: jaxmesh mesh redistances", capsys.readouterr().out)
    assert main(["mesh", str(phi), "-o", str(out), "--h", "0.1", "--redistance", "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["metadata"]["validation"]["ok"] is True
    assert data["metadata"]["parameters"]["redistance"] is True
    capsys.readouterr()
    assert main(["validate", str(out), "--geometry", str(phi), "--redistance"]) == 0
    capsys.readouterr()
    assert main(["validate", str(out), "--geometry", str(phi)]) == 0
    assert "as the mesh file says it was meshed: --redistance\n" in capsys.readouterr().out
    legacy = write_mesh(read_mesh(out), tmp_path / "m.vtk")
    assert main(["validate", str(legacy), "--geometry", str(phi)]) == 1
    assert "hint: valid with --redistance: the input read so is what the mesh follows" in capsys.readouterr().out
