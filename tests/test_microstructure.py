"""Microstructure: periodic components, per-inclusion level sets, DN1/DN2, labels, bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmesh._periodic import minimum_image, points_near
from jaxmesh.geometry._components import chord_thickness, label_components
from jaxmesh.geometry._grid import grid_phi_fn, make_levelset_grid
from jaxmesh.geometry._microstructure import Microstructure
from jaxmesh.io._read import load_input
from _fields import flat_bottom_ellipsoid


def nodes(n, d):
    x = np.arange(n) / n
    return np.stack(np.meshgrid(*[x] * d, indexing="ij"), axis=-1)


def ball(points, center, r):
    """Exact periodic signed distance to a ball (unit box), NumPy."""
    dd = points - np.asarray(center)
    dd -= np.round(dd)
    return np.linalg.norm(dd, axis=-1) - r


def jball(center, r):
    c = jnp.asarray(center)
    return lambda p: jnp.linalg.norm(p - c, axis=-1) - r


def on_sphere(center, r, m, d=3, seed=0):
    u = np.random.default_rng(seed).normal(size=(m, d))
    return np.asarray(center) + r * u / np.linalg.norm(u, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def two_spheres():
    """Spheres r=0.15 at x=0.3 and 0.7 on 32^3, the exact SDF as input."""
    X = nodes(32, 3)
    s1, s2 = ball(X, (0.3, 0.5, 0.5), 0.15), ball(X, (0.7, 0.5, 0.5), 0.15)
    return Microstructure.from_levelset(np.minimum(s1, s2)), s1, s2


# ---- periodic components ----

def test_label_components_merges_across_faces():
    mask = np.zeros((8, 8), bool)
    mask[0, 2:4] = mask[7, 2:4] = True  # one blob split by the x face
    mask[3:5, 0] = mask[3:5, 7] = True  # one split by the y face
    mask[0, 0] = mask[7, 7] = mask[0, 7] = mask[7, 0] = True  # one at the corner
    labels, n = label_components(mask, periodic=True)
    assert n == 3
    assert label_components(mask, periodic=False)[1] == 8


@pytest.mark.parametrize("center", [(0.0, 0.0, 0.0), (0.0, 0.5, 0.5), (0.99, 0.02, 0.5)])
def test_sphere_through_corner_or_face_is_one_inclusion(center):
    ms = Microstructure.from_levelset(ball(nodes(24, 3), center, 0.2))
    assert len(ms.inclusions) == 1
    inc = ms.inclusions[0]
    # unwrapped bounds around the centre, bbox centre inside the box
    c = (inc.lower + inc.upper) / 2
    assert np.all((c >= -1e-9) & (c < 1.0))
    np.testing.assert_allclose(inc.upper - inc.lower, 0.4, atol=1 / 24)
    exact = ((np.asarray(center) - c + 0.5) % 1.0) - 0.5
    np.testing.assert_allclose(exact, 0.0, atol=0.5 / 24)
    pts = np.mod(on_sphere(center, 0.12, 50) , 1.0)
    assert (ms.label(pts) == 1).all()
    assert (ms.label(np.mod(on_sphere(center, 0.3, 50), 1.0)) == 0).all()


def test_circle_at_corner_2d_and_volume_fraction():
    X = nodes(48, 2)
    ms = Microstructure.from_levelset(np.minimum(ball(X, (0, 0), 0.2), ball(X, (0.5, 0.5), 0.1)))
    assert len(ms.inclusions) == 2 and ms.dim == 2
    assert ms.volume_fraction() == pytest.approx(np.pi * (0.2**2 + 0.1**2), rel=0.01)
    pts = np.array([[0.01, 0.99], [0.5, 0.5], [0.3, 0.3]])
    assert ms.label(pts).tolist() == [1, 2, 0]


def test_percolating_cylinder():
    X = nodes(24, 3)
    phi = np.hypot(((X[..., 1] - 0.5 + 0.5) % 1) - 0.5, ((X[..., 2] - 0.5 + 0.5) % 1) - 0.5) - 0.2
    ms = Microstructure.from_levelset(phi)
    inc, = ms.inclusions
    assert inc.upper[0] - inc.lower[0] == pytest.approx(1.0)
    np.testing.assert_allclose(inc.upper[1:] - inc.lower[1:], 0.4, atol=1 / 24)
    assert ms.inclusion_phi(1, np.array([[0.37, 0.5, 0.5]]))[0] == pytest.approx(-0.2, abs=1e-3)


# ---- per-inclusion level sets ----

@pytest.mark.parametrize("order", ["cubic", "linear"])
def test_two_spheres_one_step_apart_stay_two(order):
    n, r = 32, 0.15
    h = 1 / n
    c1, c2 = (0.5 - r - 0.6 * h, 0.5, 0.5), (0.5 + r + 0.6 * h, 0.5, 0.5)
    X = nodes(n, 3)
    s1, s2 = ball(X, c1, r), ball(X, c2, r)
    phi = np.minimum(s1, s2)
    ms = Microstructure.from_levelset(phi, order=order)
    assert len(ms.inclusions) == 2
    # each inclusion's level set is positive on the other (nodes and points inside it)
    assert (ms.inclusion_phi(1, X[s2 < 0]) > 0).all() and (ms.inclusion_phi(2, X[s1 < 0]) > 0).all()
    inside2 = on_sphere(c2, 0.9 * r, 300)
    assert (ms.inclusion_phi(1, inside2) > 0).all()
    # its zero set is the input field's zero set (same interpolation), near the gap too
    global_fn = grid_phi_fn(make_levelset_grid(phi), order=order)
    pts = on_sphere(c1, r, 400, seed=1)
    own, ref = ms.inclusion_phi(1, pts), np.asarray(global_fn(pts))
    # the cubic prefilter is not local: the changed values across the gap weigh ~0.268^steps
    assert np.abs(own - ref)[pts[:, 0] < 0.5 - 3 * h].max() < 1e-2 * h
    assert np.abs(own - ref)[pts[:, 0] < 0.5 - 6 * h].max() < 1e-3 * h
    assert np.abs(own - ref).max() < 0.25 * h
    assert np.abs(own).max() < (0.05 if order == "cubic" else 0.2) * h + np.abs(ref).max()
    assert ms.label(np.array([c1, c2, (0.5, 0.5, 0.5)])).tolist() == [1, 2, 0]


@pytest.mark.parametrize("d", [2, 3])
def test_levelset_inclusions_touching_at_the_grid_resolution_are_refused_by_id(d):
    n, r = 32, 0.15
    h = 1 / n
    X = nodes(n, d)

    def pair(gap):  # the gap centred on the grid node x = 0.5 (that node is the matrix between them)
        c1, c2 = [0.5] * d, [0.5] * d
        c1[0], c2[0] = 0.5 - 0.5 * gap - r, 0.5 + 0.5 * gap + r
        return np.minimum(ball(X, c1, r), ball(X, c2, r))

    with pytest.raises(ValueError, match=r"at least 0\.02 grid step .* inclusions 1 and 2: gap ~ 0\.010 steps "
                                         r"near x = \(0\.5"):
        Microstructure.from_levelset(pair(0.01 * h))
    assert len(Microstructure.from_levelset(pair(0.01 * h), check_gaps=False).inclusions) == 2
    assert len(Microstructure.from_levelset(pair(0.05 * h)).inclusions) == 2


def test_diagonal_cells_find_components_that_meet_across_a_square_or_a_cube():
    from jaxmesh.geometry._components import diagonal_cells

    def found(negative, periodic=False):
        v = np.ones((4, 4, 4))
        for node, value in negative.items():
            v[node] = value
        ids, centres = diagonal_cells(v, label_components(v < 0, periodic)[0], periodic)
        return ids.tolist(), centres.tolist()

    assert found({(1, 1, 1): -1.0, (2, 2, 1): -0.5}) == ([[1, 2]], [[1.5, 1.5, 1.0]])  # a square
    assert found({(1, 1, 1): -1.0, (2, 2, 2): -0.5}) == ([[1, 2]], [[1.5, 1.5, 1.5]])  # a cube
    assert found({(1, 1, 1): -1.0, (2, 1, 1): -1.0, (2, 2, 1): -0.5}) == ([], [])  # one component
    assert found({(0, 0, 0): -1.0, (3, 3, 0): -1.0}) == ([], [])  # apart on a plain box
    assert found({(0, 0, 0): -1.0, (3, 3, 0): -1.0}, periodic=True) == ([[1, 2]], [[3.5, 3.5, 0.0]])


def test_a_matrix_node_shared_by_two_inclusions_does_not_pull_the_farther_one():
    """Two spheres one step apart, the gap's ends 0.04 steps past nodes 23 and 24: node 24 holds
    sphere 2's distance (0.04 steps). As sphere 1's value it made sphere 1's cubic level set ring
    half a step into the gap (its zero set at x = 0.4986, not 0.48); its extrapolation is used."""
    n, r = 48, 0.18
    h = 1 / n
    X = nodes(n, 3)
    phi = np.minimum(ball(X, (0.3, 0.5, 0.5), r), ball(X, (0.3 + 2 * r + h, 0.5, 0.5), r))
    ms = Microstructure.from_levelset(phi)
    line = np.stack([np.linspace(0.47, 0.5, 3001), np.full(3001, 0.5), np.full(3001, 0.5)], axis=-1)
    phi1 = ms.inclusion_phi(1, line)
    crossing = line[np.flatnonzero(phi1 > 0)[0], 0]
    assert crossing == pytest.approx(0.3 + r, abs=0.02 * h)
    assert (np.diff(phi1) > 0).all()  # no ringing on the way to node 24
    node = (24, 24, 24)
    assert ms.nearest_id[node] == 2 and ms.dn2[node] == pytest.approx(0.96 * h, abs=0.02 * h)


def _dumbbell(n, d, rod_radius_steps, rod_end=0.7):
    """Two balls (r = 0.12) at x = 0.3 and 0.7 joined by a rod along x, axis off the grid lines."""
    h = 1 / n
    X = nodes(n, d)
    axis = np.array([0.5 + 0.3 * h, 0.5 + 0.2 * h][: d - 1])
    rel = X[..., 1:] - axis
    rel -= np.round(rel)
    rod = np.maximum(np.linalg.norm(rel, axis=-1) - rod_radius_steps * h,
                     np.maximum(0.3 - X[..., 0], X[..., 0] - rod_end))
    centre = lambda x: [x, *axis]  # noqa: E731
    balls = np.minimum(ball(X, centre(0.3), 0.12), ball(X, centre(0.7), 0.12))
    return np.minimum(balls, rod) if rod_end > 0.7 - 0.12 else np.minimum(ball(X, centre(0.3), 0.12), rod)


@pytest.mark.parametrize("d", [2, 3])
def test_levelset_neck_below_a_grid_step_is_refused_with_its_place(d):
    """A rod 0.9-1.2 steps across between two balls is a neck the grid does not resolve (the
    surfaces pinch it: an l = 3 steps excursion set meshed into two pieces there); 1.6 steps load."""
    with pytest.raises(ValueError, match=r"at least 1 grid step wide .* inclusion 1 narrows to 0\.\d\d steps "
                                         r"near x = \(0\.[3-6]\d*, 0\.5"):
        Microstructure.from_levelset(_dumbbell(32, d, 0.6 if d == 3 else 0.45))
    ms = Microstructure.from_levelset(_dumbbell(32, d, 0.6 if d == 3 else 0.45), check_necks=False)
    assert len(ms.inclusions) == 1 and ms.inclusions[0].description["neck_steps"] < 1.0
    ms = Microstructure.from_levelset(_dumbbell(32, d, 0.8))
    assert len(ms.inclusions) == 1 and "neck_steps" not in ms.inclusions[0].description


def test_levelset_thin_tip_is_not_a_neck():
    # the same rod from one ball into the matrix joins nothing
    ms = Microstructure.from_levelset(_dumbbell(32, 3, 0.6, rod_end=0.55))
    assert len(ms.inclusions) == 1 and "neck_steps" not in ms.inclusions[0].description


def test_labels_joined_by_a_one_voxel_line_are_refused():
    lab = np.zeros((32, 32, 32), int)
    lab[6:14, 12:20, 12:20] = 1
    lab[18:26, 12:20, 12:20] = 1
    lab[14:18, 16, 16] = 1
    with pytest.raises(ValueError, match=r"inclusion 1 \(label 1\) narrows to"):
        Microstructure.from_labels(lab)
    lab[14:18, 16:18, 16:18] = 1  # a bar two voxels across
    assert len(Microstructure.from_labels(lab).inclusions) == 1


def test_labels_touching_along_an_edge_or_a_corner_still_load():
    # the smoothed voxel level sets keep such pairs apart
    for second in (np.s_[14:20, 14:20, 8:14], np.s_[14:20, 14:20, 14:20]):
        lab = np.zeros((32, 32, 32), int)
        lab[8:14, 8:14, 8:14] = 1
        lab[second] = 2
        assert len(Microstructure.from_labels(lab).inclusions) == 2


def _thresholded_random_field(n, seed, fraction, correlation):
    """A smoothed periodic random field thresholded into blobs: far from a distance off its zero
    set (|grad| ~ 20 there, then flat), with the specks below 30 nodes filled."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n) * n
    k2 = sum(a**2 for a in np.meshgrid(k, k, k, indexing="ij"))
    f = np.real(np.fft.ifftn(np.fft.fftn(rng.standard_normal((n,) * 3)) * np.exp(-2 * np.pi**2 * k2 * correlation**2)))
    f /= f.std()
    phi = np.quantile(f, 1 - fraction) - f
    labels, m = label_components(phi < 0, True)
    speck = np.bincount(labels.ravel(), minlength=m + 1) < 30
    speck[0] = False
    return np.where(speck[labels], np.abs(phi) + 0.1, phi)


