"""PNG views of a mesh: 2D triangles or a 3D mid-plane cut, plus the quality histogram (matplotlib Agg).

Figures are built with `matplotlib.figure.Figure` (no pyplot, no global backend state) and saved
atomically through `jaxmesh.io._write.atomic_path`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._quality import TET_EDGES, cell_quality
from .io._write import atomic_path

_MATRIX_RGBA = (0.86, 0.86, 0.86, 1.0)


def check_png_path(path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"plots are written as PNG, got {path.name!r}; hint: use a .png file name")
    return path


def _colors(ids: np.ndarray, color_by: str) -> np.ndarray:
    """RGBA per cell: matrix grey; inclusions from tab20 (by id) or one colour (by phase)."""
    from matplotlib import colormaps

    if color_by not in ("inclusion", "phase"):
        raise ValueError(f"color_by must be 'inclusion' or 'phase', got {color_by!r}")
    # tab20 without its two greys (14, 15): an inclusion must never look like the matrix
    palette = np.asarray(colormaps["tab20"].colors)[[i for i in range(20) if i not in (14, 15)]]
    rgba = np.tile(np.asarray(_MATRIX_RGBA), (len(ids), 1))
    inc = ids > 0
    index = (ids[inc] - 1) % len(palette) if color_by == "inclusion" else np.zeros(inc.sum(), int)
    rgba[inc, :3] = palette[index]
    rgba[inc, 3] = 1.0
    return rgba


def mid_plane_section(points, tets, z: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Cross-sections of tetrahedra with the plane z = const.

    Vertices exactly on the plane count as above it, so a facet lying in the plane is drawn
    once (from the cell below) and no degenerate polygon appears.

    Args:
        points: (n, 3); tets: (m, 4); z: plane height.
    Returns:
        (polygons, cell ids): a list of (k, 2) xy polygons (k = 3 or 4, counter-clockwise, non-zero
        area; their areas sum to the box section) and the index of the tetrahedron each one cuts.
    """
    p = np.asarray(points, dtype=float)[np.asarray(tets)]  # (m, 4, 3)
    s = p[..., 2] - z
    below = s < 0
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    cross = below[:, i] != below[:, j]  # (m, 6)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, s[:, i] / (s[:, i] - s[:, j]), 0.0)
    xy = p[:, i, :2] + t[..., None] * (p[:, j, :2] - p[:, i, :2])  # (m, 6, 2)
    count = cross.sum(axis=1)
    polys, owner = [], []
    for k in (3, 4):
        cells = np.flatnonzero(count == k)
        if len(cells) == 0:
            continue
        pts = xy[cells][cross[cells]].reshape(len(cells), k, 2)
        centre = pts.mean(axis=1, keepdims=True)
        ang = np.arctan2(pts[..., 1] - centre[..., 1], pts[..., 0] - centre[..., 0])
        pts = np.take_along_axis(pts, np.argsort(ang, axis=1)[..., None], axis=1)
        x, y = pts[..., 0], pts[..., 1]
        area = 0.5 * np.sum(x * np.roll(y, -1, axis=1) - y * np.roll(x, -1, axis=1), axis=1)
        # Cells touching the plane only at a vertex or an edge give zero-area polygons: drop them.
        keep = area > 1e-12 * np.max(np.abs(p[..., :2]), initial=1.0) ** 2
        polys.extend(pts[keep])
        owner.append(cells[keep])
    return polys, (np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64))


def _draw_histogram(ax, q: np.ndarray, threshold: float = 0.3) -> None:
    ax.hist(q, bins=np.linspace(0.0, 1.0, 21), color="#4c72b0", edgecolor="white")
    ax.axvline(threshold, color="#c44e52", linestyle="--", linewidth=1)
    below = float(np.mean(q < threshold)) if len(q) else 0.0
    stats = f"min {q.min():.3f}  mean {q.mean():.3f}\n{100 * below:.2f}% below {threshold}" if len(q) else "no cells"
    ax.text(0.03, 0.95, stats, transform=ax.transAxes, va="top", fontsize=9)
    ax.set_xlim(0.0, 1.0)
    ax.set_xlabel("quality q = d r_in / r_circ")
    ax.set_ylabel("cells")
    ax.set_title("element quality")


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return path


def plot_mesh(mesh, path, *, title: str | None = None, color_by: str = "inclusion") -> Path:
    """Save a PNG of the mesh next to its quality histogram.

    2D: all triangles filled by inclusion (or phase) with their edges. 3D: the section of the
    tetrahedra crossing the mid-plane z = Lz / 2, each cut polygon filled by its cell's colour.

    Args:
        mesh: a `jaxmesh.Mesh`.
        path: target .png (written atomically; its folder must exist).
        title: figure title (default: a one-line description of the mesh).
        color_by: "inclusion" (one colour per id) or "phase" (matrix / inclusions).
    Returns:
        the written path.

    Example: ``plot_mesh(mesh, "rve.png")``.
    """
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    path = check_png_path(path)
    pts, cells, ids = np.asarray(mesh.points), np.asarray(mesh.cells), np.asarray(mesh.inclusion_id)
    box = np.asarray(mesh.box, dtype=float)
    colors = _colors(ids, color_by)
    fig = Figure(figsize=(11.0, 5.0))
    ax, hax = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.2, 1.0]})
    if mesh.dim == 2:
        polys, face = list(pts[cells]), colors
        view = "triangles"
    else:
        z = 0.5 * box[2]
        polys, owner = mid_plane_section(pts, cells, z)
        face = colors[owner]
        view = f"section z = {z:.4g} ({len(polys)} cells cut)"
    lw = 0.6 if len(polys) < 5000 else 0.15
    ax.add_collection(PolyCollection(polys, facecolors=face, edgecolors="k", linewidths=lw))
    ax.set_xlim(0.0, box[0])
    ax.set_ylim(0.0, box[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title(view)
    _draw_histogram(hax, cell_quality(pts, cells))
    n_inc = len(np.unique(ids[ids > 0]))
    fig.suptitle(title or f"{mesh.dim}D mesh: {len(pts)} nodes, {len(cells)} cells, {n_inc} inclusions")
    return _save(fig, path)


def plot_quality_histogram(mesh, path, *, title: str | None = None) -> Path:
    """Save a PNG histogram of the cell quality q (20 bins on [0, 1], 0.3 marked).

    Args:
        mesh: a `jaxmesh.Mesh` (or anything with points and cells).
        path: target .png (written atomically).
        title: figure title.
    Returns:
        the written path.
    """
    from matplotlib.figure import Figure

    path = check_png_path(path)
    fig = Figure(figsize=(6.0, 4.0))
    ax = fig.subplots()
    _draw_histogram(ax, cell_quality(mesh.points, mesh.cells))
    if title:
        ax.set_title(title)
    return _save(fig, path)
