#!/usr/bin/env bash
# Creates the environment if needed, then runs the default test suite (extra pytest args pass through).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
cd "$JAXMESH_ROOT"
export JAXMESH_SMOKE=1
exec python -m pytest -q "$@"