@pytest.mark.parametrize("seed", [13, 11])
def test_own_level_sets_of_a_thresholded_random_field_have_no_stray_zero_set(seed):
    """Each inclusion's own level set is negative only next to its own nodes. Kept input values
    that jumped against the distances beyond them once made the cubic spline ring below zero a
    step or two away (an open marching-cubes surface in the pipeline)."""
    from scipy.spatial import cKDTree

    n = 48
    h = 1 / n
    phi = _thresholded_random_field(n, seed, 0.07, 0.05)
    ms = Microstructure.from_levelset(phi)
    assert ms.inclusions[0].description["scale"] > 5  # not distance-like
    labels, m = label_components(phi < 0, True)
    assert m == len(ms.inclusions) >= 5
    x = nodes(n, 3).reshape(-1, 3)
    offsets = np.array([[0.5, 0.5, 0.5], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]]) * h
    probe = np.concatenate([x + o for o in offsets]) % 1.0  # cell centres and edge midpoints
    for inc in ms.inclusions:
        own_nodes = x[labels.ravel() == inc.id]
        near = cKDTree(own_nodes, boxsize=1.0).query(probe)[0] < 1.8 * h
        far = probe[~near]
        assert (ms.inclusion_phi(inc.id, far) > 0).all(), f"inclusion {inc.id}"


