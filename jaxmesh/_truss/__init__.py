"""The truss engine (paper 3.2, 4.4, 4.7): energies, constraints and the relaxation driver.

Shared by the surface, face, volume and 2D meshers. JAX kernels live in ``_energy`` and
``_constraints``, the NumPy topology in ``_topology`` (never imports jax), the driver in ``_relax``.
"""

from ._constraints import NodeConstraints as NodeConstraints
from ._constraints import average_periodic as average_periodic
from ._constraints import filter_forces as filter_forces
from ._constraints import impose_periodicity as impose_periodicity
from ._constraints import make_constraints as make_constraints
from ._constraints import project_to_surface as project_to_surface
from ._constraints import truss_step as truss_step
from ._energy import alpha_schedule as alpha_schedule
from ._energy import ball_vertex_energy as ball_vertex_energy
from ._energy import bar_energy as bar_energy
from ._energy import bar_force as bar_force
from ._energy import bar_lengths as bar_lengths
from ._energy import phi_and_grad as phi_and_grad
from ._energy import safe_norm as safe_norm
from ._energy import surface_reaction_energy as surface_reaction_energy
from ._energy import target_lengths as target_lengths
from ._energy import tet_quality as tet_quality
from ._energy import truss_energy as truss_energy
from ._energy import truss_forces as truss_forces
from ._relax import RelaxResult as RelaxResult
from ._relax import TrussConfig as TrussConfig
from ._relax import relax as relax
from ._relax import relax_fixed_topology as relax_fixed_topology
from ._topology import bucket_capacity as bucket_capacity
from ._topology import edges_from_simplices as edges_from_simplices
from ._topology import pad_rows as pad_rows
