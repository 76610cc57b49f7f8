"""The closed periodic surface mesh handed from the surface stages to the volume stage.

NumPy only. Produced by the surface / box-face stages (paper 4.4-4.5), consumed by the volume stage (4.6):
every triangle here must appear unchanged in the tetrahedral mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

OUTSIDE = -1  # side id of the exterior of the box, for box-face triangles

INTERFACE, BOX_FACE = 0, 1


@dataclass(eq=False)
class SurfaceMesh:
    """Triangulated interfaces and box faces of a periodic RVE.

    Attributes:
        points: (n, 3) float64. Box-face nodes lie exactly on 0 or L; interface nodes on their level set.
        triangles: (t, 3) int64, oriented so that the right-hand normal points from ``sides[:, 0]`` to ``sides[:, 1]``.
        sides: (t, 2) int64 region ids on each side: inclusion id k > 0, matrix 0, OUTSIDE (-1) beyond the box.
            Interface triangles: (k, 0) (normal points out of inclusion k). Box-face triangles: (region, OUTSIDE).
        kind: (t,) int8, INTERFACE or BOX_FACE.
        node_inclusion: (n,) int64, the inclusion whose zero level set a node lies on (0: none, e.g. plain box nodes).
        box: box lengths.
        periodic_pairs: axis -> (k, 2) int64 (node on the 0-face, its exact translate on the L-face).
        metadata: counts, timings, parameters.
        periodic: opposite faces are translates (periodic_pairs cover them); False: a plain box,
            each face meshed on its own, no pairs.
    """

    points: np.ndarray
    triangles: np.ndarray
    sides: np.ndarray
    kind: np.ndarray
    node_inclusion: np.ndarray
    box: tuple[float, ...]
    periodic_pairs: dict[int, np.ndarray] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    periodic: bool = True

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        self.triangles = np.asarray(self.triangles, dtype=np.int64)
        self.sides = np.asarray(self.sides, dtype=np.int64)
        self.kind = np.asarray(self.kind, dtype=np.int8)
        self.node_inclusion = np.asarray(self.node_inclusion, dtype=np.int64)
        self.box = tuple(float(v) for v in self.box)
        n, t = len(self.points), len(self.triangles)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points: expected shape (n, 3), got {self.points.shape}")
        if self.triangles.shape != (t, 3) or self.sides.shape != (t, 2) or self.kind.shape != (t,):
            raise ValueError(
                f"triangles (t,3), sides (t,2), kind (t,) must agree: got {self.triangles.shape}, "
                f"{self.sides.shape}, {self.kind.shape}"
            )
        if self.node_inclusion.shape != (n,):
            raise ValueError(f"node_inclusion: expected shape ({n},), got {self.node_inclusion.shape}")
        if t and (self.triangles.min() < 0 or self.triangles.max() >= n):
            raise ValueError("triangles index points out of range")

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def interface_triangles(self) -> np.ndarray:
        return self.triangles[self.kind == INTERFACE]