def test_dn1_dn2_nearest_vs_brute_force(two_spheres):
    ms, s1, s2 = two_spheres
    h = 1 / 32
    d1, d2 = np.minimum(s1, s2), np.maximum(s1, s2)
    near = np.abs(d1) < 2 * h
    np.testing.assert_allclose(ms.dn1[near], d1[near], atol=1e-12)  # the input's values kept
    band = np.abs(d1) < 8 * h
    assert np.abs(ms.dn1 - d1)[band].max() < 0.15 * h
    assert np.abs(ms.dn2 - d2)[d2 < 8 * h].max() < 0.15 * h  # sub-voxel surface distances
    assert np.abs(ms.dn1 - d1).max() < 0.55 * h and np.abs(ms.dn2 - d2).max() < 0.55 * h
    assert (ms.dn2 > 0).all() and ms.reach == np.inf
    clear = np.abs(s1 - s2) > h
    np.testing.assert_array_equal(ms.nearest_id[clear], np.where(s1 < s2, 1, 2)[clear])


def test_phi_label_global_fn_and_gradients(two_spheres):
    ms, _, _ = two_spheres
    h = 1 / 32
    pts = np.random.default_rng(3).random((600, 3))
    exact = np.minimum(ball(pts, (0.3, 0.5, 0.5), 0.15), ball(pts, (0.7, 0.5, 0.5), 0.15))
    near = np.abs(exact) < 3 * h
    err = np.abs(ms.phi(pts) - exact)
    assert err[np.abs(exact) < h].max() < 0.02 * h and err[near].max() < 0.15 * h  # cubic interpolation
    assert np.abs(ms.phi(pts) - exact).max() < 2 * h  # farther: a distance estimate, right sign
    np.testing.assert_array_equal(ms.phi(pts)[clear := np.abs(exact) > 0.02 * h] < 0, exact[clear] < 0)
    np.testing.assert_array_equal((ms.label(pts) > 0)[clear], (exact < 0)[clear])
    fn = jax.jit(ms.global_phi_fn())
    np.testing.assert_allclose(np.asarray(fn(pts))[near], ms.phi(pts)[near], atol=1e-12)
    # gradient of an inclusion's phi_fn and of DN1 vs central differences; |grad| ~ 1 near surfaces
    x = on_sphere((0.3, 0.5, 0.5), 0.15 + h, 8, seed=4)
    for f in (ms.inclusions[0].phi_fn, fn):
        g = np.asarray(jax.vmap(jax.grad(lambda p: f(p[None])[0]))(jnp.asarray(x)))
        eps = 1e-6
        fd = np.stack([(np.asarray(f(x + eps * e)) - np.asarray(f(x - eps * e))) / (2 * eps)
                       for e in np.eye(3)], -1)
        np.testing.assert_allclose(g, fd, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=0.05)


def test_phi_fn_periodic_and_positive_far_away(two_spheres):
    ms, _, _ = two_spheres
    pts = np.random.default_rng(5).random((200, 3))
    for inc in ms.inclusions:
        a = ms.inclusion_phi(inc.id, pts)
        np.testing.assert_allclose(ms.inclusion_phi(inc.id, pts + np.array([1.0, -2.0, 3.0])), a, atol=1e-10)
    far = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    assert (ms.inclusion_phi(1, far) > 0.2).all()


def test_scaled_field_is_normalised():
    X = nodes(24, 3)
    phi = ball(X, (0.5, 0.5, 0.5), 0.25)
    ms = Microstructure.from_levelset(40.0 * phi)
    assert ms.inclusions[0].description["scale"] == pytest.approx(40.0, rel=0.05)
    assert np.abs(ms.inclusion_phi(1, on_sphere((0.5, 0.5, 0.5), 0.25, 100))).max() < 0.01 / 24


def test_finite_reach_caps_dn2_and_fills_far_nodes():
    X = nodes(32, 3)
    centers = [(0.2, 0.2, 0.2), (0.7, 0.3, 0.6), (0.4, 0.75, 0.8)]
    phi = np.min([ball(X, c, 0.1) for c in centers], axis=0)
    full = Microstructure.from_levelset(phi)
    capped = Microstructure.from_levelset(phi, reach=0.1)
    assert np.isfinite(capped.reach) and capped.reach >= 0.1
    assert np.isfinite(capped.dn1).all() and capped.dn2.max() <= capped.reach + 1e-12
    near = np.abs(full.dn1) < 3 / 32
    np.testing.assert_allclose(capped.dn1[near], full.dn1[near], atol=1e-12)
    np.testing.assert_allclose(capped.dn2, np.minimum(full.dn2, capped.reach), atol=0.55 / 32)
    np.testing.assert_array_equal(capped.nearest_id[near], full.nearest_id[near])


