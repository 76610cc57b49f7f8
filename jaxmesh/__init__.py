"""jaxmesh: periodic, conforming, differentiable meshes of implicit microstructures."""

from ._errors import MeshingError as MeshingError

__version__ = "0.1.0"
