"""Backward over forward of the km.grid smoke-control gradient in CPU time on one thread: the
figure bench/grid/diff_grid_bench.py measures in wall time, but robust to a loaded machine
(other processes inflate wall time, not this process's CPU time, as long as it runs on one
thread). Same task (diff_grid_bench.task): forward = T plain steps; backward = km.diff's
backward after a rollout with every state stored and with K = 2 sqrt(T) checkpoints
(recomputation included); FD agreement as there.

    .venv/bin/python bench/grid/diff_grid_cpu.py [--quick] [--dims 3] [--schemes maccormack bfecc] [--reps 3]
    .venv/bin/python bench/grid/diff_grid_cpu.py --dims 3 --schemes maccormack bfecc --ab 3
    .venv/bin/python bench/grid/diff_grid_cpu.py --per-gradient [--sizes 64 128 256]

Prints one line per case and a SUMMARY line. --ab R: per case, R rounds alternating the adjoint
without and with the forward's kept advection scratch (the A/B of that change, in one process). --per-gradient: instead, the CPU time of one
gradient (rollout stored + backward, best of 3) of the Taichi comparison's task (2D
semi-Lagrangian RK1, T = 16) at pressure tolerances 1e-10 to 1e-3 and with the fixed projection
of 1, 2 and 4 V-cycles (pressure_vcycles), each with its FD agreement, the mean number of
iterations per projection and the divergence it leaves (mean pressure.residual).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diff_grid_bench import TOL, kinema_fluid, task  # noqa: E402


def setup(shape, steps, advection, rk, tol, vcycles=None):
    """The task's fluid, its initial state, the loss of a control sequence, and the task."""
    h, dt, rho0, controls, weights, direction = task(shape, steps)
    sim = kinema_fluid(shape, h, rho0, advection, rk, tol, vcycles)
    s0 = sim.state()

    def loss(c):
        sim.set_state(s0)
        for k in range(steps):
            sim._diff_step(dt, c[k], {})
        return float(np.sum(weights * sim.density))

    return sim, s0, loss, dt, controls, weights, direction


def recompute(sim):
    """sim's adjoint without the forward's kept advection scratch: every adjoint step recomputes
    MacCormack's or BFECC's first passes (the code before they were kept; the same bits)."""
    sim._diff_step_keep = None
    sim._diff_record = lambda dt, steps, controls, options: km.grid._Record(
        sim, sim._core.record(dt, int(steps), controls, False))


def case(shape, steps, advection, rk, tol=TOL, kept=True, reps=1):
    sim, s0, loss, dt, controls, weights, direction = setup(shape, steps, advection, rk, tol)
    if not kept:
        recompute(sim)

    def cpu(fn, reps=1):
        best = float("inf")
        for _ in range(reps):
            t = time.process_time()
            fn()
            best = min(best, time.process_time() - t)
        return best

    forward = cpu(lambda: loss(controls), reps)
    e = 1e-5
    fd = (loss(controls + e * direction) - loss(controls - e * direction)) / (2 * e)
    out = {"forward": forward}
    for name, ck in (("stored", None), ("checkpointed", int(2 * np.sqrt(steps)))):
        box, rollouts, backward = {}, [], float("inf")
        for _ in range(reps):  # a fresh rollout per backward: a checkpointed one spends its spine
            sim.set_state(s0)
            t = time.process_time()
            run = km.diff.rollout(sim, steps, dt, wrt=("controls",), controls=controls, checkpoints=ck)
            rollouts.append(time.process_time() - t)
            backward = min(backward, cpu(lambda: box.update(g=run.backward({"density": weights})["controls"])))
        out[name + " rollout"] = min(rollouts)
        err = abs(float(np.sum(box["g"] * direction)) - fd) / abs(fd)
        out[name] = backward / forward
        out[name + " backward"] = backward
        print(f"{len(shape)}D {'x'.join(map(str, shape))} {advection} rk{rk} T={steps} {name:12s}"
              f"{'' if kept else ' (recomputed)'}: CPU rollout {out[name + ' rollout']:.3f} s, forward "
              f"{forward:.3f} s, backward {backward:.3f} s, backward/forward {backward / forward:.2f}, "
              f"|adj - FD|/|FD| {err:.1e}", flush=True)
    return out


