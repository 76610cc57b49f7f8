#!/usr/bin/env bash
# Creates the environment if needed, then runs the main job on built-in examples, writing into ./out:
#   a 3D RVE (random spheres, periodic, with a guaranteed gap) generated and inspected, and
#   a 2D RVE (random ellipses) generated, meshed periodically, validated, with a JSON report and a PNG.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
cd "$JAXMESH_ROOT"
mkdir -p out
jaxmesh generate out/rve3d.npz --dim 3 --kind sphere --n 60 --volume-fraction 0.30 --radius 0.09 --radius-std 0.02 \
    --min-gap 0.02 --grid 64 --seed 1
jaxmesh info out/rve3d.npz
jaxmesh generate out/rve2d.npz --dim 2 --kind ellipsoid --n 30 --volume-fraction 0.35 --radius 0.07 --radius-std 0.015 \
    --min-gap 0.02 --grid 256 --seed 1
jaxmesh mesh out/rve2d.npz -o out/rve2d.vtu --report out/rve2d.json --plot out/rve2d.png
jaxmesh validate out/rve2d.vtu --geometry out/rve2d.npz
echo "[jaxmesh] done: out/rve2d.vtu (open in ParaView), out/rve2d.json (quality + validation), out/rve2d.png"