def test_non_periodic_inclusion_cut_by_the_domain():
    X = nodes(32, 3)
    exact = np.minimum(np.linalg.norm(X - np.array([0.05, 0.5, 0.5]), axis=-1) - 0.2,
                       np.linalg.norm(X - np.array([0.6, 0.5, 0.5]), axis=-1) - 0.15)
    ms = Microstructure.from_levelset(exact, periodic=False)
    assert len(ms.inclusions) == 2 and not ms.periodic
    assert ms.inclusions[0].lower[0] == 0.0
    np.testing.assert_allclose(ms.inclusions[1].lower, [0.45, 0.35, 0.35], atol=1e-3)
    pts = np.random.default_rng(8).random((1000, 3)) * (31 / 32)
    ref = np.minimum(np.linalg.norm(pts - np.array([0.05, 0.5, 0.5]), axis=-1) - 0.2,
                     np.linalg.norm(pts - np.array([0.6, 0.5, 0.5]), axis=-1) - 0.15)
    assert np.abs(ms.phi(pts) - ref)[np.abs(ref) < 1 / 32].max() < 0.05 / 32
    clear = np.abs(ref) > 0.1 / 32
    np.testing.assert_array_equal((ms.label(pts) > 0)[clear], (ref < 0)[clear])
    assert ms.dn2.min() > 0.1


# ---- labels and functions ----

def test_from_labels():
    n = 24
    X = nodes(n, 3)
    lab = np.zeros((n,) * 3, np.int32)
    lab[ball(X, (0.3, 0.5, 0.5), 0.15) < 0] = 3
    lab[ball(X, (0.0, 0.0, 0.9), 0.15) < 0] = 7  # through a corner
    ms = Microstructure.from_labels(lab)
    assert [inc.description["label"] for inc in ms.inclusions] == [3, 7]
    assert ms.label(np.array([[0.3, 0.5, 0.5], [0.98, 0.01, 0.9], [0.6, 0.1, 0.3]])).tolist() == [1, 2, 0]
    assert ms.volume_fraction() == pytest.approx((lab > 0).mean(), rel=1e-6)  # volume preserved
    dev = ms.inclusion_phi(1, on_sphere((0.3, 0.5, 0.5), 0.15, 500))
    assert abs(dev.mean()) < 0.1 / n and np.abs(dev).max() < 0.5 / n  # staircase -> within half a step
    # node labels are reproduced exactly, and each level set is positive on the other label
    np.testing.assert_array_equal(ms.label(X.reshape(-1, 3)), np.searchsorted([0, 3, 7], lab.ravel()))
    assert (ms.inclusion_phi(1, X[lab == 7]) > 0).all()
    b = Microstructure.from_labels(lab > 0)
    assert len(b.inclusions) == 2


def test_from_functions_analytic():
    n = 24
    fns = [jball((0.0, 0.0, 0.0), 0.2), jball((0.5, 0.55, 0.5), 0.15)]
    vols = [4 / 3 * np.pi * 0.2**3, 4 / 3 * np.pi * 0.15**3]
    ms = Microstructure.from_functions(fns, (1.0, 1.0, 1.0), (n, n, n), volumes=vols,
                                       descriptions=[{"kind": "sphere"}, {"kind": "sphere"}])
    np.testing.assert_allclose(ms.inclusions[0].lower, -0.2, atol=0.02 / n)
    np.testing.assert_allclose(ms.inclusions[1].upper, [0.65, 0.7, 0.65], atol=0.02 / n)
    X = nodes(n, 3)
    e1, e2 = ball(X, (0, 0, 0), 0.2), ball(X, (0.5, 0.55, 0.5), 0.15)
    np.testing.assert_allclose(ms.dn1, np.minimum(e1, e2), atol=1e-12)
    np.testing.assert_allclose(ms.dn2, np.maximum(e1, e2), atol=1e-12)
    assert ms.volume_fraction() == pytest.approx(sum(vols))
    pts = np.random.default_rng(6).random((300, 3))
    exact = np.minimum(ball(pts, (0, 0, 0), 0.2), ball(pts, (0.5, 0.55, 0.5), 0.15))
    near = np.abs(exact) < 0.2
    np.testing.assert_allclose(ms.phi(pts)[near], exact[near], atol=1e-12)
    np.testing.assert_allclose(ms.phi(pts + 3.0)[near], exact[near], atol=1e-12)
    ms2 = Microstructure.from_functions([jball((0.5, 0.5), 0.3)], (2.0, 2.0), (32, 32))  # 2D, L = 2
    assert ms2.dim == 2 and ms2.label(np.array([[0.6, 0.5], [1.5, 1.5]])).tolist() == [1, 0]


def test_chord_thickness_of_a_slab():
    field = np.tile(np.abs(np.arange(12) - 5.5)[:, None] - 1.25, (1, 6))  # slab 2.5 steps thick
    assert chord_thickness(field, field < 0) == pytest.approx(2.5)


@pytest.mark.parametrize("periodic", [True, False])
def test_points_near_matches_brute_force(periodic):
    rng = np.random.default_rng(3)
    box = np.array([1.0, 2.0, 0.5])
    pts = rng.uniform(-0.2, 1.2, (3000, 3)) * box  # some outside the cell
    pts[:3] = [[0, 0, 0], box, [1.0, 0.0, 0.5]]  # on the planes
    centres = rng.uniform(-0.5, 1.5, (40, 3)) * box
    radii = rng.uniform(0.05, 0.9, 40)
    found = points_near(pts, centres, radii, box, periodic)
    for c, r, f in zip(centres, radii, found):
        d = pts - c
        if periodic:
            d = minimum_image(d, box)
        np.testing.assert_array_equal(f, np.flatnonzero(np.linalg.norm(d, axis=1) <= r))


def test_chord_thickness_does_not_depend_on_the_window():
    """The component is cropped to its bounds plus one outside layer: a wider window, or the
    component at the window's end (periodic there), gives the same thickness."""
    x = np.arange(40.0)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    field = np.sqrt((X - 20.3) ** 2 + (Y - 19.6) ** 2 / 4 + (Z - 20.1) ** 2) - 6.2  # ellipsoid, half-axes 6.2, 12.4
    tight = field[12:30, 6:34, 12:30]
    assert chord_thickness(field, field < 0) == chord_thickness(tight, tight < 0)
    wrapped = np.roll(field, 20, axis=0)  # split across the window's ends along x
    assert chord_thickness(wrapped, wrapped < 0) == pytest.approx(chord_thickness(field, field < 0), abs=1e-12)
    assert 11.0 < chord_thickness(field, field < 0) < 12.5  # chords of the widest section


# ---- bad inputs ----

def _raises(match, fn, *args, **kw):
    with pytest.raises(ValueError, match=match):
        fn(*args, **kw)


