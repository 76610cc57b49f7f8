"""Surface nodes that slide while the volume mesh is smoothed (paper 4.7): interface nodes on their
level set, box-face nodes in their plane together with their periodic copy.

NumPy only. The smoothing (`_slivers.smooth_vertices`) takes its candidates for these nodes in
their tangent planes and asks `keeps_triangles` whether their surface triangles stay well shaped.
A box-face node on x_a = 0 moves with its translate on x_a = L: the smoothing sees the two stars as
one (the copy's tets shifted by -L e_a, `partner` and `shift`), so the faces stay exact translates.
After each sweep `project` puts the moved interface nodes back on the level set by secant steps
along their normals and undoes any move that the projection would leave with a non-positive tet.
The surface triangles never change, only where their vertices sit on the level set or the box
plane: the mesh stays conforming and periodic. Trace, box-edge and corner nodes stay fixed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._mesh import on_box_planes
from ._quality import _angle
from ._slivers import _star_rows, tet_quality

__all__ = ["SurfaceSlide"]

# A move may not take a surface triangle's smallest angle below min(its angle now, MIN_ANGLE).
MIN_ANGLE = 30.0
# Secant steps of the projection, and |phi| it must reach (times the box's longest side).
SECANT_STEPS, PHI_TOL = 8, 1e-13


class SurfaceSlide:
    """The surface nodes of a surface mesh that may slide during the volume smoothing.

    Args:
        points: (n, 3) mesh points (the surface nodes first).
        triangles: (t, 3) surface triangles. node_inclusion: (ns,) inclusion of each surface node (0: none).
        box: box lengths. phi_fn: NumPy global level set points (k, 3) -> (k,) (negative inside).
        periodic_pairs: axis -> (k, 2) (node on x_a = 0, its translate on x_a = L); the face nodes of
            those pairs slide too (None: only interface nodes).
        periodic: False: a plain box; every node on one face (and no inclusion) slides in its plane alone.
    Attributes:
        mask: (n,) bool, the sliding nodes: interface nodes on no box plane, and box-face nodes of the
            0-faces on one plane only (their copies follow; they are not in the mask), or of any face
            when not periodic.
        partner: (n,) int64, the copy on x_a = L of a sliding 0-face node, else -1.
        shift: (n, 3) that copy's position minus the node's (L e_a).
    """

    def __init__(self, points: np.ndarray, triangles: np.ndarray, node_inclusion: np.ndarray, box,
                 phi_fn: Callable, periodic_pairs: dict | None = None, periodic: bool = True):
        n, ns = len(points), len(node_inclusion)
        box = np.asarray(box, dtype=float)
        planes = on_box_planes(points[:ns], box)  # (ns, 3, 2)
        self.mask = np.zeros(n, bool)
        self.mask[:ns] = (np.asarray(node_inclusion) > 0) & ~planes.any(axis=(1, 2))
        self.on_level_set = self.mask.copy()  # the nodes `project` puts back on phi = 0
        self.partner = np.full(n, -1, np.int64)
        self.shift = np.zeros((n, 3))
        self.normals = np.zeros((n, 3))  # unit gradients of phi at the first positions; e_a on faces
        self.grad_norm = np.ones(n)
        one_plane = (planes.sum(axis=(1, 2)) == 1) & (np.asarray(node_inclusion) == 0)
        if not periodic:  # every face node slides in its plane on its own
            face = np.flatnonzero(one_plane)
            self.mask[face] = True
            self.normals[face, np.argmax(planes[face].any(axis=2), axis=1)] = 1.0
        for a, pairs in (periodic_pairs or {}).items():
            pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
            u, v = pairs[:, 0], pairs[:, 1]
            face = one_plane[u] & planes[u, a, 0]
            u, v = u[face], v[face]
            self.mask[u] = True
            self.partner[u] = v
            self.shift[u] = points[v] - points[u]
            self.normals[u, a] = 1.0
        self.copy_of = np.full(n, -1, np.int64)  # the inverse of partner
        self.copy_of[self.partner[self.partner >= 0]] = np.flatnonzero(self.partner >= 0)
        self.phi_fn = phi_fn
        self.tol = PHI_TOL * float(box.max())
        self.triangles = np.asarray(triangles, dtype=np.int64)
        flat = self.triangles.ravel()
        order = np.argsort(flat, kind="stable")  # node -> its surface triangles, CSR
        self._tri_of = order // 3
        self._tri_off = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n))])
        self._refresh(points, np.flatnonzero(self.on_level_set))

    def contract(self, edges: np.ndarray) -> np.ndarray:
        """Edges (k, 2) with each copy replaced by its sliding 0-face node: colour classes of these
        never hold two nodes whose (joint) stars share a tet."""
        rep = np.where(self.copy_of >= 0, self.copy_of, np.arange(len(self.copy_of)))
        e = rep[edges]
        return e[e[:, 0] != e[:, 1]]

    def _refresh(self, points: np.ndarray, nodes: np.ndarray) -> None:
        if not len(nodes):
            return
        x = points[nodes]
        eps = 1e-7 * max(float(np.abs(x).max()), 1.0)
        g = np.stack([(self._phi(x + eps * e) - self._phi(x - eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
        norm = np.linalg.norm(g, axis=1)
        ok = norm > 0
        self.normals[nodes] = np.where(ok[:, None], g / np.where(ok, norm, 1.0)[:, None], 0.0)
        self.grad_norm[nodes] = np.where(ok, norm, 1.0)
        self.mask[nodes[~ok]] = False  # no normal (a kink of the field): keep the node where it is
        self.on_level_set[nodes[~ok]] = False

    def _phi(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.phi_fn(x), dtype=float).reshape(-1)

    def tangent_frame(self, points: np.ndarray, verts: np.ndarray) -> _Frame | None:
        """The sliding part of one colour class of the smoothing, or None when it has none."""
        sliding = self.mask[verts]
        if not sliding.any():
            return None
        return _Frame(self, points, verts, sliding)

    def project(self, points: np.ndarray, before: np.ndarray, cells: np.ndarray, by: np.ndarray,
                off: np.ndarray) -> int:
        """Put the interface nodes moved since `before` back on the level set, in place.

        Only the tets around them change shape; where one is no longer positive, the moves of its
        vertices (any vertex, and a face node with its copy) are undone, until every tet is positive
        again. by, off: vertex -> tets CSR of cells. The normals are those of the first positions
        (they turn by about the curvature times the moves, which the secant steps absorb). Returns
        the number of moves undone.
        """
        moved = np.flatnonzero(self.on_level_set & np.any(points != before, axis=1))
        if not len(moved):
            return 0
        x0, n = points[moved], self.normals[moved]
        t, phi = _secant_roots(lambda t, rows: self._phi(x0[rows] + t[:, None] * n[rows]), self._phi(x0),
                               self.grad_norm[moved], self.tol)
        off_set = np.abs(phi) > self.tol
        points[moved] = np.where(off_set[:, None], before[moved], x0 + t[:, None] * n)
        undone = int(off_set.sum())
        check = moved
        while len(check):
            tets = np.unique(_star_rows(by, off, check)[0])
            back = np.unique(cells[tets[tet_quality(points[cells[tets]]) <= 1e-9]].ravel())
            back = np.unique(np.concatenate([back, self.partner[back], self.copy_of[back]]))
            back = back[back >= 0]
            back = back[np.any(points[back] != before[back], axis=1)]
            points[back] = before[back]
            undone += int((self.copy_of[back] < 0).sum())  # a face node and its copy are one move
            check = back
        return undone


def _secant_roots(f: Callable, f0: np.ndarray, slope: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Roots near 0 of k line functions, f(t, rows) the values of rows' functions at t (len(rows),),
    f(0) = f0, by the secant method, the first step with the given slope. Converged rows are not
    evaluated again (each level-set evaluation is the cost). Returns (t, f(t)); rows that do not
    reach |f| <= tol in SECANT_STEPS keep their last iterate."""
    t_prev, f_prev = np.zeros_like(f0), np.array(f0, dtype=float)
    t = -f0 / slope
    f_t = np.array(f(t, np.arange(len(f0))), dtype=float)
    for _ in range(SECANT_STEPS):
        active = np.flatnonzero(np.abs(f_t) > tol)
        if not len(active):
            break
        df = f_t[active] - f_prev[active]
        step = np.where(df != 0, f_t[active] * (t[active] - t_prev[active]) / np.where(df != 0, df, 1.0), 0.0)
        t_prev[active], f_prev[active] = t[active], f_t[active]
        t[active] -= step
        f_t[active] = f(t[active], active)
    return t, f_t


