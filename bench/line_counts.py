"""Lines per method at a git revision: the method's C++ folder, its binding and its Python
module (and, apart, the shared C++ folders), as the before/after figures of a refactor.

    .venv/bin/python bench/line_counts.py [REV ...]     # default HEAD; several revisions side by side

`km.grid` lived in cpp/fluid/ and `km.poisson` in cpp/grid/ before the folders took their
modules' names; a revision that still has cpp/fluid/ is counted with that layout. Lines are
physical lines (as `wc -l`), blank and comment lines included.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("sph", "grid", "poisson", "diffusion", "sparse", "massspring", "fem", "mpm", "fmm", "contact")
SHARED = ("core", "linalg", "particles", "mesh", "render", "geometry")


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout


def counts(rev: str) -> dict:
    """{row: (cpp, binding, python)} line counts at `rev`."""
    files = git("ls-tree", "-r", "--name-only", rev).split()
    old_layout = any(f.startswith("cpp/fluid/") for f in files)
    folder = {m: m for m in METHODS}
    if old_layout:
        folder["grid"], folder["poisson"] = "fluid", "grid"

    def lines(paths) -> int:
        total = 0
        for p in paths:
            total += git("show", f"{rev}:{p}").count("\n")
        return total

    def under(prefix):
        return [f for f in files if f.startswith(prefix) and f.endswith((".h", ".hpp", ".cpp"))]

    rows = {}
    for m in METHODS:
        rows[m] = (lines(under(f"cpp/{folder[m]}/")),
                   lines([f for f in files if f == f"cpp/bindings/bind_{m}.cpp"]),
                   lines([f for f in files if f == f"python/kinema/{m}.py"]))
    for s in SHARED:
        rows[f"(shared) {s}"] = (lines(under(f"cpp/{s}/")), 0, 0)
    rows["(shared) bindings"] = (0, lines([f for f in files if f.startswith("cpp/bindings/")
                                           and not f.startswith("cpp/bindings/bind_")]), 0)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("revs", nargs="*", default=["HEAD"], help="git revisions (commits, branches, tags)")
    args = ap.parse_args(argv)
    try:
        table = {rev: counts(rev) for rev in args.revs}
    except subprocess.CalledProcessError as exc:
        print(f"git failed: {exc.stderr.strip()}", file=sys.stderr)
        return 2
    head = "| method | " + " | ".join(f"{r}: C++ + binding + Python = total" for r in args.revs) + " |"
    print(head)
    print("| --- |" + " --- |" * len(args.revs))
    for row in table[args.revs[0]]:
        cells = []
        for rev in args.revs:
            c, b, p = table[rev].get(row, (0, 0, 0))
            cells.append(f"{c} + {b} + {p} = {c + b + p}")
        print(f"| {row} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
