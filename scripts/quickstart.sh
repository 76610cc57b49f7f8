#!/usr/bin/env bash
# Creates the environment if needed, then runs the main job on built-in examples, writing into ./out:
#   a 3D RVE (random spheres, periodic, guaranteed gap) generated and meshed: out/rve3d.vtu + .json report + .png,
#   a 2D RVE (random ellipses) generated and meshed the same way: out/rve2d.vtu + .json + .png.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
cd "$JAXMESH_ROOT"
mkdir -p out
jaxmesh generate out/rve3d.npz --dim 3 --kind sphere --n 6 --radius 0.14 --radius-std 0.02 --min-gap 0.05 \
    --grid 48 --seed 2
jaxmesh info out/rve3d.npz
jaxmesh mesh out/rve3d.npz -o out/rve3d.vtu --iis 0.08 --report out/rve3d.json --plot out/rve3d.png
jaxmesh validate out/rve3d.vtu --geometry out/rve3d.npz
jaxmesh generate out/rve2d.npz --dim 2 --kind ellipsoid --n 30 --volume-fraction 0.35 --radius 0.07 \
    --radius-std 0.015 --min-gap 0.02 --grid 256 --seed 1
jaxmesh mesh out/rve2d.npz -o out/rve2d.vtu --report out/rve2d.json --plot out/rve2d.png
jaxmesh validate out/rve2d.vtu --geometry out/rve2d.npz
echo "[jaxmesh] done: out/rve3d.vtu and out/rve2d.vtu (ParaView), .json reports (quality + validation), .png pictures"
