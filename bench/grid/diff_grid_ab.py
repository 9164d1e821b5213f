"""A/B of the km.grid gradient's backward over forward between two builds of kinema, in one run:
rounds alternate a baseline build (e.g. main's wheel unpacked in a directory) and the installed
one, each running bench/grid/diff_grid_cpu.py (1-thread CPU time) or diff_grid_bench.py (wall
time); per case the best ratio of the rounds of each, so a loaded machine disturbs both alike.

    # main's wheel, once: pip wheel --no-deps -w /tmp/main-dist <checkout of main>; then unpack it
    .venv/bin/python -m zipfile -e /tmp/main-dist/kinema-*.whl /tmp/main-kinema
    .venv/bin/python bench/grid/diff_grid_ab.py --baseline /tmp/main-kinema --rounds 3 \\
        -- bench/grid/diff_grid_cpu.py --dims 3 --schemes maccormack bfecc --reps 2
    .venv/bin/python bench/grid/diff_grid_ab.py --baseline /tmp/main-kinema --rounds 3 \\
        -- bench/grid/diff_grid_bench.py --threads 2 --dims 3 --no-per-gradient

Prints every round's SUMMARY line and one A/B SUMMARY line: per case, baseline -> this build.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# the cases of a SUMMARY line: diff_grid_cpu's "3D maccormack 2.73/3.02", diff_grid_bench's
# "3D 64^3 maccormack bwd/fwd 3.09 stored, 3.14 checkpointed"
CASES = (re.compile(r"(\d)D (\w+) (\d+\.\d+)/(\d+\.\d+)"),
         re.compile(r"(\d)D \S+ (\w+) bwd/fwd (\d+\.\d+) stored, (\d+\.\d+) checkpointed"))


def run(script_args, baseline):
    env = dict(os.environ)
    if baseline:
        env["PYTHONPATH"] = str(baseline) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    out = subprocess.run([sys.executable, *script_args], cwd=ROOT, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(script_args)} failed ({'baseline' if baseline else 'this build'}):\n"
                         f"{out.stderr[-2000:]}")
    lines = [line for line in out.stdout.splitlines() if line.startswith("SUMMARY")]
    if not lines:
        raise SystemExit(f"no SUMMARY line in the output of {' '.join(script_args)}:\n{out.stdout[-2000:]}")
    summary = lines[-1]
    body = summary.split(":", 1)[1]
    cases = {f"{d}D {name}": (float(a), float(b)) for case in CASES for d, name, a, b in case.findall(body)}
    return summary, cases


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, type=Path,
                    help="a directory holding the baseline's kinema package (put first on PYTHONPATH)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("script", nargs=argparse.REMAINDER, help="-- the bench script and its arguments")
    opts = ap.parse_args()
    script = [a for a in opts.script if a != "--"]
    if not script:
        raise SystemExit("script: give the bench script after --")
    if not (opts.baseline / "kinema" / "__init__.py").exists():
        raise SystemExit(f"baseline: no kinema package in {opts.baseline}")
    best = {"baseline": {}, "this": {}}
    for r in range(opts.rounds):
        for name, path in (("baseline", opts.baseline), ("this", None)):
            summary, cases = run(script, path)
            print(f"round {r + 1} {name}: {summary}", flush=True)
            for case, (a, b) in cases.items():
                old = best[name].get(case, (float("inf"), float("inf")))
                best[name][case] = (min(old[0], a), min(old[1], b))
    parts = [f"{case} {a0:.2f}/{b0:.2f} -> {best['this'][case][0]:.2f}/{best['this'][case][1]:.2f}"
             for case, (a0, b0) in best["baseline"].items() if case in best["this"]]
    print(f"SUMMARY A/B (best of {opts.rounds} rounds, backward/forward stored/checkpointed, baseline -> this "
          f"build; {' '.join(script)}): " + "; ".join(parts), flush=True)


if __name__ == "__main__":
    main()
