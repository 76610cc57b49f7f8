import gc
import os

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAXMESH_SMOKE", "1")
os.environ.setdefault("JAXMESH_CACHE_DIR", "")  # no persistent compilation cache: tests stay hermetic

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


# Each compiled kernel keeps a few memory mappings; one process running the whole suite compiles
# enough of them to reach Linux's default limit of 65,530 mappings (vm.max_map_count), where XLA's
# compiler segfaults. One test module adds up to ~30,000.
_MAPPINGS_BEFORE_CLEARING = 20_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


# A module that starts just under the threshold above can still cross the limit on its own (seen: a
# fresh-clone CI run segfaulted in test_nonperiodic after test modules were added before it), so
# single tests clear too once the process is this close to it.
_MAPPINGS_BEFORE_CLEARING_IN_A_MODULE = 40_000


def _release():
    jax.clear_caches()
    gc.collect()


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_kernels():
    """After a test module, drop the compiled kernels when the process holds many mappings (the
    next modules then compile theirs again: clearing after every module made the suite markedly slower)."""
    yield
    if _mappings() > _MAPPINGS_BEFORE_CLEARING:
        _release()


@pytest.fixture(autouse=True)
def _release_compiled_kernels_near_the_limit():
    """After a test, drop the compiled kernels when the process is near vm.max_map_count."""
    yield
    if _mappings() > _MAPPINGS_BEFORE_CLEARING_IN_A_MODULE:
        _release()
