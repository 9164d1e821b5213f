"""Runs the API fuzz cases (cases.py), each in its own forked process, and classifies them.

Outcomes: ok (returned, every number finite), clean (ValueError or km.KinemaError, or a
TypeError from copying a simulation object), interrupted (a case sent SIGINT answered with
KeyboardInterrupt), raw (any other exception type: a traceback a user should not see),
nonfinite (returned a NaN or Inf without an error), wrong (a scenario's own check of the
answer failed), crash (the process died: signal or abort),
hang (no answer to the SIGINT sent at the case's interrupt time or at the time limit),
invalid_case (the case's own code failed before it reached kinema: a defect of the case).
An explicit step's stability warning (a RuntimeWarning that names the argument and the limit it
passes, e.g. "dt: ... exceeds cfl_dt()") is kinema saying so, not a failure: it is recorded in
the result's "warned" and the case runs on, judged by what it then returns or raises.

The parent imports kinema once and forks a child per case; it never runs kinema code itself, so
the children inherit no OpenMP thread pool. Usage:
    python tests/fuzz/runner.py [--all] [--json FILE] [--timeout S] [--match SUBSTRING]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import select
import signal
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cases as fuzz_cases  # noqa: E402

OUTCOMES = ("ok", "clean", "interrupted", "raw", "nonfinite", "wrong", "crash", "hang", "invalid_case")


def _nonfinite(value, depth=0):
    import numpy as np
    if depth > 4:
        return False
    if isinstance(value, (bool, int, str, bytes, type(None))):
        return False
    if isinstance(value, (float, complex, np.number)):
        return not np.isfinite(value)
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "fc" and not np.isfinite(value).all()
    if isinstance(value, dict):
        return any(_nonfinite(v, depth + 1) for v in value.values())
    if isinstance(value, (tuple, list)):
        return any(_nonfinite(v, depth + 1) for v in value[:1000])
    if hasattr(value, "__dataclass_fields__"):
        return any(_nonfinite(getattr(value, f), depth + 1) for f in value.__dataclass_fields__)
    if hasattr(value, "toarray") and hasattr(value, "data"):  # scipy sparse
        return _nonfinite(value.data, depth + 1)
    return False


def _run_child(case, fd):
    """In the child: runs the case, writes one JSON line to fd, exits."""
    import warnings
    warnings.simplefilter("error")
    # the bad values themselves (an array times 1e308) overflow while the case builds them;
    # what kinema returns from such input is judged by its result
    warnings.filterwarnings("ignore", category=RuntimeWarning, message="(overflow|invalid value)")
    result = {"outcome": None, "type": None, "message": None}
    stability = r"\w+: .*(stability limit|explicit_dt_limit|cfl_dt\(\))"
    warnings.filterwarnings("always", category=RuntimeWarning, message=stability)

    def record(message, category, filename, lineno, file=None, line=None):
        result.setdefault("warned", []).append(str(message)[:200])
    warnings.showwarning = record
    try:
        env = {}
        exec(case["setup"], env)
        exec(case["expr"].rpartition(";")[0] if ";" in case["expr"] else "", env)
        value = eval(case["expr"].rpartition(";")[2].strip(), env)
        result["outcome"] = "nonfinite" if _nonfinite(value) else "ok"
    except KeyboardInterrupt:
        result.update(outcome="interrupted", type="KeyboardInterrupt")
    except BaseException as exc:  # noqa: BLE001 - classifying every exception is the point
        import kinema
        name = type(exc).__name__
        clean = isinstance(exc, (ValueError, kinema.KinemaError)) or (
            isinstance(exc, TypeError) and "cannot be copied" in str(exc))
        if isinstance(exc, AssertionError):
            clean = False
        frames = traceback.extract_tb(exc.__traceback__)
        inside = any(f"{os.sep}kinema{os.sep}" in f.filename for f in frames) or "kinema" in str(exc)
        if isinstance(exc, AssertionError):
            outcome = "wrong"  # a scenario's check of kinema's answer failed
        else:
            outcome = "clean" if clean else "raw" if inside else "invalid_case"
        result.update(outcome=outcome, type=name, message=str(exc)[:300])
        if not clean:
            result["traceback"] = traceback.format_exc()[-1500:]
    os.write(fd, (json.dumps(result) + "\n").encode())
    os._exit(0)


def run_case(case, timeout):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            _run_child(case, w)
        finally:
            os._exit(3)
    os.close(w)
    start = time.monotonic()
    deadline = start + timeout + 2.0
    # A case still running at its interrupt time (or at the time limit) is sent SIGINT and must
    # answer with KeyboardInterrupt within 2 s: long runs are allowed when Ctrl-C stops them.
    sigint_at = start + (case["interrupt"] or timeout)
    sent_sigint = None
    data = b""
    while True:
        now = time.monotonic()
        if sigint_at and not sent_sigint and now >= sigint_at:
            os.kill(pid, signal.SIGINT)
            sent_sigint = now
            deadline = min(deadline, now + 2.0)  # Ctrl-C must be answered within ~2 s
        wait = deadline - now
        if sigint_at and not sent_sigint:
            wait = min(wait, sigint_at - now)
        if wait <= 0:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(r)
            what = "no answer to SIGINT" if sent_sigint else f"no answer in {timeout} s"
            return {"outcome": "hang", "type": None, "message": what, "seconds": time.monotonic() - start}
        ready, _, _ = select.select([r], [], [], wait)
        if ready:
            chunk = os.read(r, 65536)
            if not chunk:
                break
            data += chunk
    os.close(r)
    _, status = os.waitpid(pid, 0)
    seconds = time.monotonic() - start
    try:
        result = json.loads(data.decode().splitlines()[0])
    except (IndexError, ValueError):
        how = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
        return {"outcome": "crash", "type": None, "message": how, "seconds": seconds}
    result["seconds"] = seconds
    return result


def run(selected, timeout, log=None):
    import numpy  # noqa: F401 - imported before forking so that children start fast
    import scipy.sparse  # noqa: F401
    import kinema  # noqa: F401
    if any("torch" in case["expr"] for case in selected):
        try:  # the torch bridge's cases: a 2-3 s import, done once here, not in every child
            import torch  # noqa: F401
        except ImportError:
            pass
    results = {}
    for case in selected:
        res = run_case(case, timeout)
        results[case["id"]] = res
        if log:
            print(f"{res['outcome']:12s} {res['seconds']:6.2f}s {case['id']}  {res.get('type') or ''}"
                  f" {(res.get('message') or '')[:120]}", file=log, flush=True)
    return results


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--all", action="store_true", help="every case (default: the fast subset)")
    p.add_argument("--json", help="write the per-case results to this file")
    p.add_argument("--timeout", type=float, default=20.0, help="seconds per case")
    p.add_argument("--match", default="", help="only cases whose id contains this")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    selected = [c for c in fuzz_cases.cases() if (a.all or c["fast"]) and a.match in c["id"]]
    results = run(selected, a.timeout, None if a.quiet else sys.stdout)
    counts = collections.Counter(r["outcome"] for r in results.values())
    summary = {o: counts.get(o, 0) for o in OUTCOMES}
    print(json.dumps({"cases": len(selected), **summary}))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"summary": summary, "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
