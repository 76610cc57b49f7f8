"""Reading inputs and writing meshes."""