def test_bad_levelsets():
    X = nodes(24, 3)
    phi = ball(X, (0.5, 0.5, 0.5), 0.2)
    bad = phi.copy()
    bad[1, 2, 3] = np.nan
    _raises("finite", Microstructure.from_levelset, bad)
    _raises("2D or 3D", Microstructure.from_levelset, phi[0, 0])
    _raises("no negative values", Microstructure.from_levelset, np.abs(phi) + 0.1)
    _raises("some matrix", Microstructure.from_levelset, -np.abs(phi) - 0.1)
    _raises("periodic=False", Microstructure.from_levelset, np.linalg.norm(X - 0.3, axis=-1) - 0.2)
    ms = Microstructure.from_levelset(np.linalg.norm(X - 0.3, axis=-1) - 0.2, periodic=False)
    assert len(ms.inclusions) == 1
    closed = np.pad(phi, [(0, 1)] * 3, mode="wrap")  # sampled at x = i L / (n - 1): nodes at x = L
    _raises(r"axes \[0, 1, 2\] the last slice repeats the first", Microstructure.from_levelset, closed)
    speck = phi.copy()
    speck[2, 2, 2] = -0.01  # one negative node: not resolved by the grid
    _raises(r"inclusion 1: 1 negative samples", Microstructure.from_levelset, speck)
    sheet = np.abs(X[..., 0] - 0.5) - 0.3 / 24  # a sheet one node thick
    _raises("steps thick", Microstructure.from_levelset, sheet)
    _raises("box", Microstructure.from_levelset, phi, box=(1.0, 1.0))
    _raises(r"equal grid spacing .*if the voxels are cubic, the box is \(1.0, 1.0, 1.0\); .*resample the grid to one "
            r"step first, e.g. to shape \(24, 48, 24\)", Microstructure.from_levelset, phi, box=(1.0, 2.0, 1.0))
    _raises("order", Microstructure.from_levelset, phi, order="quintic")
    _raises("from_labels", Microstructure.from_levelset, phi < 0)


def test_bad_labels():
    lab = np.zeros((16, 16), np.int64)
    lab[2:6, 2:6] = 1
    lab[6:9, 2:6] = 2
    _raises("sharing a grid face", Microstructure.from_labels, lab)
    lab = np.zeros((16, 16), np.int64)
    lab[2:6, 2:6] = 1
    lab[10:14, 10:14] = 1
    parts = Microstructure.from_labels(lab)  # a phase image: one inclusion per region of label 1
    assert [(i.description["label"], i.description["part"]) for i in parts.inclusions] == [(1, 1), (1, 2)]
    assert parts.label(np.array([[4.0 / 16, 4.0 / 16], [12.0 / 16, 12.0 / 16], [8.0 / 16, 8.0 / 16]])).tolist() == [1, 2, 0]
    lab = np.zeros((16, 16), np.int64)
    lab[0:3, 5:9] = 4
    lab[14:16, 5:9] = 4  # one inclusion through the periodic face: fine
    assert len(Microstructure.from_labels(lab).inclusions) == 1
    plain = Microstructure.from_labels(lab, periodic=False)  # the box cuts label 4: one inclusion per part
    assert [(i.description["label"], i.description["part"]) for i in plain.inclusions] == [(4, 1), (4, 2)]
    assert plain.label(np.array([[1.0 / 16, 7.0 / 16], [15.0 / 16, 7.0 / 16]])).tolist() == [1, 2]
    _raises("only zeros", Microstructure.from_labels, np.zeros((8, 8), int))
    _raises(">= 0", Microstructure.from_labels, -lab)
    _raises("integer or bool", Microstructure.from_labels, lab.astype(float))
    tiny = np.zeros((16, 16), int)
    tiny[4:8, 4:8] = 1
    tiny[12, 12] = 2
    _raises(r"inclusion 2 \(label 2\)", Microstructure.from_labels, tiny)


def test_bad_functions():
    box, shape = (1.0, 1.0), (32, 32)
    h = 1 / 32
    _raises("touch", Microstructure.from_functions,
            [jball((0.3, 0.5), 0.15), jball((0.6 + 0.4 * h, 0.5), 0.15)], box, shape)
    _raises("overlap", Microstructure.from_functions,
            [jball((0.3, 0.5), 0.15), jball((0.5, 0.5), 0.15)], box, shape)
    ok = Microstructure.from_functions(
        [jball((0.3, 0.5), 0.15), jball((0.6 + 1.5 * h, 0.5), 0.15)], box, shape)
    assert len(ok.inclusions) == 2
    _raises("negative somewhere", Microstructure.from_functions, [lambda p: jnp.ones(p.shape[0])], box, shape)
    _raises("negative", Microstructure.from_functions, [jball((0.51, 0.5), 0.2 * h)], box, shape)
    _raises(r"inclusion 2: 5 negative samples", Microstructure.from_functions,
            [jball((0.3, 0.5), 0.1), jball((0.75, 0.5), 1.2 * h)], box, shape)
    _raises("failed", Microstructure.from_functions, [lambda p: p @ jnp.ones(3)], box, shape)
    _raises("NaN", Microstructure.from_functions, [lambda p: jnp.full(p.shape[0], jnp.nan)], box, shape)
    _raises("callables", Microstructure.from_functions, [1.0], box, shape)
    _raises("sequence", Microstructure.from_functions, jball((0.5, 0.5), 0.2), box, shape)
    _raises("grid_shape", Microstructure.from_functions, [jball((0.5, 0.5), 0.2)], box, (32,))
    _raises("volumes", Microstructure.from_functions, [jball((0.5, 0.5), 0.2)], box, shape, volumes=[-1.0])
    ms = Microstructure.from_functions([jball((0.5, 0.5), 0.2)], box, shape)
    _raises("points of shape", ms.phi, np.zeros((3, 3)))
    _raises("inclusion id", ms.inclusion_phi, 2, np.zeros((1, 2)))


def test_no_recompilation_for_new_points(two_spheres):
    from jaxmesh.geometry._microstructure import _map_kernel

    ms, _, _ = two_spheres
    rng = np.random.default_rng(7)
    ms.phi(rng.random((500, 3)))
    before = _map_kernel._cache_size()
    for _ in range(3):  # same power-of-two buckets: the compiled kernels are reused
        ms.phi(rng.random((500, 3)))
        ms.label(rng.random((500, 3)))
    assert _map_kernel._cache_size() <= before + 1  # label's smaller margin may add one bucket


@pytest.mark.slow
def test_many_inclusions_memory_scales_with_windows():
    n, rng = 96, np.random.default_rng(0)
    centers, radii = [], []
    while len(centers) < 150:
        c, r = rng.random(3), rng.uniform(0.03, 0.05)
        if all(np.linalg.norm((c - c2) - np.round(c - c2)) > r + r2 + 0.03 for c2, r2 in zip(centers, radii)):
            centers.append(c)
            radii.append(r)
    X = nodes(n, 3)
    phi = np.full((n,) * 3, np.inf)
    for c, r in zip(centers, radii):
        phi = np.minimum(phi, ball(X, c, r))
    ms = Microstructure.from_levelset(phi)
    assert len(ms.inclusions) == 150
    # each window is the inclusion's extent + 2 x 7 steps, rounded up by at most 1.5 per axis
    for inc in ms.inclusions:
        extent = (inc.upper - inc.lower) * n + 2 * 7
        assert all(e < w <= 1.5 * e + 1 for e, w in zip(extent, inc.phi_fn.args[0].shape))
    assert sum(inc.phi_fn.args[0].size for inc in ms.inclusions) < 150 * phi.size / 30  # not 150 grids
    near = np.abs(phi) < 2 / n
    np.testing.assert_allclose(ms.dn1[near], phi[near], atol=1e-12)
    assert ms.volume_fraction() == pytest.approx(sum(4 / 3 * np.pi * r**3 for r in radii), rel=0.02)


