"""The before/after tools in bench/: the result comparison of shape_compare.py and the line
counts of line_counts.py (their timings are benchmarks, not tests)."""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from load_script import load_script

BENCH = Path(__file__).resolve().parents[1] / "bench"


def load(name):
    return load_script(BENCH / f"{name}.py")


def test_shape_compare_reports_bitwise_and_relative_differences(tmp_path):
    sc = load("shape_compare")
    x = np.linspace(-2.0, 4.0, 7)
    np.savez(tmp_path / "a.npz", x=x, v=np.ones(3))
    np.savez(tmp_path / "b.npz", x=x.copy(), v=np.ones(3))
    assert sc.compare(tmp_path / "a.npz", tmp_path / "b.npz") == (True, 0.0, "")
    y = x.copy()
    y[2] += 1e-9
    np.savez(tmp_path / "c.npz", x=y, v=np.ones(3))
    same, rel, where = sc.compare(tmp_path / "a.npz", tmp_path / "c.npz")
    assert not same and where == "x" and rel == pytest.approx(1e-9 / 4.0, rel=1e-6)
    np.savez(tmp_path / "d.npz", x=x)
    assert sc.compare(tmp_path / "a.npz", tmp_path / "d.npz")[1] == float("inf")


def test_shape_compare_workloads_cover_every_method():
    sc = load("shape_compare")
    methods = {name.split("_")[0] for name in sc.WORKLOADS}
    assert methods == {"sph", "grid", "poisson", "massspring", "fem", "mpm", "fmm"}


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_line_counts_match_wc_at_head(capsys):
    root = BENCH.parent
    if subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    lc = load("line_counts")
    rows = lc.counts("HEAD")
    tracked = subprocess.run(["git", "-C", str(root), "show", "HEAD:python/kinema/sph.py"], capture_output=True,
                             text=True, check=True).stdout
    assert rows["sph"][2] == tracked.count("\n") > 0
    assert lc.main(["HEAD"]) == 0 and "| sph |" in capsys.readouterr().out
