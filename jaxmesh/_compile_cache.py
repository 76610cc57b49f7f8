"""A persistent cache of XLA compilations for the command line (and for notebooks that ask).

Most of jaxmesh's kernels compile in well under JAX's default 1 s threshold for caching, yet
together they take ~12 s of a 40-inclusion run (benchmarks/README.md): cached, a second run skips it.
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "JAXMESH_CACHE_DIR"


def default_cache_dir() -> Path | None:
    """$JAXMESH_CACHE_DIR (set but empty: no cache), else $XDG_CACHE_HOME/jaxmesh/xla or ~/.cache/jaxmesh/xla."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return Path(value).expanduser() if value.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxmesh" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> str | None:
    """Keep every XLA compilation in `path` (default `default_cache_dir()`), so later processes reuse it.

    Call it before the first jitted call of the process. Returns the folder, or None when caching is
    off (JAXMESH_CACHE_DIR set to '') or the folder cannot be created (then nothing changes).
    """
    import jax

    target = Path(path).expanduser() if path is not None else default_cache_dir()
    if target is None:
        return None
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(target))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return str(target)
