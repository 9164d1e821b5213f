"""km.fmm beside the direct sum and Flatiron's FMM2D (issue 6, "Speed, side by side").

    .venv/bin/python bench/fmm/fmm_bench.py --quick        # wiring check, N <= 1e5 (~1-2 min)
    .venv/bin/python bench/fmm/fmm_bench.py                # N = 1e3 .. 1e6, eps sweep at N = 1e6
    .venv/bin/python bench/fmm/fmm_bench.py --large        # also N = 1e7
    .venv/bin/python bench/fmm/fmm_bench.py --no-peer      # kinema and direct2d only

Problem: N points uniform in the unit square (seed 0), charges uniform in [-1, 1]; potential
AND gradient at the sources themselves (self term left out), in float64, by
km.fmm.laplace2d(gradient=True) and by FMM2D's rfmm2d(pg=2) at the same thread count.
Errors are measured, never assumed: the relative 2-norm errors of phi and of the gradient
against km.fmm.direct2d on a fixed random subset of targets (all of them for N <= 5e3).
FMM2D's error is usually far below the eps it is given, so the two are compared at equal
MEASURED error: the eps sweep (``--wp-size``, default 1e6) gives each code a time-against-error
curve, and the summary interpolates kinema's time (log-log) at each of FMM2D's errors.

The peer runs in its own virtual environment (bench/out/venv-fmm2d, numpy<2 and fmm2dpy,
created on first use; fmm2dpy's only release is built for numpy 1.x) through
bench/fmm/fmm2d_worker.py as a subprocess; its figure is the time of the rfmm2d call itself
(timed inside the worker, without start-up and I/O).

Every call goes through harness.measure (repeated when other processes loaded the machine) and
into bench/out/fmm.csv; plots: bench/out/fmm_scaling.png, bench/out/fmm_work_precision.png.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "out"
PEER_VENV = OUT / "venv-fmm2d"
WORKER = HERE / "fmm2d_worker.py"

KINEMA_EPS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)
PEER_EPS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)


def problem(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((n, 2)), rng.uniform(-1.0, 1.0, n)


def subset_of(n, size, seed=1):
    if n <= max(size, 5000):
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size, replace=False))


def errors(phi, grad, ref):
    phi_ref, grad_ref = ref
    e_phi = np.linalg.norm(phi - phi_ref) / np.linalg.norm(phi_ref)
    e_grad = np.linalg.norm(grad - grad_ref) / np.linalg.norm(grad_ref)
    return float(e_phi), float(e_grad)


# ------------------------------------------------------------------ the peer


def peer_python() -> Path:
    """The python of the FMM2D environment, created with numpy<2 and fmm2dpy when missing."""
    python = PEER_VENV / "bin" / "python"
    ok = python.exists() and subprocess.run([str(python), "-c", "import fmm2dpy"],
                                            capture_output=True).returncode == 0
    if not ok:
        print(f"[fmm_bench] creating {PEER_VENV} (numpy<2, fmm2dpy)", flush=True)
        subprocess.run([sys.executable, "-m", "venv", str(PEER_VENV)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", "numpy<2", "fmm2dpy"], check=True)
    return python


class Peer:
    """FMM2D's rfmm2d on one problem, through the worker subprocess."""

    def __init__(self, python, x, q, subset, threads):
        self.python = python
        self.dir = tempfile.TemporaryDirectory(prefix="fmm2d_", dir=OUT)
        folder = Path(self.dir.name)
        np.save(folder / "sources.npy", x)
        np.save(folder / "charges.npy", q)
        np.save(folder / "subset.npy", subset)
        self.env = dict(os.environ, OMP_NUM_THREADS=str(threads))

    def run(self, eps):
        text = f"{eps:.0e}"
        done = subprocess.run([str(self.python), str(WORKER), self.dir.name, text], env=self.env,
                              capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"fmm2d worker failed: {done.stderr[-2000:]}")
        report = json.loads(done.stdout.strip().splitlines()[-1])
        data = np.load(Path(self.dir.name) / f"fmm2d_{text}.npz")
        return report["seconds"], data["pot"], data["grad"]


# ------------------------------------------------------------------ runs