@pytest.mark.parametrize("center", [(0.0, 0.1, 0.5), (1e-17, 0.0, 0.0), (-1e-17, 0.5, 0.5)])
def test_from_functions_centre_on_the_box_boundary(center):
    """A centre exactly on (or a rounding error off) a face: its bounds straddle 0 and must not lose it."""
    import jax.numpy as jnp

    from jaxmesh.geometry._shapes import sphere_sdf

    ms = Microstructure.from_functions([sphere_sdf(jnp.array(center), 0.2)], (1.0, 1.0, 1.0), (24, 24, 24))
    assert len(ms.inclusions) == 1
    n_inside = int(np.sum(ms.dn1 < 0))
    expected = 4.0 / 3.0 * np.pi * 0.2**3 * 24**3
    assert abs(n_inside - expected) < 0.1 * expected


@pytest.mark.parametrize("shape, box", [((32, 32, 32), (1.0, 1.0, 1.0)), ((40, 24, 16), (1.0, 0.6, 0.5)),
                                        ((64, 48), (1.0, 0.75))])
def test_function_bounds_coarse_to_fine_search_finds_every_negative_node(shape, box):
    """Against every node of [-L, 2L)^d: small inclusions between lattice nodes, in the box, beyond it."""
    from jaxmesh.geometry._components import chord_thickness, crossing_bounds
    from jaxmesh.geometry._microstructure import _grid_points, evaluate, function_bounds
    from jaxmesh.geometry._shapes import ellipsoid_sdf, sphere_sdf

    d = len(shape)
    spacing = np.asarray(box) / np.asarray(shape)
    rng = np.random.default_rng(len(shape) * shape[0])
    full = [np.arange(-n, 2 * n) for n in shape]
    pts = _grid_points(full, spacing)
    for k in range(6):
        centre = rng.uniform(-0.9, 1.9, d) * np.asarray(box)
        r = (1.2 + 3 * rng.random()) * spacing.max()
        f = sphere_sdf(centre, r) if k % 2 else ellipsoid_sdf(centre, np.array([1.6, 1.0, 0.7][:d]) * r)
        lower, upper, count, thick = function_bounds(f, k, shape, spacing)
        vals = evaluate(f, pts).reshape([len(a) for a in full])
        own = vals < 0
        lo, hi = crossing_bounds(vals, own, [False] * d)
        assert count == own.sum()
        np.testing.assert_allclose(lower, (lo - np.asarray(shape)) * spacing, atol=1e-12)
        np.testing.assert_allclose(upper, (hi - np.asarray(shape)) * spacing, atol=1e-12)
        assert thick == pytest.approx(chord_thickness(vals, own), abs=1e-12)


@pytest.mark.parametrize("periodic", [True, False])
def test_analytic_inclusions_evaluated_together_match_one_by_one(periodic):
    """Analytic inclusions of one kind are evaluated in one compiled call (Microstructure.phi,
    label): the same values and ids as each phi_fn on its own, beside an opaque function."""
    from jaxmesh import ellipsoid_sdf, sphere_sdf

    fns = [sphere_sdf(jnp.array([0.2, 0.25, 0.5]), 0.12), sphere_sdf(jnp.array([0.95, 0.7, 0.3]), 0.15),
           ellipsoid_sdf(jnp.array([0.6, 0.3, 0.75]), jnp.array([0.15, 0.08, 0.1])),
           ellipsoid_sdf(jnp.array([0.55, 0.75, 0.8]), jnp.array([0.12, 0.1, 0.06])),
           jball((0.5, 0.5, 0.1), 0.08),
           grid_phi_fn(make_levelset_grid(ball(nodes(32, 3), (0.1, 0.8, 0.8), 0.08)))]
    ms = Microstructure.from_functions(fns, (1.0, 1.0, 1.0), (32, 32, 32), periodic=periodic)
    # spheres and ellipsoids stacked; the lambda and the grid function (large parameters) one by one
    assert [len(g) for g in ms._groups()] == [0, 2, 2]
    pts = np.random.default_rng(7).random((3000, 3))
    one_by_one = np.stack([ms.inclusion_phi(inc.id, pts) for inc in ms.inclusions])
    near = np.abs(one_by_one.min(axis=0)) < 0.1
    np.testing.assert_allclose(ms.phi(pts)[near], one_by_one.min(axis=0)[near], atol=1e-14)
    inside = one_by_one.min(axis=0) < 0
    np.testing.assert_array_equal(ms.label(pts), np.where(inside, one_by_one.argmin(axis=0) + 1, 0))
    assert inside.sum() > 50


@pytest.mark.parametrize("box", [(1.0, 1.0, 1.0), (1.0, 0.6, 1.4), (1.0, 0.8)])
def test_nearest_images_give_the_values_and_gradients_of_all_images(box):
    """A periodized sphere or ellipsoid evaluated over the 2^d images nearest its centre equals the
    minimum over all 3^d images, bit for bit, at points anywhere (far outside the box too), for
    centres on the box planes and the longest ellipsoid the bound admits; beyond the bound, or with
    the centre outside the box, all images are kept."""
    from jaxmesh import ellipsoid_sdf, sphere_sdf
    from jaxmesh._periodic import nearest_images_suffice
    from jaxmesh.geometry._microstructure import _Periodized, evaluate, periodized

    d, L = len(box), np.asarray(box)
    half_diagonal = 0.5 * np.linalg.norm(L)
    bound = np.hypot(half_diagonal, L.min()) - half_diagonal
    rng = np.random.default_rng(len(box) + int(10 * box[1]))
    rotation = np.linalg.qr(rng.normal(size=(d, d)))[0]
    longest = np.full(d, 0.05)
    longest[0] = 0.05 + 0.999 * bound
    fns = [sphere_sdf(jnp.asarray(L * 0.3), 0.2), sphere_sdf(jnp.zeros(d), 0.1),
           ellipsoid_sdf(jnp.asarray(L * 0.9), jnp.asarray(np.linspace(0.2, 0.06, d)), jnp.asarray(rotation)),
           ellipsoid_sdf(jnp.asarray(L), jnp.asarray(longest), jnp.asarray(rotation))]
    pts = rng.uniform(-1.5, 2.5, (3000, d)) * L
    for f in fns:
        fast, every = periodized(f, box), _Periodized(f, tuple(box), False)
        assert fast.nearest_images
        np.testing.assert_array_equal(evaluate(fast, pts), evaluate(every, pts))
        grad = [jax.vmap(jax.grad(lambda x, g=g: g(x[None])[0]))(jnp.asarray(pts[:300])) for g in (fast, every)]
        np.testing.assert_allclose(grad[0], grad[1], atol=1e-12)
    too_long = np.full(d, 0.05)
    too_long[0] = 0.05 + 1.01 * bound
    assert not periodized(ellipsoid_sdf(jnp.asarray(L / 2), jnp.asarray(too_long)), box).nearest_images
    assert not periodized(sphere_sdf(jnp.asarray(-0.01 * L), 0.1), box).nearest_images
    assert nearest_images_suffice(L / 2, bound, box) and not nearest_images_suffice(L / 2, 1.001 * bound, box)


