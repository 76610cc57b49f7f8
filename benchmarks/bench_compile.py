"""Cold-run JAX compilations of `jaxmesh mesh`: how many per kernel, and their seconds (not a test).

A user's first run, and every CI run, starts with no compilation cache; then each distinct shape of a
jitted kernel's arguments costs a trace, a lowering and an XLA compilation (seconds for the truss scan
and the Newton projection). This runs `jaxmesh mesh INPUT -o OUT ARGS` with the cache off
(JAXMESH_CACHE_DIR='') and JAX_LOG_COMPILES=1, and sums JAX's log lines per kernel.

Usage:
    python benchmarks/bench_compile.py INPUT [--checkout PATH ...] [-- MESH ARGS ...]

    --checkout PATH   also run another checkout's library (PYTHONPATH=PATH; e.g. a `git worktree` of an
                      older commit), one after the other in this run, to compare the two.
Example:
    git worktree add /tmp/old HEAD~3
    python benchmarks/bench_compile.py rve.npy --checkout /tmp/old -- --no-periodic
"""

from __future__ import annotations

import argparse
import collections
import datetime
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
LINE = re.compile(r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation of) (?:jit\()?([^ )]+)\)?"
                  r"(?: for jit)? in ([0-9.]+) sec")
PHASES = {"tracing": "trace", "jaxpr to MLIR module conversion": "lower", "XLA compilation of": "compile"}


def run(checkout: Path, input_path: str, mesh_args: list[str]) -> dict:
    """One cold `jaxmesh mesh` with checkout's library: wall seconds, exit code, and per kernel the
    number of XLA compilations and the seconds of each phase."""
    env = dict(os.environ, JAXMESH_CACHE_DIR="", JAX_LOG_COMPILES="1", PYTHONPATH=str(checkout))
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "jaxmesh._cli", "mesh", input_path, "-o", str(Path(tmp) / "out.vtu"), *mesh_args]
        start = time.perf_counter()
        proc = subprocess.run(cmd, env=env, cwd=checkout, capture_output=True, text=True)
        wall = time.perf_counter() - start
    kernels: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for line in proc.stderr.splitlines() + proc.stdout.splitlines():
        m = LINE.search(line)
        if m:
            phase, name, sec = PHASES[m.group(1)], m.group(2), float(m.group(3))
            kernels[name][phase] += sec
            kernels[name]["count"] += phase == "compile"
    summary = [line for line in proc.stdout.splitlines() if line.startswith("[jaxmesh]") or "quality:" in line]
    if proc.returncode:
        summary += proc.stderr.strip().splitlines()[-3:]
    return {"wall": wall, "rc": proc.returncode, "kernels": kernels, "summary": summary}


def report(label: str, result: dict, top: int) -> None:
    kernels = result["kernels"]
    total = collections.Counter()
    for c in kernels.values():
        total.update(c)
    print(f"\n## {label}: rc {result['rc']}, wall {result['wall']:.1f} s; {int(total['count'])} XLA compilations, "
          f"trace {total['trace']:.1f} s, lower {total['lower']:.1f} s, compile {total['compile']:.1f} s")
    for line in result["summary"]:
        print("   ", line.strip())
    print("| kernel | compilations | trace + lower + compile (s) |\n| --- | ---: | ---: |")
    by_time = sorted(kernels.items(), key=lambda kv: -(kv[1]["trace"] + kv[1]["lower"] + kv[1]["compile"]))
    for name, c in by_time[:top]:
        print(f"| {name} | {int(c['count'])} | {c['trace'] + c['lower'] + c['compile']:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input")
    parser.add_argument("--checkout", action="append", default=[], help="another checkout to run as well")
    parser.add_argument("--top", type=int, default=10, help="kernels listed per run")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args, mesh_args = parser.parse_args(argv[:cut]), argv[cut + 1:]  # after --: jaxmesh mesh's own
    input_path = str(Path(args.input).resolve())
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True).stdout
    print(f"# cold-run compilations, {datetime.date.today()}, {platform.machine()}, {os.cpu_count()} CPUs; "
          f"jaxmesh mesh {args.input} {' '.join(mesh_args)}")
    for checkout in [HERE, *map(Path, args.checkout)]:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=checkout, capture_output=True, text=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=checkout,
                               capture_output=True, text=True).stdout.strip()
        label = f"{checkout} at {rev.stdout.strip() or commit.strip()}{' + changes' if dirty else ''}"
        report(label, run(checkout, input_path, mesh_args), args.top)


if __name__ == "__main__":
    main()
