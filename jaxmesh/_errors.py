"""Errors raised by jaxmesh."""


class MeshingError(RuntimeError):
    """A meshing stage failed on valid input.

    Carries the stage name and, where it applies, the inclusion id, so that a user
    can tell which part of a large RVE caused the failure. frame_dependent=False marks a
    cause that moving the box planes cannot remove (mesh_rve then skips its rolled retry);
    redistance_helps=True one that a first-order signed distance of the field removes (mesh_rve then
    meshes a level set as given once more redistanced); at_box_plane=True a volume recovery stopped where
    an interface grazes a box plane (mesh_rve then meshes a plain-box level set once more with the
    layers along its planes closed).
    """

    def __init__(self, stage: str, message: str, inclusion: int | None = None, *, frame_dependent: bool = True,
                 redistance_helps: bool = False, at_box_plane: bool = False):
        self.stage = stage
        self.inclusion = inclusion
        self.message = message
        self.frame_dependent = frame_dependent
        self.redistance_helps = redistance_helps
        self.at_box_plane = at_box_plane
        where = f"stage '{stage}'" + (f", inclusion {inclusion}" if inclusion is not None else "")
        super().__init__(f"{where}: {message}")
