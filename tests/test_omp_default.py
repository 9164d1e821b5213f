"""kinema's default OpenMP waiting policy (python/kinema/__init__.py): a bounded spin set before
the OpenMP runtime starts when the user set none, and the user's own setting left alone. The
speed it buys on a loaded machine is measured in bench/common/omp_wait_policy.py (bench/RESULTS.md),
not here. Each case runs in a fresh interpreter: the runtime reads its environment once."""

import json
import os
import subprocess
import sys

import pytest

PROBE = """
import json, os
import kinema as km
maps = open("/proc/self/maps").read()
print(json.dumps({"GOMP_SPINCOUNT": os.environ.get("GOMP_SPINCOUNT"),
                  "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
                  "wait": km.build_info()["openmp_wait"],
                  "libgomp": "libgomp" in maps}))
"""


def probe(**env):
    base = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    base.update(env)
    out = subprocess.run([sys.executable, "-c", PROBE], env=base, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_default_spin_count_is_set_before_the_runtime_starts():
    import kinema as km

    r = probe()
    assert r["libgomp"]  # the runtime that reads GOMP_SPINCOUNT is the one in use
    assert r["GOMP_SPINCOUNT"] == km.DEFAULT_GOMP_SPINCOUNT and r["OMP_WAIT_POLICY"] is None
    assert "kinema default" in r["wait"]


@pytest.mark.parametrize("env", [{"OMP_WAIT_POLICY": "passive"}, {"OMP_WAIT_POLICY": "active"},
                                 {"GOMP_SPINCOUNT": "5"}, {"GOMP_SPINCOUNT": "infinite"}])
def test_a_users_own_setting_is_respected(env):
    r = probe(**env)
    for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY"):
        assert r[k] == env.get(k)  # nothing added, nothing changed
    assert "set by the user" in r["wait"]