def timing(args):
    return dict(min_of=args.min_of, max_load=args.max_load, max_tries=args.max_tries,
                quiet_timeout=5.0 if args.max_tries <= 1 else harness.DEFAULT_QUIET_TIMEOUT)


def run_size(km, rec, n, eps_list, peer_eps, args, python, direct=False):
    x, q = problem(n)
    subset = subset_of(n, args.check)
    ref = km.fmm.direct2d(x, q, x[subset], gradient=True)
    rows = []
    for eps in eps_list:
        m = harness.measure(lambda: km.fmm.laplace2d(x, q, eps=eps, gradient=True), **timing(args))
        phi, grad = m.value
        e_phi, e_grad = errors(phi[subset], grad[subset], ref)
        info = km.fmm.last_info()
        rec.record("kinema", n, m.seconds, error=e_phi, measurement=m,
                   notes={"eps": eps, "grad_error": e_grad, "order": info["order"],
                          "leaf_size": info["leaf_size"], "checked": len(subset)})
        rows.append(("kinema", eps, m.seconds, e_phi, e_grad, m.other_load))
        print(f"  kinema  N={n:>8} eps={eps:.0e} p={info['order']:>3} {m.seconds:9.4f} s  "
              f"err phi {e_phi:.2e} grad {e_grad:.2e}  load {m.other_load:.2f}", flush=True)
    if python is not None:
        peer = Peer(python, x, q, subset, args.threads)
        for eps in peer_eps:
            m = harness.measure(lambda: peer.run(eps), figure=lambda value, wall: value[0],
                                **timing(args))
            _, pot, grad = m.value
            e_phi, e_grad = errors(pot, grad, ref)
            rec.record("fmm2d", n, m.seconds, error=e_phi, measurement=m,
                       notes={"eps": eps, "grad_error": e_grad, "checked": len(subset)})
            rows.append(("fmm2d", eps, m.seconds, e_phi, e_grad, m.other_load))
            print(f"  fmm2d   N={n:>8} eps={eps:.0e}       {m.seconds:9.4f} s  "
                  f"err phi {e_phi:.2e} grad {e_grad:.2e}  load {m.other_load:.2f}", flush=True)
        peer.dir.cleanup()
    if direct:
        m = harness.measure(lambda: km.fmm.direct2d(x, q, gradient=True), **timing(args))
        rec.record("direct2d", n, m.seconds, measurement=m)
        rows.append(("direct2d", 0.0, m.seconds, 0.0, 0.0, m.other_load))
        print(f"  direct2d N={n:>8}                {m.seconds:9.4f} s  load {m.other_load:.2f}", flush=True)
    return rows


def crossover(scaling):
    """Smallest N at which the FMM is faster than direct2d (log-log interpolation)."""
    fmm = {n: s for n, method, s in scaling if method == "kinema"}
    direct = {n: s for n, method, s in scaling if method == "direct2d"}
    ns = sorted(set(fmm) & set(direct))
    for a, b in zip(ns, ns[1:]):
        ra, rb = np.log(fmm[a] / direct[a]), np.log(fmm[b] / direct[b])
        if ra > 0 >= rb:
            return float(np.exp(np.log(a) + (np.log(b) - np.log(a)) * ra / (ra - rb)))
    if ns and fmm[ns[0]] < direct[ns[0]]:
        return float(ns[0])
    return None


