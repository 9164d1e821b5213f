"""km.fmm.laplace3d beside the direct sum and Flatiron's FMM3D (issue 23, "Speed").

    .venv/bin/python bench/fmm/fmm3d_bench.py --quick       # wiring check, N = 1e5 (~2 min)
    .venv/bin/python bench/fmm/fmm3d_bench.py               # crossover, eps sweep at N = 1e6
    .venv/bin/python bench/fmm/fmm3d_bench.py --large       # also N = 1e7 at eps 1e-6
    .venv/bin/python bench/fmm/fmm3d_bench.py --no-crossover --peer-eps 1e-3 1e-4 1e-6 1e-8 1e-9 --tries 1
                                            # the curve 1e-3 .. 1e-12 beside fmm3dpy (RESULTS.md)

Problem: N points uniform in the unit cube (seed 0), charges uniform in [-1, 1]; potential AND
gradient at the sources (self term left out), float64: km.fmm.laplace3d(gradient=True) and
fmm3dpy.lfmm3d(pg=2) (whose kernel carries 1/(4 pi), removed before comparing). Errors are
measured, never assumed: relative 2-norm errors of phi and grad against km.fmm.direct3d on a
fixed random subset of 1000 targets. Two builds of fmm3dpy 2.1.0 are run: "fmm3dpy", the PyPI
wheel, built without OpenMP (one core whatever the thread count), and "fmm3dpy-omp", the same
release's source (PyPI sdist) built by `bash scripts/setup.sh bench` with OpenMP and FMM3D's
own makefile flags (-O3 -march=native -funroll-loops -fopenmp, gfortran) into
.venv/peers/fmm3dpy_openmp, run with kinema's thread count (2 here). Every figure is recorded
with its wall and CPU seconds. Rows go to bench/out/fmm3d.csv through harness.measure
(repeated while other processes load the machine). The last line printed is the summary: the
best peer's time over kinema's at each of the peers' measured errors, wall and CPU.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402
import kinema as km  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "out"
TRIES = 2
EPS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12)


def problem(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((n, 3)), rng.uniform(-1.0, 1.0, n)


def reference(x, q, idx):
    return km.fmm.direct3d(x, q, x[idx], gradient=True)


def errors(phi, grad, ref, idx):
    e_phi = np.linalg.norm(phi[idx] - ref[0]) / np.linalg.norm(ref[0])
    e_grad = np.linalg.norm(grad[idx] - ref[1]) / np.linalg.norm(ref[1])
    return float(e_phi), float(e_grad)


def run_kinema(x, q, eps):
    return km.fmm.laplace3d(x, q, eps=eps, gradient=True)


OPENMP_PEER = HERE.parents[1] / ".venv" / "peers" / "fmm3dpy_openmp" / "fmm3dpy"


def openmp_peer():
    """fmm3dpy built from source with OpenMP (scripts/setup.sh bench), imported as fmm3dpy_openmp
    beside the wheel's fmm3dpy (its modules import each other relatively); None if not built."""
    if "fmm3dpy_openmp" in sys.modules:
        return sys.modules["fmm3dpy_openmp"]
    init = OPENMP_PEER / "__init__.py"
    if not init.exists():
        return None
    spec = importlib.util.spec_from_file_location("fmm3dpy_openmp", init,
                                                  submodule_search_locations=[str(OPENMP_PEER)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["fmm3dpy_openmp"] = module
    spec.loader.exec_module(module)
    return module


def lfmm3d(module, x, q, eps):
    out = module.lfmm3d(eps=eps, sources=np.ascontiguousarray(x.T), charges=q, pg=2)
    return out.pot * (4 * np.pi), out.grad.T * (4 * np.pi)


def run_fmm3d(x, q, eps):
    import fmm3dpy

    return lfmm3d(fmm3dpy, x, q, eps)


def run_fmm3d_omp(x, q, eps):
    return lfmm3d(openmp_peer(), x, q, eps)


PEERS = {"fmm3dpy": run_fmm3d, "fmm3dpy-omp": run_fmm3d_omp}


def sweep(rec, n, eps_list, peers, max_seconds, peer_eps=None):
    x, q = problem(n)
    idx = np.sort(np.random.default_rng(1).choice(n, min(n, 1000), replace=False))
    ref = reference(x, q, idx)
    rows = []
    for name, fn in [("kinema", run_kinema)] + [(p, PEERS[p]) for p in peers]:
        for eps in (peer_eps or eps_list) if name != "kinema" else eps_list:
            m = harness.measure(harness.with_cpu(lambda: fn(x, q, eps)), max_tries=TRIES, quiet_timeout=10)
            (phi, grad), cpu = m.value
            e_phi, e_grad = errors(phi, grad, ref, idx)
            threads = 1 if name == "fmm3dpy" else harness.default_threads()
            info = km.fmm.last_info() if name == "kinema" else {}
            rec.record(f"{name} eps={eps:g}", n, m.seconds, error=max(e_phi, e_grad), threads=threads,
                       measurement=m, notes={"err_phi": f"{e_phi:.2e}", "err_grad": f"{e_grad:.2e}",
                                             "cpu_s": f"{cpu:.2f}", "order": info.get("order", "")})
            rows.append((name, eps, m.seconds, cpu, e_phi, e_grad, m.other_load))
            print(f"{name:11s} N={n:.0e} eps={eps:.0e}: {m.seconds:8.2f} s (cpu {cpu:7.2f} s)  "
                  f"err phi {e_phi:.2e} grad {e_grad:.2e}  load {m.other_load:.2f}"
                  f"{' order ' + str(info['order']) if info else ''}", flush=True)
            if m.seconds > max_seconds:
                print(f"  ({name}: stopping the sweep, {m.seconds:.0f} s > {max_seconds:.0f} s)")
                break
    return rows


def crossover(rec):
    """FMM against the direct sum (both with all threads) for N = 1e3 .. 1e4 at eps 1e-6."""
    print("direct-sum crossover (eps 1e-6, phi and gradient):")
    found = None
    for n in (1000, 2000, 3000, 4000, 5000, 7000, 10000):
        x, q = problem(n)
        f = harness.measure(harness.with_cpu(lambda: km.fmm._eval3d(x, q, None, eps=1e-6, derivatives=1)),
                            min_of=3, max_tries=3 * TRIES, quiet_timeout=10)
        d = harness.measure(harness.with_cpu(lambda: km.fmm._eval3d(x, q, None, eps=1e-6, derivatives=1, direct=True)),
                            min_of=3, max_tries=3 * TRIES, quiet_timeout=10)
        fc, dc = f.value[1], d.value[1]
        rec.record("fmm crossover", n, f.seconds, measurement=f, notes={"cpu_s": f"{fc:.4f}"})
        rec.record("direct crossover", n, d.seconds, measurement=d, notes={"cpu_s": f"{dc:.4f}"})
        print(f"  N={n:6d}: fmm {f.seconds * 1e3:8.2f} ms (cpu {fc * 1e3:8.2f})  direct {d.seconds * 1e3:8.2f} ms "
              f"(cpu {dc * 1e3:8.2f})  load {f.other_load:.2f}/{d.other_load:.2f}", flush=True)
        if found is None and fc < dc:
            found = n
    print(f"  FMM faster from N = {found}" if found else "  FMM not faster up to N = 1e4")


def summary(rows):
    """kinema's wall and CPU seconds at each of the peers' measured errors (log-log interpolation
    over kinema's runs), the ratios peer / kinema, and the one-line summary: at each error the
    best (fastest) peer's ratio."""
    kin = sorted((max(r[4], r[5]), r[2], r[3]) for r in rows if r[0] == "kinema")
    peer = sorted(((max(r[4], r[5]), r[2], r[3], r[1], r[0]) for r in rows if r[0] != "kinema"), reverse=True)
    if not kin or not peer:
        return
    le = np.log([k[0] for k in kin])
    print("at equal measured error (max of phi and grad): peer / kinema in wall and CPU seconds")
    best = {}
    for err, wall, cpu, eps, name in peer:
        if not (le.min() <= math.log(err) <= le.max()):
            print(f"  {name} eps={eps:.0e} err {err:.1e}: outside kinema's measured range")
            continue
        kw, kc = (math.exp(np.interp(math.log(err), le, np.log([k[i] for k in kin]))) for i in (1, 2))
        print(f"  err {err:.1e}: {name:11s} wall {wall:8.2f} s cpu {cpu:8.2f} s | kinema wall {kw:7.2f} s "
              f"cpu {kc:7.2f} s | ratio wall {wall / kw:5.2f}x cpu {cpu / kc:5.2f}x")
        key = f"peer eps {eps:.0e} (err {err:.1e})"  # the two fmm3dpy builds: the same errors
        b = best.setdefault(key, [math.inf, "", math.inf, ""])
        if wall / kw < b[0]:
            b[0], b[1] = wall / kw, name
        if cpu / kc < b[2]:
            b[2], b[3] = cpu / kc, name
    print("SUMMARY best peer / kinema at equal error: " + "; ".join(
        f"{k}: wall {b[0]:.2f}x ({b[1]}), cpu {b[2]:.2f}x ({b[3]})" for k, b in best.items()))
    # The other way round: at each kinema run, the peers' cheapest run at least as accurate
    # (a peer's curve as a step function; fmm3dpy reaches no error above ~4e-5 at any eps).
    dual = []
    for err, wall, cpu in kin:
        ok = [r for r in peer if r[0] <= err]
        if ok:
            pw, pc = min(ok, key=lambda r: r[1]), min(ok, key=lambda r: r[2])
            dual.append(f"{err:.1e}: wall {pw[1] / wall:.2f}x ({pw[4]} eps {pw[3]:.0e}), "
                        f"cpu {pc[2] / cpu:.2f}x ({pc[4]} eps {pc[3]:.0e})")
    print("SUMMARY peers' cheapest run at least as accurate / kinema, per kinema run: " + "; ".join(dual))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--large", action="store_true")
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--peers", nargs="*", choices=sorted(PEERS),
                    help="peers to run (default: fmm3dpy, and fmm3dpy-omp when scripts/setup.sh bench built it)")
    ap.add_argument("--no-crossover", action="store_true")
    ap.add_argument("--size", type=float, default=1e6)
    ap.add_argument("--eps", type=float, nargs="*")
    ap.add_argument("--peer-eps", type=float, nargs="*",
                    help="fmm3dpy's eps values (default: --eps); its errors run 1-3 decades below eps, "
                         "so 1e-3 .. 1e-9 span kinema's 1e-3 .. 1e-12 curve")
    ap.add_argument("--max-seconds", type=float, default=300)
    ap.add_argument("--tries", type=int, default=2, help="timed calls per figure while the machine is loaded")
    args = ap.parse_args()
    global TRIES
    TRIES = args.tries
    rec = harness.Recorder(OUT / "fmm3d.csv", "fmm3d")
    print(f"commit {rec.commit}, threads {rec.threads}, load average {os.getloadavg()}")
    if not (args.quick or args.no_crossover):
        crossover(rec)
    n = int(1e5 if args.quick else args.size)
    eps_list = args.eps or ((1e-3, 1e-6, 1e-9) if args.quick else EPS)
    peers = [] if args.no_peer else args.peers if args.peers is not None else \
        ["fmm3dpy"] + (["fmm3dpy-omp"] if openmp_peer() is not None else [])
    if "fmm3dpy-omp" in peers and openmp_peer() is None:
        sys.exit(f"fmm3dpy-omp: not built ({OPENMP_PEER} missing): run `bash scripts/setup.sh bench`")
    print(f"peers: {', '.join(peers) or 'none'}")
    rows = sweep(rec, n, eps_list, peers, args.max_seconds, args.peer_eps)
    summary(rows)
    if args.large:
        sweep(rec, int(1e7), (1e-6,), [], 1e9)
    print(f"load average at the end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
