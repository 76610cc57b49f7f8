"""An inclusion that crosses a box plane by much less than a grid step, end to end through mesh_rve.

The surface stage meshes it as not crossing the plane, yet its level set does: the volume recovery
once projected split points beyond the plane, outside the hull, and diverged (the 200-sphere RVE,
inclusion 53, crossed y = 0 by 7e-5 with grid step 1/128).
"""

import numpy as np

from jaxmesh import InclusionSpec, MeshConfig, mesh_rve, microstructure_from_specs, validate


def test_sphere_grazing_a_box_plane_meshes_and_validates():
    n, r = 32, 0.2
    depth = 0.005 / n  # the cap beyond y = 0: 1/200 of a grid step deep, radius 0.009 (h = 0.05)
    spec = InclusionSpec("sphere", np.array([0.43, r - depth, 0.57]), np.full(3, r), np.eye(3))
    ms = microstructure_from_specs([spec], (1.0, 1.0, 1.0), (n,) * 3)
    mesh = mesh_rve(ms, MeshConfig(h=0.05, seed=0))
    assert mesh.metadata["volume"]["surface_splits"] > 0  # the recovery had to split interface edges
    assert np.all((mesh.points >= 0) & (mesh.points <= 1))
    report = validate(mesh, ms)
    assert report.ok, report.summary()
