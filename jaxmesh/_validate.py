"""Mesh validation: the invariants every jaxmesh output must satisfy (NumPy/SciPy only).

`validate` runs eight checks and returns a `ValidationReport`; each check is designed to catch
one class of defect (inverted cells, holes/overlaps, non-manifold facets or nodes in no cell, stray
boundary facets, non-periodic faces, non-conforming interfaces, wrong labels, merged/split inclusions).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ._errors import MeshingError
from ._mesh import AXES, LOCAL_FACETS, classify_facets, facet_table, match_periodic_nodes
from ._quality import FLAT_ANGLE_DEG, FLAT_REL_VOLUME, flat_mask, longest_edges, signed_volumes, smallest_angles

CHECKS = ("orientation", "volume", "manifold", "boundary", "periodic", "interface", "labels", "connectivity")


@dataclass
class Check:
    """Outcome of one check: passed, a one-line detail, and the numbers behind it."""

    name: str
    passed: bool
    detail: str
    counts: dict = field(default_factory=dict)
    skipped: bool = False

    @property
    def value(self) -> str:
        return self.detail

    def to_dict(self) -> dict:
        return {"passed": bool(self.passed), "skipped": bool(self.skipped), "detail": self.detail,
                "counts": {k: _py(v) for k, v in self.counts.items()}}


def _py(v):
    """NumPy scalars -> Python scalars for JSON."""
    if isinstance(v, (np.integer, np.bool_)):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


@dataclass
class ValidationReport:
    """All checks of `validate`; `.ok` is True when every check passed (skipped ones pass)."""

    checks: dict[str, Check]

    @property
    def ok(self) -> bool:
        return all(c.passed for c in self.checks.values())

    @property
    def failed(self) -> list[str]:
        return [n for n, c in self.checks.items() if not c.passed]

    def to_dict(self) -> dict:
        return {"ok": self.ok, "checks": {n: c.to_dict() for n, c in self.checks.items()}}

    def summary(self) -> str:
        lines = [f"mesh validation: {'OK' if self.ok else 'FAILED (' + ', '.join(self.failed) + ')'}"]
        for n, c in self.checks.items():
            tag = "SKIP" if c.skipped else ("PASS" if c.passed else "FAIL")
            lines.append(f"  [{tag}] {n}: {c.detail}")
        return "\n".join(lines)

    def raise_if_invalid(self) -> None:
        """Raise MeshingError('validate', ...) listing the failed checks."""
        if not self.ok:
            raise MeshingError("validate", self.summary())


def _check_inputs(mesh, microstructure, interface_tol):
    for attr in ("points", "cells", "inclusion_id", "box"):
        if not hasattr(mesh, attr):
            raise ValueError(f"validate expects a jaxmesh.Mesh, got {type(mesh).__name__} without .{attr}; "
                             "hint: build one with jaxmesh.Mesh(points, cells, inclusion_id, box)")
    box = np.asarray(mesh.box, dtype=float)
    if microstructure is not None:
        for attr in ("phi", "label", "inclusions"):
            if not hasattr(microstructure, attr):
                raise ValueError(f"microstructure must provide .{attr}, got {type(microstructure).__name__}")
        mbox = getattr(microstructure, "box", None)
        if mbox is not None and (np.shape(mbox) != box.shape or not np.allclose(mbox, box, rtol=1e-12)):
            raise ValueError(f"microstructure box {np.asarray(mbox).tolist()} differs from mesh box "
                             f"{box.tolist()}; hint: validate a mesh against the field it was made from")
    if interface_tol is not None and not interface_tol > 0:
        raise ValueError(f"interface_tol must be positive, got {interface_tol}")
    return box


def _keys(rows: np.ndarray, n: int) -> np.ndarray:
    """One sortable key per row of sorted vertex ids: packed int64 when it fits, else structured."""
    rows = np.sort(np.asarray(rows, dtype=np.int64), axis=1)
    d = rows.shape[1]
    if n**d < 2**62:
        key = rows[:, 0].copy()
        for j in range(1, d):
            key = key * n + rows[:, j]
        return key
    rec = np.dtype([(f"v{j}", np.int64) for j in range(d)])
    return np.ascontiguousarray(rows).view(rec).ravel()


def _orientation(points, cells, flat_eps, flat_angle):
    vol = signed_volumes(points, cells)
    lmax = longest_edges(points[cells])
    d = points.shape[1]
    rel = vol / np.maximum(lmax, np.finfo(float).tiny) ** d
    angles = smallest_angles(points, cells) if len(cells) else np.zeros(0)
    inverted = int(np.sum(rel < -flat_eps))
    flat = int(np.sum(flat_mask(rel, angles, flat_eps, flat_angle)))
    worst = int(np.argmin(rel)) if len(rel) else -1
    sharpest = int(np.argmin(angles)) if len(angles) else -1
    counts = {"inverted": inverted, "flat": flat, "worst_cell": worst,
              "worst_rel_volume": float(rel[worst]) if worst >= 0 else 0.0,
              "min_angle_deg": float(angles[sharpest]) if sharpest >= 0 else 0.0}
    ok = inverted == 0 and flat == 0
    smallest = f"smallest angle {counts['min_angle_deg']:.3g} deg in cell {sharpest}"
    detail = (f"all {len(cells)} cells positive (min V/l_max^{d} = {counts['worst_rel_volume']:.3g}, {smallest})"
              if ok else f"{inverted} inverted, {flat} flat cells; worst cell {worst} with V/l_max^{d} = "
              f"{counts['worst_rel_volume']:.3g}; {smallest}")
    return Check("orientation", ok, detail, counts), vol, lmax


def _periodic(points, box, table, face, pairs_given, n, tol):
    """Check 5; also returns the torus node map (node -> canonical min-side representative)."""
    d = points.shape[1]
    matched = match_periodic_nodes(points, box, tol)
    canon = np.arange(n)
    counts, problems = {}, []
    one = np.flatnonzero(table.counts == 1)
    for a in range(d):
        pairs, lo_bad, hi_bad = matched[a]
        canon[pairs[:, 1]] = pairs[:, 0]
        lo_map = np.full(n, -1, dtype=np.int64)
        lo_map[pairs[:, 0]] = pairs[:, 1]
        f_lo = table.facets[one[face == 2 * a]]
        f_hi = table.facets[one[face == 2 * a + 1]]
        moved = lo_map[f_lo]
        no_partner = np.any(moved < 0, axis=1)
        k_lo, k_hi = _keys(moved[~no_partner], n), _keys(f_hi, n)
        miss_lo = int(no_partner.sum() + np.sum(~np.isin(k_lo, k_hi)))
        miss_hi = int(np.sum(~np.isin(k_hi, k_lo)))
        given = pairs_given.get(a)
        if given is None:
            pair_bad = -1
        else:
            given = np.asarray(given, dtype=np.int64).reshape(-1, 2)
            kg, km = given[:, 0] * n + given[:, 1], pairs[:, 0] * n + pairs[:, 1]
            pair_bad = int(np.sum(~np.isin(kg, km)) + np.sum(~np.isin(km, kg)))
        ax = AXES[a]
        counts.update({f"{ax}_unmatched_nodes": int(len(lo_bad) + len(hi_bad)),
                       f"{ax}_unmatched_facets": miss_lo + miss_hi, f"{ax}_pair_disagreements": pair_bad})
        if len(lo_bad) + len(hi_bad):
            problems.append(f"{ax}: {len(lo_bad)}+{len(hi_bad)} face nodes without translate")
        if miss_lo + miss_hi:
            problems.append(f"{ax}: {miss_lo} facets on {ax}=0 / {miss_hi} on {ax}=L unmatched")
        if pair_bad:
            problems.append(f"{ax}: periodic_pairs " + ("missing" if pair_bad < 0 else
                                                        f"disagree with translation in {pair_bad} pairs"))
    for _ in range(d):  # edge and corner nodes reach the all-min corner in <= d hops
        canon = canon[canon]
    detail = "opposite faces are translates; periodic_pairs agree" if not problems else "; ".join(problems)
    return Check("periodic", not problems, detail, counts), canon


def _interface(points, cells, ids, ttable, ms, tol):
    d = points.shape[1]
    two, owners = ttable.pairs()
    diff = ids[owners[:, 0]] != ids[owners[:, 1]]
    f, own = two[diff], owners[diff]
    verts = []
    for side in (0, 1):  # both copies: across a periodic face the two cells use different nodes
        c = own[:, side]
        local = np.argmax(ttable.cell_facet[c] == f[:, None], axis=1)
        verts.append(cells[c[:, None], LOCAL_FACETS[d][local]])
    v = np.unique(np.concatenate(verts).ravel()) if len(f) else np.zeros(0, dtype=np.int64)
    phi = np.abs(np.asarray(ms.phi(points[v]), dtype=float).reshape(-1)) if len(v) else np.zeros(0)
    bad = phi > tol
    counts = {"interface_facets": int(len(f)), "interface_vertices": int(len(v)),
              "off_level_set": int(bad.sum()), "max_abs_phi": float(phi.max()) if len(phi) else 0.0}
    detail = (f"{len(f)} interface facets, max |phi| = {counts['max_abs_phi']:.3g} <= {tol:.3g}"
              if not bad.any() else f"{int(bad.sum())} of {len(v)} interface vertices off the level set "
              f"(max |phi| = {counts['max_abs_phi']:.3g} > {tol:.3g}, e.g. node {int(v[bad][0])})")
    return Check("interface", not bad.any(), detail, counts)


def _labels(points, cells, ids, lmax, ms):
    cen = points[cells].mean(axis=1)
    lab = np.asarray(ms.label(cen)).reshape(-1).astype(np.int64)
    mismatch = lab != ids
    bad = mismatch.copy()  # near the interface a centroid may fall either side: phi where they disagree
    if mismatch.any():  # (phi at every centroid costs minutes on millions of analytic-ellipsoid cells)
        bad[mismatch] = np.abs(np.asarray(ms.phi(cen[mismatch]), dtype=float).reshape(-1)) > 0.5 * lmax[mismatch]
    known = {int(i.id) for i in ms.inclusions} | {0}
    unknown = sorted(set(np.unique(ids).tolist()) - known)
    # One-to-one: the dominant field label of each mesh id is the id itself, and the dominant
    # mesh id of each field label is that label (catches merges of small inclusions whose every
    # centroid sits near the interface).
    wrong_map = {}
    for src, dst, fmt in ((ids, lab, "mesh {} -> field {}"), (lab, ids, "field {} -> mesh {}")):
        for k in np.unique(src):
            vals, cnt = np.unique(dst[src == k], return_counts=True)
            if int(vals[np.argmax(cnt)]) != int(k):
                wrong_map[fmt.format(int(k), int(vals[np.argmax(cnt)]))] = 1
    counts = {"mismatched": int(mismatch.sum()), "tolerated_near_interface": int((mismatch & ~bad).sum()),
              "bad": int(bad.sum()), "unknown_ids": len(unknown), "wrong_mapping": len(wrong_map)}
    ok = not bad.any() and not unknown and not wrong_map
    if ok:
        detail = f"labels agree ({counts['tolerated_near_interface']} near-interface centroids tolerated)"
    else:
        parts = []
        if bad.any():
            parts.append(f"{int(bad.sum())} cells labelled against the field away from the interface "
                         f"(e.g. cell {int(np.flatnonzero(bad)[0])})")
        if unknown:
            parts.append(f"mesh ids {unknown} are not inclusions of the microstructure")
        if wrong_map:
            parts.append(f"ids do not map one-to-one: {', '.join(wrong_map)}")
        detail = "; ".join(parts)
    return Check("labels", ok, detail, counts)


def _connectivity(ids, ttable, ms, at_boundary=None):
    """Each inclusion one face-connected piece. at_boundary: (m,) cells on the box boundary of a
    non-periodic mesh, where the box cuts an inclusion into pieces that all touch it."""
    m = len(ids)
    two, owners = ttable.pairs()
    same = ids[owners[:, 0]] == ids[owners[:, 1]]
    a, b = owners[same, 0], owners[same, 1]
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(m, m))
    _, comp = connected_components(graph, directed=False)
    n_comp, split = {}, {}
    for k in np.unique(ids):
        pieces = np.unique(comp[ids == k])
        n_comp[int(k)] = len(pieces)
        if k > 0 and len(pieces) > 1:
            if at_boundary is not None and np.isin(pieces, comp[(ids == k) & at_boundary]).all():
                continue
            split[int(k)] = len(pieces)
    mesh_inc = {k for k in n_comp if k > 0}
    missing, unknown = [], []
    if ms is not None:
        field_inc = {int(i.id) for i in ms.inclusions} - {0}
        missing, unknown = sorted(field_inc - mesh_inc), sorted(mesh_inc - field_inc)
    counts = {"inclusions": len(mesh_inc), "disconnected": len(split), "missing": len(missing),
              "unknown": len(unknown), "matrix_components": n_comp.get(0, 0)}
    ok = not split and not missing and not unknown
    parts = []
    if split:
        parts.append(f"ids with several face-connected pieces {split}")
    if missing:
        parts.append(f"inclusions {missing} of the microstructure have no cells")
    if unknown:
        parts.append(f"mesh ids {unknown} are not inclusions of the microstructure")
    detail = "; ".join(parts) if parts else f"{len(mesh_inc)} inclusions, each one connected piece"
    return Check("connectivity", ok, detail, counts)


def validate(mesh, microstructure=None, *, interface_tol=None, volume_rtol: float = 1e-9,
             periodic_tol: float = 1e-9, flat_eps: float = FLAT_REL_VOLUME,
             flat_angle: float = FLAT_ANGLE_DEG) -> ValidationReport:
    """Check a mesh for the invariants of a periodic conforming RVE mesh.

    Args:
        mesh: a `jaxmesh.Mesh` (points (n, d), cells (m, d+1), inclusion_id (m,), box, periodic,
            periodic_pairs).
        microstructure: optional object with .box, .inclusions (each with .id), .phi(points (k, d))
            -> (k,) signed distance (negative inside) and .label(points) -> (k,) int ids; without it
            the interface and label checks are skipped.
        interface_tol: allowed |phi| at interface vertices (default 1e-6 * max(box)).
        volume_rtol: relative tolerance of sum |V| == box volume.
        periodic_tol: relative tolerance (times L) for face planes and periodic translation.
        flat_eps, flat_angle: a cell is flat when |V| <= flat_eps * (its longest edge)^d or its
            smallest angle (dihedral angle of a tet) is below flat_angle degrees.
    Returns:
        ValidationReport with checks orientation, volume, manifold, boundary, periodic, interface,
        labels, connectivity.

    Example: ``validate(mesh, ms).raise_if_invalid()``.
    """
    box = _check_inputs(mesh, microstructure, interface_tol)
    points = np.asarray(mesh.points, dtype=float)
    cells = np.asarray(mesh.cells, dtype=np.int64)
    ids = np.asarray(mesh.inclusion_id, dtype=np.int64)
    n, d = points.shape
    checks: dict[str, Check] = {}

    checks["orientation"], vol, lmax = _orientation(points, cells, flat_eps, flat_angle)

    total, box_vol = float(np.abs(vol).sum()), float(np.prod(box))
    rel = abs(total - box_vol) / box_vol
    checks["volume"] = Check("volume", rel <= volume_rtol,
                             f"sum |V| = {total:.12g}, box {box_vol:.12g}, rel. error {rel:.3g}",
                             {"total": total, "box": box_vol, "rel_error": rel})

    table = facet_table(cells, n)
    over = int(np.sum(table.counts > 2))
    unused = int(np.count_nonzero(np.bincount(cells.ravel(), minlength=n) == 0))  # an empty row in an FE system
    checks["manifold"] = Check("manifold", over == 0 and unused == 0,
                               f"{len(table.counts)} facets, {over} in more than two cells; {unused} nodes in no cell",
                               {"facets": len(table.counts), "non_manifold": over,
                                "max_cells_per_facet": int(table.counts.max(initial=0)), "unused_nodes": unused})

    one = np.flatnonzero(table.counts == 1)
    face = classify_facets(points, table.facets[one], box, periodic_tol)
    stray = int(np.sum(face < 0))
    checks["boundary"] = Check("boundary", stray == 0,
                               f"{len(one)} boundary facets, {stray} not on a box face",
                               {"boundary_facets": len(one), "off_box": stray})

    if getattr(mesh, "periodic", False):
        checks["periodic"], canon = _periodic(points, box, table, face,
                                              dict(getattr(mesh, "periodic_pairs", None) or {}), n, periodic_tol)
        tcells = canon[cells]
        collapsed = int(np.sum(np.any(np.diff(np.sort(tcells, axis=1), axis=1) == 0, axis=1)))
        checks["periodic"].counts["cells_collapsed_on_torus"] = collapsed
        ttable = facet_table(tcells, n)
    else:
        checks["periodic"] = Check("periodic", True, "skipped: mesh.periodic is False", skipped=True)
        ttable = table

    if microstructure is None:
        for name in ("interface", "labels"):
            checks[name] = Check(name, True, "skipped: no microstructure given", skipped=True)
    else:
        tol = 1e-6 * float(box.max()) if interface_tol is None else float(interface_tol)
        checks["interface"] = _interface(points, cells, ids, ttable, microstructure, tol)
        checks["labels"] = _labels(points, cells, ids, lmax, microstructure)

    at_boundary = None if getattr(mesh, "periodic", False) else (table.counts[table.cell_facet] == 1).any(axis=1)
    checks["connectivity"] = _connectivity(ids, ttable, microstructure, at_boundary)
    return ValidationReport({k: checks[k] for k in CHECKS})
