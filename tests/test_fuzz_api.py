"""The API fuzz harness (tests/fuzz/) as a test family: bad and edge calls across the public
API, each in its own forked process, must end as ok (finite result), a clean ValueError or
km.KinemaError, or KeyboardInterrupt when Ctrl-C is sent; never as a crash, a hang, a raw
exception type or a silent NaN/Inf. The fast subset runs by default; the whole set is slow."""

import json
import os
import subprocess
import sys

import pytest

RUNNER = os.path.join(os.path.dirname(__file__), "fuzz", "runner.py")
BAD = ("raw", "nonfinite", "wrong", "crash", "hang", "invalid_case")


def _run(tmp_path, *args):
    out = tmp_path / "fuzz.json"
    # two OpenMP threads per case: the cases are small, and the machine runs them one at a time
    env = dict(os.environ, OMP_NUM_THREADS="2")
    r = subprocess.run([sys.executable, RUNNER, "--quiet", "--json", str(out), *args], env=env,
                       capture_output=True, text=True, timeout=3000)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads(out.read_text())
    bad = {cid: res for cid, res in data["results"].items() if res["outcome"] in BAD}
    report = "\n".join(f"{res['outcome']}: {cid}: {res.get('type')} {res.get('message')}"
                       for cid, res in sorted(bad.items()))
    return data, report


def test_fuzz_fast_subset(tmp_path):
    data, report = _run(tmp_path)
    assert sum(data["summary"].values()) > 200
    assert not report, report


@pytest.mark.slow
def test_fuzz_all_cases(tmp_path):
    data, report = _run(tmp_path, "--all")
    assert sum(data["summary"].values()) > 1000
    assert not report, report
