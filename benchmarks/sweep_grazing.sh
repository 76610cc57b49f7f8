#!/usr/bin/env bash
# Robustness sweep (not a test): RVEs whose inclusions may cross or graze the box anywhere
# (--box-gap 0), meshed with the CLI defaults. Prints one line per input: exit status, time,
# tets, mean q, min dihedral, how many tets stay below 10 deg and how many of those have a node on
# the box, and the validator's verdict. SUMMARY_ONLY=1 re-reads the meshes of an earlier run;
# MESH_ARGS adds options to `jaxmesh mesh` (e.g. MESH_ARGS="--roll auto"; MESH_ARGS="--roll 0 0 0" keeps
# the frame as given, which the defaults roll when its box grazes an interface).
#   bash benchmarks/sweep_grazing.sh [OUT_DIR] [SEEDS...]      (default: /tmp/jaxmesh_grazing, seeds 0-3)
set -u
here="$(cd "$(dirname "$0")/.." && pwd)"
jaxmesh="$here/.venv/bin/jaxmesh"
python="$here/.venv/bin/python"
out="${1:-/tmp/jaxmesh_grazing}"
shift || true
seeds="${*:-0 1 2 3}"
mkdir -p "$out"
echo "# $(date -u +%F\ %T) UTC, $(nproc) cores, commit $(git -C "$here" rev-parse --short HEAD)$(git -C "$here" diff --quiet HEAD -- jaxmesh || echo +modified), mesh options: ${MESH_ARGS:-none}"
for kind in sphere ellipsoid; do
  for seed in $seeds; do
    name="$out/${kind}_$seed"
    if [ "${SUMMARY_ONLY:-0}" = 1 ]; then
      rc=$(test -f "$name.vtu" && echo 0 || echo 1); secs="-"
    else
    "$jaxmesh" generate "$name.npz" --dim 3 --kind "$kind" --n 30 --volume-fraction 0.35 --radius 0.09 \
      --radius-std 0.02 --min-gap 0.02 --box-gap 0 --grid 64 --seed "$seed" > "$name.gen.log" 2>&1 || {
      echo "${kind} seed $seed: generate failed: $(tail -1 "$name.gen.log")"; continue; }
    start=$(date +%s)
    # shellcheck disable=SC2086  # MESH_ARGS holds several words
    "$jaxmesh" mesh "$name.npz" -o "$name.vtu" --report "$name.json" ${MESH_ARGS:-} > "$name.mesh.log" 2>&1
    rc=$?
    secs=$(( $(date +%s) - start ))
    fi
    if [ $rc -eq 0 ] || [ -f "$name.json" ]; then
      summary=$("$python" -c "
import json, sys
import meshio, numpy as np
from jaxmesh._quality import dihedral_angles
r = json.load(open(sys.argv[1])); q = r['quality']; v = r['metadata']['validation']
m = meshio.read(sys.argv[2]); p, t = m.points, m.cells_dict['tetra']
low = t[dihedral_angles(p, t).min(axis=1) < 10.0]
on_box = np.any((np.abs(p) < 1e-9) | (np.abs(p - 1.0) < 1e-9), axis=1)  # the unit box
print(f\"{q['n_cells']} tets, mean q {q['q_mean']:.3f}, {100 * q['frac_below']:.3f} % below 0.3, \"
      f\"min dihedral {q['min_dihedral_deg']:.1f} deg ({len(low)} below 10, {on_box[low].any(axis=1).sum()} of \"
      f\"them with a box node), {'valid' if v['ok'] else 'INVALID'}\")" "$name.json" "$name.vtu")
    else
      summary=$(tail -1 "$name.mesh.log" | cut -c1-240)
    fi
    echo "${kind} seed $seed: rc $rc, ${secs} s: $summary"
  done
done
