"""Implicit geometry: level-set grids as JAX functions, differential geometry, microstructures."""
