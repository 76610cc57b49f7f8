#!/usr/bin/env bash
# Source me: finds a Python 3.12, creates .venv (once), installs jaxmesh editable with dev extras.
set -euo pipefail
JAXMESH_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${JAXMESH_VENV:-$JAXMESH_ROOT/.venv}"

find_python312() {
    local candidates=()
    [ -n "${JAXMESH_PYTHON:-}" ] && candidates+=("$JAXMESH_PYTHON")
    candidates+=(python3.12)
    if command -v pyenv >/dev/null 2>&1; then
        local v
        for v in $(pyenv versions --bare 2>/dev/null | grep -E '^3\.12(\.[0-9]+)?$' | sort -V -r); do
            candidates+=("$(pyenv root)/versions/$v/bin/python3.12")
        done
    fi
    candidates+=("$HOME"/.pyenv/versions/3.12*/bin/python3.12 /root/.pyenv/versions/3.12*/bin/python3.12
                 /usr/local/bin/python3.12 /usr/bin/python3.12 /opt/python*/bin/python3.12 python3)
    local c
    for c in "${candidates[@]}"; do
        # print the real executable: a pyenv shim only works with PYENV_VERSION set
        if "$c" -c 'import sys, venv; sys.exit(0 if sys.version_info[:2] == (3, 12) else 1)' >/dev/null 2>&1; then
            "$c" -c 'import sys; print(sys.executable)'
            return 0
        fi
    done
    return 1
}

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 12) else 1)' 2>/dev/null; then
    if ! PY="$(PYENV_VERSION=3.12.1 find_python312)"; then
        echo "jaxmesh needs Python 3.12 (3.11 only gets jax 0.10.2, whose jaxlib crashes in optimistix gradients)." >&2
        echo "None found. Install one (e.g. 'pyenv install 3.12' or 'apt-get install python3.12-venv')," >&2
        echo "or point JAXMESH_PYTHON at a python3.12 executable." >&2
        exit 1
    fi
    echo "[jaxmesh] creating $VENV with $PY"
    rm -rf "$VENV"
    "$PY" -m venv "$VENV"
fi

stamp="$VENV/.jaxmesh-installed"
if [ ! -f "$stamp" ] || [ "$JAXMESH_ROOT/pyproject.toml" -nt "$stamp" ]; then
    echo "[jaxmesh] installing jaxmesh (editable) and its dependencies into $VENV"
    "$VENV/bin/python" -m pip install --quiet --upgrade pip
    "$VENV/bin/python" -m pip install --quiet -e "$JAXMESH_ROOT[dev]"
    touch "$stamp"
fi
export PATH="$VENV/bin:$PATH"
