"""Gradients of mass-spring cloth runs (km.diff): backward against forward time, stored and
checkpointed, peak memory; and the time per gradient side by side with Taichi (ti.ad.Tape) and
NVIDIA Warp (wp.Tape) on the CPU at equal agreement with finite differences.

Parts (one command runs them all, in one process plus one subprocess per peer and per memory
figure; CSV rows in bench/out/diff_massspring.csv):
- implicit: the 129 x 129-vertex cloth of bench/deform_bench.py (Taichi's layout: structural
  and shear springs, k = 1000, c = 0.5, unit masses, gravity (0, -2), two corners pinned),
  T implicit steps of dt = 0.01 with kinema's default solver (PCG with a lagged CHOLMOD factor),
  from rest (no step clamps: checked); loss L = sum_i w_i . x_i(T), gradient wrt v0 and
  stiffness.
  Times: T plain steps; km.diff.rollout (forward with recording) and backward, with every state
  stored and with K = 2 sqrt(T) checkpoints; checkpointed gradient = stored (bitwise is
  checked); peak memory of each, measured in a fresh process (tracemalloc's peak of the
  NumPy memory km.diff holds: the recorded states), also in units of one state. The directional derivative
  along a random direction is checked against the central difference of the direct-solve
  forward run (h = 1e-5) before any time is recorded (they differ by the forward's PCG
  tolerance: the default run's trajectory is the direct one's to about cg_tol = 1e-8 per step).
- peers: the same cloth (from rest) and loss, symplectic Euler at dt = 0.005 for --peer-steps steps,
  float64 on the CPU: kinema (rollout + backward), Taichi 1.7 (ti.ad.Tape over time-indexed
  fields, the DiffTaichi pattern) and Warp (wp.Tape over per-step arrays, the pattern of its
  cloth_throw example), bench/deform/diff_massspring_peers.py. Each directional derivative is compared
  with the same finite difference (kinema's forward, h = 1e-5) and with each other.
- step_ab (with --old DIR): the 129^2 implicit forward step of an older kinema build (a
  directory holding its installed `kinema` package) against this one, alternated in rounds.

    .venv/bin/python bench/deform/diff_massspring_bench.py [--steps 100] [--peer-steps 100] [--old DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "common"))  # harness.py
import harness  # noqa: E402

OUT = HERE.parent / "out"


def cloth(N, km):
    x, springs, kinds = km.massspring.cloth(N + 1, N + 1, 0.5, dim=2, return_kinds=True)
    x += 0.25
    NV = (N + 1) ** 2
    return km.massspring.System(x, springs[kinds < 2], stiffness=1000.0, damping=0.5, mass=1.0,
                                gravity=(0.0, -2.0), fixed=[N, NV - 1])


def problem(N, km, seed=0):
    """The cloth at rest with a random initial velocity, the loss weights and a direction."""
    sys_ = cloth(N, km)
    rng = np.random.default_rng(seed)
    free = np.ones(len(sys_.x))
    free[[N, (N + 1) ** 2 - 1]] = 0
    sys_.v = 0.1 * rng.standard_normal(sys_.x.shape) * free[:, None]
    w = rng.standard_normal(sys_.x.shape)
    direction = rng.standard_normal(sys_.x.shape) * free[:, None]
    return sys_, w, direction


def loss_of(sys_, v0, steps, dt, w, **options):
    start = sys_.state()
    sys_.v = v0
    for _ in range(steps):
        sys_.step(dt, **options)
    value = float(np.sum(w * sys_.x))
    sys_.set_state(start)
    return value


def fd(sys_, steps, dt, w, direction, h=1e-5, **options):
    v0 = sys_.v.copy()
    return (loss_of(sys_, v0 + h * direction, steps, dt, w, **options) -
            loss_of(sys_, v0 - h * direction, steps, dt, w, **options)) / (2 * h)


def measure(fn, opts):
    return harness.measure(fn, min_of=opts.min_of, max_load=opts.max_load, max_tries=opts.max_tries,
                           quiet_timeout=opts.quiet_timeout)


# ---------------------------------------------------------------- implicit: backward / forward

def memory_child(args):
    """In a fresh process: the peak of the memory km.diff holds during one rollout + backward.
    What grows with the run's length is the recorded states, NumPy copies that tracemalloc
    traces; the solver's own buffers (CHOLMOD factor, scratch) do not depend on T."""
    import tracemalloc

    import kinema as km
    N, steps, dt, K = args.N, args.steps, 0.01, args.memory_child
    sys_, w, _ = problem(N, km)
    sys_.v = 0.0
    sys_.step(dt)  # CHOLMOD analysis and first factor, as in a run
    state_bytes = sum(np.asarray(v).nbytes for v in sys_.state().values())  # with factor_x
    tracemalloc.start()
    run = km.diff.rollout(sys_, steps, dt, wrt=("v",), checkpoints=None if K == 0 else K)
    run.backward({"x": w})
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(json.dumps({"peak_bytes": peak, "state_bytes": state_bytes,
                      "peak_states": run.peak_states}), flush=True)