def equal_error_table(rows):
    """kinema's time interpolated at each of FMM2D's measured errors: (error, t_fmm2d, t_kinema)."""
    ours = sorted((e, s) for method, _, s, e, _, _ in rows if method == "kinema")
    out = []
    for method, eps, s, e, _, _ in rows:
        if method != "fmm2d":
            continue
        le = np.log([p[0] for p in ours])
        lt = np.log([p[1] for p in ours])
        if not (le.min() <= np.log(e) <= le.max()):
            out.append((eps, e, s, None))
            continue
        # kinema's curve at error e: the fastest of its runs at least as accurate (a running
        # minimum from the accurate end), interpolated log-log between its points.
        order = np.argsort(le)
        envelope = np.minimum.accumulate(lt[order])
        t = float(np.exp(np.interp(np.log(e), le[order], envelope)))
        out.append((eps, e, s, t))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="N <= 1e5, short sweeps")
    parser.add_argument("--large", action="store_true", help="also N = 1e7 (needs ~6 GiB)")
    parser.add_argument("--no-peer", action="store_true", help="leave FMM2D out")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--eps", type=float, default=1e-6, help="eps of the time-vs-N runs")
    parser.add_argument("--wp-size", type=int, default=None, help="N of the eps sweep (default 1e6)")
    parser.add_argument("--direct-max", type=int, default=30_000, help="largest N for direct2d")
    parser.add_argument("--check", type=int, default=1000, help="targets checked against direct2d")
    parser.add_argument("--min-of", type=int, default=1)
    parser.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD,
                        help="other processes' load [cores] above which a run is repeated")
    parser.add_argument("--max-tries", type=int, default=harness.DEFAULT_MAX_TRIES)
    parser.add_argument("--csv", type=Path, default=OUT / "fmm.csv")
    args = parser.parse_args(argv)

    import kinema as km

    km.set_num_threads(args.threads)
    python = None if args.no_peer else peer_python()
    sizes = [1_000, 3_000, 10_000, 30_000, 100_000] if args.quick else \
        [1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000]
    if args.large:
        sizes.append(10_000_000)
    wp_size = args.wp_size or (100_000 if args.quick else 1_000_000)
    eps_sweep = (1e-3, 1e-6, 1e-9, 1e-12) if args.quick else KINEMA_EPS
    peer_sweep = (1e-3, 1e-6, 1e-9, 1e-12) if args.quick else PEER_EPS
    print(f"[fmm_bench] threads {args.threads}, commit {harness.git_commit()}", flush=True)

    rec = harness.Recorder(args.csv, benchmark="fmm2d_scaling", threads=args.threads)
    scaling = []
    print(f"== time against N (eps = {args.eps:g}, potential + gradient)")
    for n in sizes:
        rows = run_size(km, rec, n, [args.eps], [args.eps], args, python, direct=n <= args.direct_max)
        scaling += [(n, method, s) for method, _, s, _, _, _ in rows]
    n_cross = crossover(scaling)
    print(f"crossover with direct2d: N ~ {n_cross:.0f}" if n_cross else "crossover: not in range")

    rec_wp = harness.Recorder(args.csv, benchmark=f"fmm2d_precision", threads=args.threads)
    print(f"== time against eps and measured error at N = {wp_size}")
    rows = run_size(km, rec_wp, wp_size, eps_sweep, peer_sweep if python else [], args, python)
    if python:
        print("== at equal measured error (phi): FMM2D's eps, its error, its time, kinema's "
              "interpolated time, ratio")
        for eps, e, t_peer, t_ours in equal_error_table(rows):
            ratio = "   n/a" if t_ours is None else f"{t_peer / t_ours:6.2f}x"
            ours = "   outside kinema's range" if t_ours is None else f"{t_ours:9.4f} s"
            print(f"  eps {eps:.0e}  error {e:.2e}  fmm2d {t_peer:9.4f} s  kinema {ours}  {ratio}")

    try:
        harness.plot_work_precision(args.csv, OUT / "fmm_work_precision.png",
                                    benchmark="fmm2d_precision", size=str(wp_size),
                                    title=f"2D Laplace FMM, N = {wp_size}, phi + gradient")
        plot_scaling(args.csv, OUT / "fmm_scaling.png")
    except Exception as exc:  # plotting is a convenience; the CSV is the record
        print(f"[fmm_bench] plot skipped: {exc}")
    print(f"[fmm_bench] rows in {args.csv}")


def plot_scaling(csv_path, png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in harness.read_rows(csv_path) if r["benchmark"] == "fmm2d_scaling"]
    fig, ax = plt.subplots(figsize=(7, 5))
    for method in sorted({r["method"] for r in rows}):
        pts = sorted((int(r["size"]), float(r["seconds"])) for r in rows if r["method"] == method)
        ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", label=method)
    ns = np.array(sorted({int(r["size"]) for r in rows}), dtype=float)
    if len(ns):
        ax.loglog(ns, ns / ns[-1] * max(float(r["seconds"]) for r in rows if r["method"] == "kinema"),
                  "k:", label="O(N)")
    ax.set_xlabel("N (sources = targets)")
    ax.set_ylabel("wall time [s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title(f"2D Laplace FMM, potential + gradient, commit {harness.git_commit()}", fontsize="medium")
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
