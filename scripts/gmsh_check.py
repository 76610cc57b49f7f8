"""Open a jaxmesh .msh in Gmsh itself (its Python API) and check what Gmsh reads back.

Gmsh is GPL, so it is not a dependency of jaxmesh; run this from a separate environment:

    python3.12 -m venv /tmp/gmsh_venv && /tmp/gmsh_venv/bin/pip install gmsh numpy
    jaxmesh mesh out/rve3d.npz -o out/rve3d.msh
    /tmp/gmsh_venv/bin/python scripts/gmsh_check.py out/rve3d.msh

It prints the entities, element counts and physical groups Gmsh sees, checks every periodic node
pair Gmsh reads against its affine transformation (slave = A master; a plain-box mesh has none), and
Gmsh's own element quality (minSICN, positive for every valid element). Exit status 1 when a check fails.
"""

import sys

import gmsh
import numpy as np


def main(path: str) -> int:
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        gmsh.open(path)
        dim = gmsh.model.getDimension()
        print(f"{path}: dimension {dim}, entities per dimension "
              f"{[len(gmsh.model.getEntities(d)) for d in range(dim + 1)]}")
        types, element_tags, _ = gmsh.model.mesh.getElements()
        for kind, tags in zip(types, element_tags):
            print(f"  {gmsh.model.mesh.getElementProperties(kind)[0]}: {len(tags)}")
        groups = [f"{gmsh.model.getPhysicalName(d, t)} ({d}D)" for d, t in gmsh.model.getPhysicalGroups()]
        print(f"  physical groups: {', '.join(groups)}")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        position = dict(zip(node_tags.tolist(), coords.reshape(-1, 3)))
        pairs, worst = 0, 0.0
        for d, t in [e for k in range(dim - 1, -1, -1) for e in gmsh.model.getEntities(k)]:
            master, slaves, masters, affine = gmsh.model.mesh.getPeriodicNodes(d, t)
            if master == t or not len(slaves):
                continue
            a = np.asarray(affine).reshape(4, 4)
            for s, m in zip(slaves, masters):
                image = (a @ np.append(position[int(m)], 1.0))[:3]
                worst = max(worst, float(np.abs(image - position[int(s)]).max()))
                pairs += 1
        print(f"  periodic node pairs: {pairs}, max |A x_master - x_slave| = {worst:.3g}" if pairs else
              "  no periodic entities (a plain-box mesh, `--no-periodic`)")
        quality = gmsh.model.mesh.getElementQualities(element_tags[-1], "minSICN")
        print(f"  Gmsh minSICN of the {dim}D elements: min {quality.min():.3f}, mean {quality.mean():.3f}, "
              f"{int((quality <= 0).sum())} <= 0")
        extent = np.ptp(coords.reshape(-1, 3), axis=0).max()
        ok = worst <= 1e-9 * extent and quality.min() > 0
        print("  ok" if ok else "  FAILED")
        return 0 if ok else 1
    finally:
        gmsh.finalize()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} MESH.msh")
    sys.exit(main(sys.argv[1]))
