"""Implicit geometry: level-set grids as JAX functions, differential geometry, microstructures."""

from ._differential import Curvatures as Curvatures
from ._differential import curvatures as curvatures
from ._differential import gradient as gradient
from ._differential import hessian as hessian
from ._differential import max_abs_curvature as max_abs_curvature
from ._differential import unit_normal as unit_normal
from ._grid import LevelSetGrid as LevelSetGrid
from ._grid import bspline_coefficients as bspline_coefficients
from ._grid import grid_phi_fn as grid_phi_fn
from ._grid import interpolate as interpolate
from ._grid import interpolate_cubic as interpolate_cubic
from ._grid import interpolate_linear as interpolate_linear
from ._grid import make_levelset_grid as make_levelset_grid
from ._microstructure import Inclusion as Inclusion
from ._microstructure import Microstructure as Microstructure
