"""jaxmesh: periodic, conforming, differentiable meshes of implicit microstructures."""

from ._compile_cache import enable_compilation_cache as enable_compilation_cache
from ._errors import MeshingError as MeshingError
from ._generate import InclusionSpec as InclusionSpec
from ._generate import excursion_set as excursion_set
from ._generate import microstructure_from_specs as microstructure_from_specs
from ._generate import random_inclusions as random_inclusions
from ._generate import sample_levelset as sample_levelset
from ._generate import write_input as write_input
from ._homogenize import homogenize_conductivity as homogenize_conductivity
from ._mesh import Mesh as Mesh
from ._mesh import make_periodic_pairs as make_periodic_pairs
from ._mesh2d import mesh_2d as mesh_2d
from ._pipeline import MeshConfig as MeshConfig
from ._pipeline import mesh_rve as mesh_rve
from ._plot import plot_mesh as plot_mesh
from ._plot import plot_quality_histogram as plot_quality_histogram
from ._quality import cell_quality as cell_quality
from ._quality import dihedral_angles as dihedral_angles
from ._quality import min_angles as min_angles
from ._quality import quality_report as quality_report
from ._sizing import SizeField as SizeField
from ._sizing import SizeParams as SizeParams
from ._sizing import size_function as size_function
from ._surface_mesh import SurfaceMesh as SurfaceMesh
from ._truss import NodeConstraints as NodeConstraints
from ._truss import TrussConfig as TrussConfig
from ._truss import make_constraints as make_constraints
from ._truss import relax as relax
from ._truss import relax_fixed_topology as relax_fixed_topology
from ._validate import ValidationReport as ValidationReport
from ._validate import validate as validate
from .geometry import LevelSetGrid as LevelSetGrid
from .geometry import curvatures as curvatures
from .geometry import grid_phi_fn as grid_phi_fn
from .geometry import interpolate as interpolate
from .geometry import make_levelset_grid as make_levelset_grid
from .geometry import unit_normal as unit_normal
from .geometry._microstructure import Inclusion as Inclusion
from .geometry._microstructure import Microstructure as Microstructure
from .geometry._shapes import ellipsoid_sdf as ellipsoid_sdf
from .geometry._shapes import sphere_sdf as sphere_sdf
from .io import read_mesh as read_mesh
from .io import write_mesh as write_mesh
from .io._read import load_input as load_input

__version__ = "0.1.0"