def memory(opts, K):
    out = subprocess.run([sys.executable, __file__, "--memory-child", str(K), "--N", str(opts.N),
                          "--steps", str(opts.steps)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_implicit(rec, opts):
    import kinema as km
    N, T, dt = opts.N, opts.steps, 0.01
    K = int(round(2 * np.sqrt(T)))
    size = f"{N + 1}x{N + 1}"
    sys_, w, direction = problem(N, km)
    # From rest: a random initial velocity field compresses springs past the definiteness of
    # the exact Jacobian, the steps clamp (StepStats.clamped) and the loss is then only
    # piecewise smooth, which no finite difference can check. The run must not clamp.
    sys_.v = 0.0
    start = sys_.state()
    clamped = sum(sys_.step(dt).clamped for _ in range(T))
    assert clamped == 0, f"{clamped} of the {T} implicit steps clamped; the gradient check needs none"
    sys_.set_state(start)
    wrt = ("v", "stiffness")
    # Check first: the gradient against finite differences of the exact-solve forward run.
    run = km.diff.rollout(sys_, T, dt, wrt=wrt)
    g_stored = run.backward({"x": w})
    ad = float(np.sum(g_stored["v"] * direction))
    sys_.set_state(start)
    ref = fd(sys_, T, dt, w, direction, linear_solver="cholmod_direct")
    fd_err = abs(ad - ref) / abs(ref)
    print(f"implicit {size}, T = {T}: dL/dv0 . d = {ad:.10e}, finite difference {ref:.10e}, "
          f"relative difference {fd_err:.1e}", flush=True)
    assert fd_err < 1e-5, f"implicit gradient disagrees with finite differences by {fd_err:.1e}"
    sys_.set_state(start)
    run_k = km.diff.rollout(sys_, T, dt, wrt=wrt, checkpoints=K)
    g_k = run_k.backward({"x": w})
    same = all(np.array_equal(g_k[n], g_stored[n]) for n in wrt)
    print(f"checkpointed (K = {K}) = stored bit for bit: {same}", flush=True)
    assert same, "checkpointed gradients differ from the stored ones"

    def plain():
        sys_.set_state(start)
        for _ in range(T):
            sys_.step(dt)
    m_fwd = measure(plain, opts)
    rows = {}
    for label, checkpoints in (("stored", None), (f"K={K}", K)):
        holder = {}

        def forward():
            sys_.set_state(start)
            holder["run"] = km.diff.rollout(sys_, T, dt, wrt=wrt, checkpoints=checkpoints)

        def backward():
            holder["run"].backward({"x": w})

        m_roll = measure(forward, opts)
        forward()
        m_back = measure(backward, opts)
        mem = memory(opts, 0 if checkpoints is None else checkpoints)
        rows[label] = (m_roll, m_back, mem)
        rec.record(f"kinema_implicit_rollout_{label}", size, m_roll.seconds, measurement=m_roll,
                   notes={"steps": T, "plain_forward": f"{m_fwd.seconds:.4f}"})
        rec.record(f"kinema_implicit_backward_{label}", size, m_back.seconds, measurement=m_back,
                   error=fd_err, notes={"steps": T, "backward_over_forward": f"{m_back.seconds / m_fwd.seconds:.3f}",
                                        "peak_bytes": mem["peak_bytes"], "state_bytes": mem["state_bytes"],
                                        "peak_states": mem["peak_states"]})
        print(f"{label:>7}: rollout {m_roll.seconds:.3f} s, backward {m_back.seconds:.3f} s "
              f"= {m_back.seconds / m_fwd.seconds:.2f} x the plain forward {m_fwd.seconds:.3f} s "
              f"(rollout + backward {(m_roll.seconds + m_back.seconds) / m_fwd.seconds:.2f} x); peak memory "
              f"{mem['peak_bytes'] / 2**20:.1f} MiB = {mem['peak_bytes'] / mem['state_bytes']:.1f} states of "
              f"{mem['state_bytes'] / 2**20:.2f} MiB (km.diff held at most {mem['peak_states']}); load "
              f"{max(m_roll.other_load, m_back.other_load):.2f}", flush=True)
    rec.record("kinema_implicit_forward", size, m_fwd.seconds, measurement=m_fwd, notes={"steps": T})
    return rows


# ---------------------------------------------------------------- peers: time per gradient

def bench_peers(rec, opts):
    import kinema as km
    N, T, dt = opts.N, opts.peer_steps, 0.005
    size = f"{N + 1}x{N + 1}"
    sys_, w, direction = problem(N, km)
    sys_.v = 0.0  # as the peers: from rest, smooth enough for the finite difference to check
    assert dt < sys_.explicit_dt_limit, (dt, sys_.explicit_dt_limit)
    start = sys_.state()
    ref = fd(sys_, T, dt, w, direction, integrator="symplectic")
    results = {}

    def kinema_gradient():
        sys_.set_state(start)
        run = km.diff.rollout(sys_, T, dt, wrt=("v",), integrator="symplectic")
        return run.backward({"x": w})["v"]
    g = kinema_gradient()
    m = measure(kinema_gradient, opts)
    cpu = []
    for _ in range(opts.min_of):
        c = time.process_time()
        kinema_gradient()
        cpu.append(time.process_time() - c)
    results["kinema"] = {"seconds": m.seconds, "cpu_seconds": min(cpu), "directional": float(np.sum(g * direction)),
                         "threads": harness.default_threads(), "load": m.other_load}
    for peer in ("taichi", "warp"):
        cmd = [sys.executable, str(HERE / "diff_massspring_peers.py"), peer, str(N), str(T), str(dt),
               "--threads", str(harness.default_threads())]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{peer}: failed ({done.stderr.strip().splitlines()[-1] if done.stderr else done.returncode})")
            continue
        results[peer] = json.loads(done.stdout.strip().splitlines()[-1])
    base = results["kinema"]["seconds"]
    for name, r in results.items():
        err = abs(r["directional"] - ref) / abs(ref)
        rec.record(f"{name}_symplectic_gradient", size, r["seconds"], error=err,
                   threads=r["threads"], measurement=m if name == "kinema" else None,
                   notes={"steps": T, "dt": dt, "vs_kinema": f"{r['seconds'] / base:.2f}",
                          "cpu_seconds": f"{r['cpu_seconds']:.4f}"})
        print(f"{name:>7}: {r['seconds'] * 1e3:8.1f} ms per gradient ({T} symplectic steps, {size}, "
              f"{r['threads']} thread(s)), {r['seconds'] / base:5.2f} x kinema; CPU time "
              f"{r['cpu_seconds'] * 1e3:8.1f} ms, {r['cpu_seconds'] / results['kinema']['cpu_seconds']:5.2f} x "
              f"kinema's; directional derivative {r['directional']:.12e}, vs finite difference {err:.1e}",
              flush=True)
    summary = ", ".join(f"{name} / kinema = {r['seconds'] / base:.2f}x" for name, r in results.items()
                        if name != "kinema")
    errors = ", ".join(f"{name} {abs(r['directional'] - ref) / abs(ref):.1e}" for name, r in results.items())
    print(f"summary: time per gradient of {T} symplectic steps ({size}): {summary} (target >= 3x); "
          f"FD agreement {errors}", flush=True)
    # kinema's implicit gradient of the same number of steps, for reference (other integrator).
    def implicit_gradient():
        sys_.set_state(start)
        run = km.diff.rollout(sys_, T, 0.01, wrt=("v",))
        return run.backward({"x": w})["v"]
    m_i = measure(implicit_gradient, opts)
    rec.record("kinema_implicit_gradient", size, m_i.seconds, measurement=m_i, notes={"steps": T, "dt": 0.01})
    print(f"kinema implicit (dt = 0.01, {T} steps): {m_i.seconds * 1e3:.1f} ms per gradient", flush=True)
    return results


# ---------------------------------------------------------------- step_ab: old build vs this one

STEP_CHILD = """
import sys, time, json
sys.path.insert(0, {path!r}) if {path!r} else None
import numpy as np
sys.path.insert(0, {here!r})
sys.path.insert(0, {common!r})
import harness
import kinema as km
from diff_massspring_bench import cloth
s = cloth({N}, km)
for _ in range(5):
    s.step(0.01)
def k_steps():
    for _ in range({k}):
        s.step(0.01)
m = harness.measure(k_steps, min_of={min_of}, max_load={max_load}, max_tries={max_tries},
                    quiet_timeout={quiet_timeout})
print(json.dumps({{"seconds": m.seconds / {k}, "load": m.other_load, "x": float(np.abs(s.x).sum()),
                   "file": km.__file__}}))
"""


def bench_step_ab(rec, opts):
    size = f"{opts.N + 1}x{opts.N + 1}"
    best = {}
    for _ in range(opts.rounds):
        for label, path in (("old", opts.old), ("new", "")):
            code = STEP_CHILD.format(path=path, here=str(HERE), common=str(HERE.parent / "common"), N=opts.N, k=opts.ab_steps, min_of=opts.min_of,
                                     max_load=opts.max_load, max_tries=opts.max_tries,
                                     quiet_timeout=opts.quiet_timeout)
            r = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                          check=True).stdout.strip().splitlines()[-1])
            if label not in best or r["seconds"] < best[label]["seconds"]:
                best[label] = r
    assert best["old"]["x"] == best["new"]["x"], "the two builds' cloths differ after the same steps"
    ratio = best["new"]["seconds"] / best["old"]["seconds"]
    for label in ("old", "new"):
        rec.record(f"kinema_implicit_cloth_step_{label}", size, best[label]["seconds"],
                   notes={"steps": opts.ab_steps, "rounds": opts.rounds, "load": f"{best[label]['load']:.2f}"})
    print(f"cloth {size} implicit step: old build {best['old']['seconds'] * 1e3:.2f} ms, this build "
          f"{best['new']['seconds'] * 1e3:.2f} ms (new / old = {ratio:.3f}; best of {opts.rounds} alternated "
          f"rounds; results bitwise equal)", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--N", type=int, default=128, help="cloth of (N+1)^2 vertices")
    p.add_argument("--steps", type=int, default=100, help="implicit steps T")
    p.add_argument("--peer-steps", type=int, default=100)
    p.add_argument("--only", choices=["implicit", "peers", "step_ab"])
    p.add_argument("--old", help="directory holding an older build's installed kinema package (step_ab)")
    p.add_argument("--ab-steps", type=int, default=30)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--min-of", type=int, default=3)
    p.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD)
    p.add_argument("--max-tries", type=int, default=6)
    p.add_argument("--quiet-timeout", type=float, default=harness.DEFAULT_QUIET_TIMEOUT)
    p.add_argument("--memory-child", type=int, help=argparse.SUPPRESS)
    p.add_argument("--out", default=str(OUT / "diff_massspring.csv"))
    opts = p.parse_args(argv)
    if opts.memory_child is not None:
        return memory_child(opts)
    rec = harness.Recorder(opts.out, "diff_massspring")
    print(f"threads {harness.default_threads()}, commit {rec.commit}", flush=True)
    if opts.only in (None, "implicit"):
        bench_implicit(rec, opts)
    if opts.only in (None, "peers"):
        bench_peers(rec, opts)
    if opts.only in (None, "step_ab") and opts.old:
        bench_step_ab(rec, opts)


if __name__ == "__main__":
    main()
