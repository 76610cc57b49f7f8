"""Reading inputs and writing meshes."""

from ._read import load_input as load_input
from ._read_mesh import read_mesh as read_mesh
from ._write import write_mesh as write_mesh