@pytest.mark.parametrize("periodic", [True, False])
def test_redistance_makes_a_field_a_distance_with_the_same_signs(periodic):
    """(r^2 - R^2)(1 + 0.8 sin 2 pi x) is far from a distance (its slope on the sphere varies
    along x); redistanced, every node keeps its sign, the nodes within a quarter step of the interface
    hold r - R to a twentieth of a step, the others to a step, and the slope is ~1 all round."""
    from jaxmesh.geometry._components import first_order_distance

    n, R = 40, 0.3
    h = 1.0 / n
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    r = np.linalg.norm(x - 0.5, axis=-1)
    field = (r**2 - R**2) * (1 + 0.8 * np.sin(2 * np.pi * x[..., 0]))
    phi = first_order_distance(field, field < 0, (h,) * 3, periodic)
    assert np.array_equal(phi < 0, field < 0)
    near = np.abs(r - R) < 0.25 * h
    assert np.abs(phi - (r - R))[near].max() < 0.05 * h
    assert np.abs(phi - (r - R)).max() < h
    ms = Microstructure.from_levelset(field, periodic=periodic, redistance=True)
    assert ms.inclusions[0].description["redistanced"] is True
    on = 0.5 + R * np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0]])
    d = 0.1 * h

    def slopes(m):
        return np.array([abs(float(m.phi(p[None] + d * a)[0] - m.phi(p[None] - d * a)[0])) / (2 * d)
                         for p in on for a in [(p - 0.5) / R]])

    assert np.allclose(slopes(ms), 1.0, atol=0.1)
    raw = slopes(Microstructure.from_levelset(field, periodic=periodic))
    assert raw.max() > 2 * raw.min()  # as given: one scale for the whole field
    from jaxmesh._pipeline import _as_microstructure

    given = Microstructure.from_levelset(field, periodic=periodic)
    meshed = _as_microstructure(given, periodic=periodic, redistance=True)[0]  # MeshConfig(redistance=True)
    assert given.can_redistance and not ms.can_redistance and not meshed.can_redistance
    assert meshed.inclusions[0].description["redistanced"] is True
    assert np.array_equal(meshed.phi(on), ms.phi(on))
    assert _as_microstructure(ms, periodic=periodic, redistance=True)[0] is ms  # redistanced already
    with pytest.raises(ValueError, match="redistanced needs a level set built by from_levelset without"):
        ms.redistanced()


def test_slope_spread_tells_distances_from_other_fields():
    """from_levelset's slope_spread (gradient_scale): about 1 for a sampled distance, below 1.5 for a
    first-order one (redistanced, or the generator's excursion sets), above 1.5 for a field whose slope
    varies along its zero set and above 2 for a thresholded Gaussian random field: mesh_rve redistances
    a level set above 1.5 after a failure."""
    from jaxmesh._generate import excursion_set
    from jaxmesh._pipeline import _DISTANCE_SPREAD

    def spread(ms):
        return ms.inclusions[0].description["slope_spread"]

    n, R = 32, 0.3
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    r = np.linalg.norm(x - 0.5, axis=-1)
    assert spread(Microstructure.from_levelset(r - R)) < 1.05
    varying = Microstructure.from_levelset((r**2 - R**2) * (1 + 0.8 * np.sin(2 * np.pi * x[..., 0])))
    assert spread(varying) > 2 * _DISTANCE_SPREAD and spread(varying.redistanced()) < _DISTANCE_SPREAD
    rng = np.random.default_rng(5)
    k2 = sum(k**2 for k in np.meshgrid(*[np.fft.fftfreq(n, 1 / n)] * 3, indexing="ij"))
    field = np.fft.ifftn(np.fft.fftn(rng.normal(size=(n,) * 3)) * np.exp(-0.5 * k2 * (2 * np.pi * 0.12) ** 2)).real
    raw = Microstructure.from_levelset(field - np.quantile(field, 0.3), check_necks=False)
    assert spread(raw) > 2 and spread(raw.redistanced()) < _DISTANCE_SPREAD
    generated = Microstructure.from_levelset(
        excursion_set((1.0,) * 3, (n,) * 3, correlation_length=0.12, volume_fraction=0.3, seed=5), check_necks=False)
    assert spread(generated) < _DISTANCE_SPREAD