class _Frame:
    """Tangent planes and surface-triangle guard of the sliding vertices of one colour class."""

    def __init__(self, slide: SurfaceSlide, points: np.ndarray, verts: np.ndarray, sliding: np.ndarray):
        self.normals = np.where(sliding[:, None], slide.normals[verts], 0.0)  # 0: moves freely
        rows = np.flatnonzero(sliding)
        tri_ids, owner = _star_rows(slide._tri_of, slide._tri_off, verts[rows])
        self.owner = rows[owner]
        tris = slide.triangles[tri_ids]
        local = np.argmax(tris == verts[self.owner][:, None], axis=1)
        self.b = points[tris[np.arange(len(tris)), (local + 1) % 3]]
        self.c = points[tris[np.arange(len(tris)), (local + 2) % 3]]
        self.k = len(verts)
        self.floor = np.minimum(self._min_angles(points[verts]), MIN_ANGLE) - 1e-9

    def tangential(self, v: np.ndarray) -> np.ndarray:
        """Vectors v (k, 3) without their normal parts at the sliding vertices (others unchanged)."""
        return v - np.einsum("ij,ij->i", v, self.normals)[:, None] * self.normals

    def _min_angles(self, x: np.ndarray) -> np.ndarray:
        """(k,) the smallest angle (degrees) of each vertex's surface triangles with it at x (k, 3)."""
        out = np.full(self.k, 180.0)
        if not len(self.owner):
            return out
        a = x[self.owner]
        worst = np.full(len(a), 180.0)
        for p, u, v in ((a, self.b, self.c), (self.b, self.c, a), (self.c, a, self.b)):
            worst = np.minimum(worst, _angle(u - p, v - p))
        np.minimum.at(out, self.owner, worst)
        return out

    def keeps_triangles(self, x: np.ndarray) -> np.ndarray:
        """(k,) bool: moving the vertices to x keeps their surface triangles' angles above the floor."""
        return self._min_angles(x) >= self.floor
