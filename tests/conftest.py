import os

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAXMESH_SMOKE", "1")
os.environ.setdefault("JAXMESH_CACHE_DIR", "")  # no persistent compilation cache: tests stay hermetic

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