def test_a_plain_box_field_is_not_rescaled_by_its_jump_across_the_wrap():
    """A sphere's distance sampled without wrapping and cut by the far planes x = z = L: the field is a
    distance (scale 1) on a plain box. The slopes once came from periodic differences, which took the
    jump from phi[n-1] (beside the sphere) to phi[0] (far from it) for one: the field was divided by
    about 20 and its inside flattened to nearly zero."""
    n, R = 48, 0.1
    x = np.stack(np.meshgrid(*[np.arange(n) / n] * 3, indexing="ij"), axis=-1)
    centre = np.array([0.9286, 0.5, 0.9286])
    ms = Microstructure.from_levelset(np.linalg.norm(x - centre, axis=-1) - R, periodic=False)
    assert ms.inclusions[0].description["scale"] == 1.0
    assert ms.inclusions[0].description["slope_spread"] < 1.1
    directions = np.random.default_rng(3).normal(size=(40, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for depth in (0.0, 0.05):  # on the sphere and half its radius in, where it lies inside the box
        pts = centre + (R - depth) * directions
        pts = pts[np.all(pts < 1 - 1.0 / n, axis=1)]
        np.testing.assert_allclose(ms.phi(pts), -depth, atol=2e-3)


def test_rolled_rebuilds_a_grid_microstructure_in_the_shifted_frame():
    """rolled(k): the grid read so that sample k lies at x = 0, so the field at x equals the original's at
    x + k h (mod L), for level sets, labelled images and analytic inclusions (whose description's centre
    moves with them); a plain box cannot roll."""
    n = 24
    x = np.arange(n) / n
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    d = X - np.array([0.1, 0.5, 0.6])
    d -= np.round(d)
    phi = np.linalg.norm(d, axis=-1) - 0.2
    pts = np.random.default_rng(0).random((50, 3))
    shift = np.array([6, 0, 3]) / n
    for ms in (Microstructure.from_levelset(phi), Microstructure.from_labels((phi < 0).astype(np.int32))):
        assert ms.can_roll
        moved = ms.rolled((6, 0, 3))
        assert moved.grid_shape == ms.grid_shape and len(moved.inclusions) == 1
        np.testing.assert_allclose(moved.phi(pts), ms.phi(np.mod(pts + shift, 1.0)), atol=1e-9)
        np.testing.assert_array_equal(moved.label(pts), ms.label(np.mod(pts + shift, 1.0)))
    assert not Microstructure.from_levelset(phi[4:-4, 4:-4, 4:-4], periodic=False).can_roll
    with pytest.raises(ValueError, match="rolled expected 3 integers"):
        Microstructure.from_levelset(phi).rolled((1, 2))
    analytic = Microstructure.from_functions([lambda p: jnp.linalg.norm(p - 0.5, axis=-1) - 0.2], (1.0,) * 3, (n,) * 3,
                                             descriptions=[{"kind": "sphere", "center": [0.5, 0.5, 0.5]}])
    moved = analytic.rolled((6, 0, 15))
    shift = np.array([6, 0, 15]) / n
    np.testing.assert_allclose(moved.phi(pts), analytic.phi(np.mod(pts + shift, 1.0)), atol=1e-12)
    assert moved.inclusions[0].description["center"] == pytest.approx([0.25, 0.5, 0.875])
    from jaxmesh import ellipsoid_sdf, sphere_sdf

    kernels = Microstructure.from_functions(
        [sphere_sdf(jnp.array([0.1, 0.5, 0.6]), 0.2),
         ellipsoid_sdf(jnp.array([0.6, 0.2, 0.1]), jnp.array([0.2, 0.1, 0.12]))],
        (1.0,) * 3, (n,) * 3)
    moved = kernels.rolled((6, 0, 15))
    np.testing.assert_allclose(moved.phi(pts), kernels.phi(np.mod(pts + shift, 1.0)), atol=1e-12)
    assert [len(g) for g in moved._groups()] == [0, 2, 0]  # still analytic kernels, evaluated together
    assert all(inc.phi_fn.nearest_images for inc in moved.inclusions)
    plain = Microstructure.from_functions([lambda p: jnp.linalg.norm(p - 0.5, axis=-1) - 0.2], (1.0,) * 3, (n,) * 3,
                                          periodic=False)
    with pytest.raises(ValueError, match="needs a periodic microstructure"):
        plain.rolled((1, 0, 0))


def test_close_box_layers_closes_only_layers_thinner_than_the_fraction_along_a_plane():
    from jaxmesh.geometry._components import close_box_layers

    n, h = 16, 1.0 / 16
    x = np.arange(n) * h
    X, Y = np.meshgrid(x, x, indexing="ij")
    fraction = 1.0 / 6.0
    # matrix layer 0.05 steps thick along x = 0 (inclusion beyond x = t): the plane sample turns negative
    thin = 0.05 * h - X
    out, changed = close_box_layers(thin, fraction)
    assert changed == n and np.all(out[0] < 0) and np.array_equal(out[1:], thin[1:])
    assert np.allclose(out[0], -fraction * np.abs(thin[1]))
    # 0.3 steps thick, or an interface crossing the plane at a right angle: nothing changes
    for kept in (0.3 * h - X, Y - 0.53):
        out, changed = close_box_layers(kept, fraction)
        assert changed == 0 and np.array_equal(out, kept)
    # a sheet of inclusion 0.05 steps deep along the far plane y = L (the continuation 2 v[n-1] - v[n-2]
    # there): |v[n-1]| rises, its sign stays, and the continued value on the plane turns positive
    sheet = (1.0 - 0.05 * h) - Y
    out, changed = close_box_layers(sheet, fraction)
    assert changed == n
    assert np.all(np.sign(out[:, -1]) == np.sign(sheet[:, -1])) and np.all(out[:, -1] > sheet[:, -1])
    assert np.all(2 * out[:, -1] - out[:, -2] > 0) and np.array_equal(out[:, :-1], sheet[:, :-1])
    # a layer under one or two samples of the plane is kept: closing it would make a speck of trace
    speck = np.ones((n, n))
    speck[1, 7:9], speck[0, 7:9] = -1.0, 0.01
    assert close_box_layers(speck, fraction)[1] == 0
    speck[1, 7:11], speck[0, 7:11] = -1.0, 0.01
    out, changed = close_box_layers(speck, fraction)
    assert changed == 4 and np.all(out[0, 7:11] < 0)


def test_with_box_layers_closed_brings_a_grazing_interface_onto_a_plain_box_plane(tmp_path):
    n = 24
    x = np.arange(n) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    phi = flat_bottom_ellipsoid(n, 0.02)
    ms = Microstructure.from_levelset(phi, periodic=False)
    assert len(ms.inclusions) == 1 and ms.can_close_box_layers and not ms.can_roll
    assert ms.inclusions[0].lower[2] > 0 and ms.phi(np.array([[0.5, 0.5, 0.0]]))[0] > 0
    closed = ms.with_box_layers_closed()
    assert len(closed.inclusions) == 1 and not closed.can_close_box_layers
    assert closed.inclusions[0].description["box_layers_closed"] > 0
    assert closed.inclusions[0].lower[2] == 0 and closed.phi(np.array([[0.5, 0.5, 0.0]]))[0] < 0
    far = np.array([[0.5, 0.5, 0.5], [0.1, 0.2, 0.05]])  # away from the layer the field is the same
    assert np.allclose(closed.phi(far), ms.phi(far), atol=1e-6)
    path = tmp_path / "grazing.npy"  # read from a file: closed in the one build
    np.save(path, phi)
    read = load_input(path, periodic=False, close_box_layers=True)
    assert read.inclusions[0].description["box_layers_closed"] == closed.inclusions[0].description["box_layers_closed"]
    assert np.allclose(read.phi(far), closed.phi(far), atol=0) and not read.can_close_box_layers
    labels = tmp_path / "labels.npy"  # labelled images have no layers to close: the option is ignored
    np.save(labels, (phi < 0).astype(np.int32))
    image = load_input(labels, periodic=False, close_box_layers=True)
    assert "box_layers_closed" not in image.inclusions[0].description
    with pytest.raises(ValueError, match="plain box"):
        Microstructure.from_levelset(phi, periodic=True, close_box_layers=True)
    ball = np.sqrt((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2) - 0.25
    assert not Microstructure.from_levelset(ball).can_close_box_layers  # periodic: roll instead
