"""A periodic conductivity homogenisation of a jaxmesh .msh in scikit-fem, an FE code of its own.

scikit-fem is not a dependency of jaxmesh; put it beside the project's environment:

    pip install --no-deps --target /tmp/skfem_lib scikit-fem
    jaxmesh mesh out/rve3d.npz -o out/rve3d.msh
    PYTHONPATH=/tmp/skfem_lib python scripts/skfem_check.py out/rve3d.msh --k-matrix 1 --k-inclusion 10

The file is read by meshio (tets, the Gmsh physical groups `matrix` / `inclusion_*` and the `$Periodic`
node pairs), the P1 stiffness is assembled by scikit-fem with one conductivity per cell, and the cell
problem u = E x + w (w periodic: one unknown per class of periodic nodes) is solved for each unit E. It
prints the effective tensor and, when jaxmesh imports, `jaxmesh.homogenize_conductivity` on the same
file for comparison. Exit status 1 when the two differ by more than 1e-8 relative.
"""

import argparse
import sys

import meshio
import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
import skfem
from skfem.helpers import dot, grad


def _periodic_classes(n: int, periodic) -> np.ndarray:
    """Each node's class id: the $Periodic pairs (slave, master) joined, chains and corners included."""
    pairs = np.concatenate([np.asarray(p, dtype=np.int64).reshape(-1, 2) for _, _, _, p in periodic])
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return csgraph.connected_components(graph, directed=False)[1]


def skfem_conductivity(path: str, k_matrix: float, k_inclusion: float) -> np.ndarray:
    mesh = meshio.read(path)
    tets = mesh.cells_dict["tetra"]
    tags = mesh.cell_data_dict["gmsh:physical"]["tetra"]
    matrix_tag = int(mesh.field_data["matrix"][0])
    k = np.where(tags == matrix_tag, k_matrix, k_inclusion)
    fem = skfem.MeshTet(mesh.points.T.copy(), tets.T.copy())
    basis = skfem.Basis(fem, skfem.ElementTetP1())
    k_field = basis.with_element(skfem.ElementTetP0()).interpolate(k)

    @skfem.BilinearForm
    def conduction(u, v, w):
        return w["k"] * dot(grad(u), grad(v))

    stiffness = conduction.assemble(basis, k=k_field).tocsr()
    classes = _periodic_classes(len(mesh.points), mesh.gmsh_periodic)
    n = len(mesh.points)
    to_class = sp.csr_matrix((np.ones(n), (np.arange(n), classes)), shape=(n, classes.max() + 1))
    reduced = (to_class.T @ stiffness @ to_class).tocsc()[1:, 1:]  # class 0 fixed: the constant is free
    volume = np.prod(np.ptp(mesh.points, axis=0))
    solve = spla.factorized(reduced)
    fields = []
    for j in range(3):
        affine = mesh.points[:, j]
        w = np.concatenate([[0.0], solve(-(to_class.T @ (stiffness @ affine))[1:])])
        fields.append(affine + to_class @ w)
    total = np.array(fields)
    return total @ stiffness @ total.T / volume


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", help="a jaxmesh .msh (Gmsh 4.1 with physical groups and $Periodic)")
    parser.add_argument("--k-matrix", type=float, default=1.0)
    parser.add_argument("--k-inclusion", type=float, default=10.0)
    args = parser.parse_args()
    k_eff = skfem_conductivity(args.mesh, args.k_matrix, args.k_inclusion)
    np.set_printoptions(precision=6, suppress=True)
    print(f"scikit-fem {skfem.__version__ if hasattr(skfem, '__version__') else ''} P1, periodic by the file's "
          f"$Periodic pairs: k_eff =\n{k_eff}")
    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jaxmesh
    except ImportError:
        return 0
    reference = jaxmesh.homogenize_conductivity(jaxmesh.read_mesh(args.mesh), {0: args.k_matrix, 1: args.k_inclusion},
                                                by="phase", solver="direct")
    difference = float(np.abs(k_eff - reference).max() / np.abs(reference).max())
    print(f"jaxmesh.homogenize_conductivity on the same file:\n{reference}\nlargest relative difference {difference:.1e}")
    return 0 if difference <= 1e-8 else 1


if __name__ == "__main__":
    sys.exit(main())