def per_gradient(n, tol, steps=16, vcycles=None):
    sim, s0, loss, dt, controls, weights, direction = setup((n, n), steps, "semi_lagrangian", 1, tol, vcycles)
    e = 1e-5
    fd = (loss(controls + e * direction) - loss(controls - e * direction)) / (2 * e)
    best, g = float("inf"), None
    for _ in range(3):
        t = time.process_time()
        sim.set_state(s0)
        g = km.diff.rollout(sim, steps, dt, wrt=("controls",), controls=controls).backward({"density": weights})
        best = min(best, time.process_time() - t)
    err = abs(float(np.sum(g["controls"] * direction)) - fd) / abs(fd)
    sim.set_state(s0)
    stats = [sim._core.step(dt, controls[k]).pressure for k in range(steps)]
    name = f"{vcycles} V-cycles" if vcycles else f"tol {tol:g}"
    print(f"{n}^2 {name}: per gradient CPU {best * 1e3:.1f} ms, |adj - FD|/|FD| {err:.1e}, "
          f"iterations per projection {np.mean([s.iterations for s in stats]):.1f}, divergence left "
          f"{np.mean([s.residual for s in stats]):.1e}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes (a check that the script runs)")
    ap.add_argument("--per-gradient", action="store_true", help="the Taichi comparison's gradient per tolerance")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--ab", type=int, default=0, metavar="ROUNDS",
                    help="A/B: per case, ROUNDS alternating runs without and with the forward's kept "
                         "advection scratch (recomputed vs read); prints the mean backward of each")
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 3], help="the dimensions to run (2, 3)")
    ap.add_argument("--reps", type=int, default=1,
                    help="the best of this many forward runs and of as many rollout + backward runs per case "
                         "(more is steadier on a loaded machine)")
    ap.add_argument("--schemes", nargs="+", default=["semi_lagrangian", "maccormack", "bfecc"],
                    help="the advection schemes to run")
    opts = ap.parse_args()
    km.set_num_threads(1)
    if opts.per_gradient:
        for n in opts.sizes:
            for tol in (1e-10, 1e-6, 1e-4, 1e-3):
                per_gradient(n, tol)
            for vcycles in (1, 2, 4):
                per_gradient(n, TOL, vcycles=vcycles)
        return
    n2, n3, t2, t3 = (256, 64, 16, 9) if not opts.quick else (32, 12, 4, 4)
    summary = []
    for shape, steps in (((n2, n2), t2), ((n3, n3, n3), t3)):
        if len(shape) not in opts.dims:
            continue
        for advection, rk in (("semi_lagrangian", 1), ("maccormack", 2), ("bfecc", 2)):
            if advection not in opts.schemes:
                continue
            if opts.ab:
                runs = {False: [], True: []}
                for _ in range(opts.ab):
                    for kept in (False, True):
                        runs[kept].append(case(shape, steps, advection, rk, kept=kept))
                mean = {kept: {key: np.mean([r[key] for r in rs]) for key in rs[0]} for kept, rs in runs.items()}
                summary.append(f"{len(shape)}D {advection} backward stored/checkpointed [s] recomputed "
                               f"{mean[False]['stored backward']:.3f}/{mean[False]['checkpointed backward']:.3f}, kept "
                               f"{mean[True]['stored backward']:.3f}/{mean[True]['checkpointed backward']:.3f}; "
                               f"backward/forward recomputed {mean[False]['stored']:.2f}/{mean[False]['checkpointed']:.2f}, "
                               f"kept {mean[True]['stored']:.2f}/{mean[True]['checkpointed']:.2f}; rollout [s] "
                               f"recomputed {mean[False]['stored rollout']:.3f}/{mean[False]['checkpointed rollout']:.3f}, "
                               f"kept {mean[True]['stored rollout']:.3f}/{mean[True]['checkpointed rollout']:.3f}")
                continue
            r = case(shape, steps, advection, rk, reps=opts.reps)
            summary.append(f"{len(shape)}D {advection} {r['stored']:.2f}/{r['checkpointed']:.2f}")
    print("SUMMARY (CPU backward/forward, stored/checkpointed, 1 thread): " + "; ".join(summary), flush=True)


if __name__ == "__main__":
    main()
