"""km.sph benchmarks: neighbour-search throughput and time per step against particle count,
side by side with SPlisHSPlasH (pysplishsplash, WCSPH and DFSPH) and a Taichi CPU WCSPH
(bench/sph/taichi_sph.py) on the same 3D dam break.

    python bench/sph/sph_bench.py                 # quick: ~10k and ~40k particles
    python bench/sph/sph_bench.py --full          # adds ~100k and ~190k (the issue's target sizes)
    python bench/sph/sph_bench.py --no-peers      # kinema only
    python bench/sph/sph_bench.py --side-by-side  # the issue's comparison: ~150k particles, all five
                                              # codes in one run, with the ratios
    python bench/sph/sph_bench.py --side-by-side --splishsplash-only   # rerun SPlisHSPlasH alone
    python bench/sph/sph_bench.py --work-precision  # DFSPH seconds per simulated second against the
                                              # measured mean density error, sweeping kinema's
                                              # tol and SPlisHSPlasH's maxError (both wall
                                              # models), ~150k particles, one run

Scene (sph_bench.scene): a water column [0, a] x [0, 2a] x [0, a] (a = 0.5 m) in the closed box
[0, 4a] x [0, 3a] x [0, a], released at rest; the spacing sets the particle count. Every code
runs the same start-up before its timed steps: round(START / dt) steps of the timed dt from rest. Each figure is
the best of a few timed calls (bench/common/harness.py records the load other processes put on the
machine; a disturbed figure is retried and flagged). Every result is checked before it is
recorded: the neighbour pairs against scipy's cKDTree, the simulations' mean density error
against a bound and their positions for finiteness.
CSV: bench/out/sph.csv; plot: bench/out/sph_step.png (seconds per step against particles).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

A = 0.5
OUT = Path(__file__).resolve().parents[1] / "out"
STEPS = 5  # steps per timed call
START = 0.02  # simulated start-up before timing [s]
MEASURE = {}  # harness.measure options; --loaded caps the retries of disturbed calls


def scene(particles: int):
    """(positions, spacing, domain) of the dam break with about `particles` particles."""
    spacing = A * (2.0 / particles) ** (1 / 3)
    import kinema as km

    x = km.sph.block([0, 0, 0], [A, 2 * A, A], spacing)
    return x, spacing, ([0, 0, 0], [4 * A, 3 * A, A])


def check(name, ok, detail):
    if not ok:
        raise AssertionError(f"{name}: result check failed ({detail}); not recording a time")


# ------------------------------------------------------------------ neighbour search

def bench_neighbors(sizes, rec):
    import kinema as km
    from scipy.spatial import cKDTree

    for n in sizes:
        x, s, _ = scene(n)
        rng = np.random.default_rng(0)
        x = x + 0.1 * s * rng.standard_normal(x.shape)  # break the lattice's ties
        r = 2 * s
        m = harness.measure(lambda: km.sph.neighbor_pairs(x, r), min_of=3, warmup=True)
        pairs = m.value
        ref = harness.measure(lambda: cKDTree(x).query_pairs(r, output_type="ndarray"), min_of=3)
        want = ref.value
        want = want[np.lexsort((want[:, 1], want[:, 0]))]
        check("neighbor_pairs", np.array_equal(pairs, want), f"{len(pairs)} vs {len(want)} pairs")
        for method, meas in (("kinema-neighbor_pairs", m), ("scipy-cKDTree.query_pairs", ref)):
            rec.record(method, len(x), meas.seconds, measurement=meas,
                       notes={"pairs": len(pairs), "pairs_per_s": f"{len(pairs) / meas.seconds:.3g}"})
            print(f"  {method:28s} n={len(x):7d} {meas.seconds * 1e3:8.1f} ms "
                  f"{len(pairs) / meas.seconds / 1e6:6.1f} M pairs/s  (other load {meas.other_load:.2f})")


# ------------------------------------------------------------------ time per step

def kinema_fluid(n, method, tol, **options):
    import kinema as km

    x, s, domain = scene(n)
    fluid = km.sph.Fluid(x, s, method=method, gravity=(0, -9.81, 0), domain=domain, tol=tol,
                         divergence_tol=tol, **options)
    return fluid, s


def started_dt(fluid, method, s):
    """Advances `fluid` to START with CFL steps and returns the step every code is timed at."""
    fluid.advance(START)  # past the start-up transient
    # WCSPH: its acoustic CFL step. DFSPH: the CFL step at the surge front's speed
    # sqrt(2 g 2a) that the run soon reaches (at START the fluid is still near rest and
    # stable_dt would give the 5 ms cap, at which a 1 m column of ~150k particles needs
    # more than max_iter Jacobi iterations: measured 2.8% compression).
    dt = fluid.stable_dt(0.4)
    if method == "dfsph":
        dt = min(dt, 0.4 * s / np.sqrt(2 * 9.81 * 2 * A))
    return dt


def timed_dt(n, method, tol):
    """(dt, spacing, speed of sound): the step every code is timed at, from a throwaway run."""
    fluid, s = kinema_fluid(n, method, tol)
    return started_dt(fluid, method, s), s, fluid.speed_of_sound


def steps_of(fluid, dt, iterations, split=None, same_steps=False):
    """The timed call: STEPS steps of dt, their pressure iterations (both solves) appended to
    ``iterations`` (and, given a dict ``split``, the steps' seconds in the neighbour search, the
    kernel pass and the solves, summed); returns the mean compression after them. With
    ``same_steps`` every call (the harness retries disturbed ones) first restores the state the
    first call started from, so that each try times the same steps, as each SPlisHSPlasH run
    does (else a retry times the next STEPS steps of the surge: at tol 1e-4 a loaded run took
    23.8 iterations per step there against 14.0 in the first window)."""
    start = fluid.state() if same_steps else None

    def run():
        if start is not None:
            fluid.set_state(start)
        iterations.clear()
        parts = dict.fromkeys(("search", "kernel", "solve", "step"), 0.0)
        for _ in range(STEPS):
            st = fluid.step(dt)
            iterations.append(st.iterations + st.divergence_iterations)
            for key, value in (("search", st.search_seconds), ("kernel", st.kernel_seconds),
                               ("solve", st.solve_seconds), ("step", st.seconds)):
                parts[key] += value
        if split is not None:
            split.clear()
            split.update(parts)
        return fluid.density_error()

    return run


def started_fluid(n, method, tol, dt, **options):
    """kinema's fluid after the start-up every code runs before its timed steps: from rest,
    round(START / dt) steps of the timed dt, as SPlisHSPlasH (fixed dt) and the Taichi WCSPH are
    started. (Started with CFL steps to START instead, kinema would be timed on its first steps
    at the larger dt: a transient at which DFSPH takes 4.2 iterations per step instead of the
    3.0 it takes here, as SPlisHSPlasH does.)"""
    fluid, _ = kinema_fluid(n, method, tol, **options)
    for _ in range(max(1, round(START / dt))):
        fluid.step(dt)
    return fluid


def peer_dts(sizes, tol):
    """The dts bench_kinema would time at, without timing kinema (for --splishsplash-only)."""
    return {(n, method): timed_dt(n, method, tol) for n in sizes for method in ("wcsph", "dfsph")}


def bench_kinema(sizes, rec, tol, results):
    dts = {}
    for n in sizes:
        for method in ("wcsph", "dfsph"):
            dt, s, c = timed_dt(n, method, tol)
            dts[(n, method)] = (dt, s, c)
            fluid = started_fluid(n, method, tol, dt)

            iterations = []
            run = steps_of(fluid, dt, iterations, same_steps=True)

            # The CPU seconds of our threads as a second figure: other processes' load disturbs
            # it far less than the wall time (spin-waiting threads inflate it somewhat).
            m = harness.measure(harness.with_cpu(run), min_of=2, **MEASURE)
            err, cpu = m.value
            bound = 0.02 if method == "wcsph" else 5 * tol
            check(f"kinema-{method}", np.isfinite(fluid.x).all() and err < bound, f"density error {err:.2e}")
            per_step = m.seconds / STEPS
            its = np.mean(iterations) if method == "dfsph" else 0
            results[(n, f"kinema-{method}")] = (per_step, dt, m.other_load)
            rec.record(f"kinema-{method}", fluid.n, per_step, error=err, measurement=m,
                       iterations=its or None,
                       notes={"dt": f"{dt:.3g}", "s_per_sim_s": f"{per_step / dt:.3g}",
                              "cpu_ms_per_step": f"{cpu / STEPS * 1e3:.1f}"})
            print(f"  kinema-{method:6s}  n={fluid.n:7d} {per_step * 1e3:8.1f} ms/step "
                  f"({cpu / STEPS * 1e3:.1f} CPU ms) dt={dt:.2e} "
                  f"{per_step / dt:7.1f} s per simulated s, density error {err:.1e}"
                  + (f", {its:.1f} solver iterations/step" if its else "")
                  + f" (other load {m.other_load:.2f})")
    return dts


def bench_taichi(sizes, rec, dts, threads, results):
    try:
        from taichi_sph import TaichiWCSPH
    except ImportError as exc:
        print(f"  taichi: not available ({exc})")
        return
    import kinema as km

    for n in sizes:
        dt, s, c = dts[(n, "wcsph")]
        x, _, (lower, upper) = scene(n)
        xb = km.sph.box_boundary(lower, upper, s, layers=2)
        # The wall samples' exact lattice volume, as kinema's domain walls use.
        cell = [(u - l) / max(1, round((u - l) / s)) for l, u in zip(lower, upper)]
        psi = np.full(len(xb), 1000.0 * np.prod(cell))
        sim = TaichiWCSPH(x, xb, psi, s, c, lower, upper, threads=threads)
        steps = max(1, round(START / dt))
        for _ in range(steps):  # same start-up transient; compiles the kernels
            sim.step(dt)
        sim.sync()

        def run():
            for _ in range(STEPS):
                sim.step(dt)
            sim.sync()
            return sim.density_error()

        m = harness.measure(run, min_of=2, **MEASURE)
        err = m.value
        check("taichi-wcsph", np.isfinite(sim.positions()).all() and err < 0.02, f"density error {err:.2e}")
        per_step = m.seconds / STEPS
        results[(n, "taichi-wcsph")] = (per_step, dt, m.other_load)
        rec.record("taichi-wcsph-f32", len(x), per_step, error=err, measurement=m,
                   notes={"dt": f"{dt:.3g}", "s_per_sim_s": f"{per_step / dt:.3g}"})
        print(f"  taichi-wcsph  n={len(x):7d} {per_step * 1e3:8.1f} ms/step, density error {err:.1e} "
              f"(other load {m.other_load:.2f})")


def run_splishsplash(method, boundary, spacing, dt, tol, stiffness, skip, threads):
    """One bench/sph/splishsplash_run.py process; its JSON result, or None (reported) if it failed."""
    script = Path(__file__).resolve().parent / "splishsplash_run.py"
    cache = OUT / "splishsplash_cache"  # wall samplings / volume maps, reused between runs
    out = Path(tempfile.mkstemp(suffix=".json")[1])
    cmd = [sys.executable, str(script), "--method", method, "--spacing", repr(float(spacing)),
           "--steps", str(STEPS + 1), "--dt", repr(float(dt)), "--tol", repr(float(tol)),
           "--stiffness", repr(float(stiffness)), "--out", str(out), "--skip", str(skip),
           "--boundary", boundary, "--cache", str(cache),
           "--quiet-timeout", str(MEASURE.get("quiet_timeout", harness.DEFAULT_QUIET_TIMEOUT))]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, env=env)
    text = out.read_text()
    out.unlink()
    if proc.returncode != 0 or not text:
        print(f"  splishsplash-{method} ({boundary}): failed (exit {proc.returncode}): {proc.stderr[-300:]}")
        return None
    return json.loads(text)


def bench_splishsplash(sizes, rec, dts, tol, threads, results, boundaries=("akinci",)):
    """SPlisHSPlasH on the same scene, per method and wall model, each run in its own process
    (bench/sph/splishsplash_run.py: kinema's lattice, kinema's dt, Tait B and tol, set on its objects
    and read back). Its per-step figure is the median of the timed steps; the check also rejects
    a run that lost particles through a wall or blew up (its earlier runs did, unnoticed, since
    scattered particles have no compression)."""
    for n in sizes:
        for method in ("wcsph", "dfsph"):
            dt, s, c = dts[(n, method)]
            stiffness = 1000.0 * c * c / 7.0  # kinema's Tait B = rho0 c^2 / gamma
            # Past the same start-up transient as kinema (its steps there are not timed).
            skip = max(1, round(START / dt))
            for boundary in boundaries:
                name = f"splishsplash-{method}" + ("" if boundary == "akinci" else f"-{boundary}")
                res = run_splishsplash(method, boundary, s, dt, tol, stiffness, skip, threads)
                if res is None:
                    continue
                per_step = float(np.median(res["per_step"]))
                cpu = float(np.median(res["cpu_per_step"]))
                err = res["density_error"]
                bound = 0.02 if method == "wcsph" else 5 * tol  # as for kinema
                steps_dt = np.array(res["sim_dt_per_step"])
                ok = (np.isfinite(per_step) and err < bound and res["outside_box"] == 0
                      and res["max_speed"] < c and np.allclose(steps_dt, dt, rtol=1e-3))
                if not ok:  # one peer variant failing must not take kinema's figures down
                    print(f"  {name}: result check failed (density error {err:.2e}, {res['outside_box']} "
                          f"particles out of the box, top speed {res['max_speed']:.3g} m/s (bound c = "
                          f"{c:.3g}), dt per step {steps_dt.min():.3g}..{steps_dt.max():.3g} (want "
                          f"{dt:.3g})); not recording a time")
                    continue
                load = res["other_load"]
                its = float(np.mean(res["iterations_per_step"])) if method == "dfsph" else 0
                results[(n, name)] = (per_step, dt, load)
                # Its process's figures as a harness.Measurement, for the CSV's load columns.
                m = harness.Measurement(seconds=per_step, wall=sum(res["per_step"]), other_load=load, repeats=1,
                                        disturbed=load > harness.DEFAULT_MAX_LOAD, value=None, runs=())
                rec.record(name, res["particles"], per_step, error=err, iterations=its or None, measurement=m,
                           notes={"dt": f"{dt:.3g}", "cpu_s_per_step": f"{cpu:.3g}",
                                  "s_per_sim_s": f"{per_step / dt:.3g}", "boundary": boundary,
                                  "boundary_samples": res["boundary_samples"],
                                  "precompute_s": f"{res['precompute_s']:.3g}",
                                  "precompute_cached": res["precompute_cached"],
                                  "max_speed": f"{res['max_speed']:.3g}", **res["applied"]})
                print(f"  {name:30s} n={res['particles']:7d} {per_step * 1e3:8.1f} ms/step "
                      f"(CPU {cpu * 1e3:.1f} ms/step) density error {err:.1e}"
                      + (f", {its:.1f} solver iterations/step" if its else "")
                      + f", wall {boundary} ({res['boundary_samples']} samples), precompute "
                      f"{res['precompute_s']:.1f} s{' (cached)' if res['precompute_cached'] else ''} "
                      f"(other load {load:.2f})")


# ------------------------------------------------------------------ work-precision (DFSPH)

WP_TOLS = (3e-3, 1e-3, 3e-4, 1e-4, 3e-5)


def bench_work_precision(n, tols, rec, threads, boundaries=("akinci", "volume-map"), two_level=False):
    """Seconds per simulated second against the measured mean density error, one point per
    solver tolerance, kinema DFSPH and SPlisHSPlasH DFSPH (each wall model) on the same scene,
    dt and start-up. The error on the x axis is measured (kinema: density_error() after the
    timed steps; SPlisHSPlasH: the same mean compression of its densities), not the tolerance
    asked for. With two_level, kinema also with its coarse correction forced on
    ("kinema-dfsph-two-level"; by default it is on only where tol > 1e-3): the A/B of the
    two-level density solve in the same run. Returns {code: [(error, s_per_sim_s), ...]} of wall
    time, and the same of CPU time (each code's own threads, harness.with_cpu; SPlisHSPlasH's
    median per step): on a loaded machine the wall times of runs minutes apart see different
    loads (one peer run at other load 1.0 took 261 s per simulated s, the same settings at
    1.4-1.6 took 496-838 s), the CPU time far less."""
    dt, s, c = timed_dt(n, "dfsph", tols[0])  # one dt for every point: the same work per step
    curves, cpu_curves = {}, {}
    variants = [("kinema-dfsph", {})] + ([("kinema-dfsph-two-level", {"coarse_correction": True})] if two_level else [])
    for (code, options), tol in ((v, tol) for tol in tols for v in variants):
        fluid = started_fluid(n, "dfsph", tol, dt, **options)
        iterations, split = [], {}
        run = steps_of(fluid, dt, iterations, split, same_steps=True)

        m = harness.measure(harness.with_cpu(run), min_of=1, **MEASURE)
        err, cpu = m.value
        check(code, np.isfinite(fluid.x).all(), "non-finite positions")
        per_sim = m.seconds / STEPS / dt
        cpu_per_sim = cpu / STEPS / dt
        curves.setdefault(code, []).append((err, per_sim))
        cpu_curves.setdefault(code, []).append((err, cpu_per_sim))
        rec.record(code, fluid.n, per_sim, error=err, measurement=m, iterations=float(np.mean(iterations)),
                   notes={"tol": tol, "dt": f"{dt:.3g}", "unit": "s per simulated s",
                          "cpu_s_per_sim_s": f"{cpu_per_sim:.4g}"})
        print(f"  {code:25s} tol={tol:7.1e} n={fluid.n:7d} density error {err:8.2e} "
              f"{per_sim:8.1f} s/sim s (CPU {cpu_per_sim:.1f}), {np.mean(iterations):5.1f} iterations/step "
              f"(other load {m.other_load:.2f})", flush=True)
        step = max(split["step"], 1e-12)  # where the step's time went (the last timed call)
        print(f"      kinema's step: search {split['search'] / step:4.0%}, kernel pass {split['kernel'] / step:4.0%}, "
              f"solves {split['solve'] / step:4.0%}, rest {1 - (split['search'] + split['kernel'] + split['solve']) / step:4.0%}",
              flush=True)
        del fluid
    for boundary in boundaries:
        name = "splishsplash-dfsph" + ("" if boundary == "akinci" else f"-{boundary}")
        for tol in tols:
            res = run_splishsplash("dfsph", boundary, s, dt, tol, 1000.0 * c * c / 7.0, max(1, round(START / dt)),
                                   threads)
            if res is None:
                continue
            per_step = float(np.median(res["per_step"]))
            err = res["density_error"]
            ok = np.isfinite(per_step) and res["outside_box"] == 0 and res["max_speed"] < c
            if not ok:
                print(f"  {name}: maxError {100 * tol:g}%: result check failed ({res['outside_box']} particles out "
                      f"of the box, top speed {res['max_speed']:.3g} m/s); not recording")
                continue
            per_sim = per_step / dt
            cpu_per_sim = float(np.median(res["cpu_per_step"])) / dt
            its = float(np.mean(res["iterations_per_step"]))
            curves.setdefault(name, []).append((err, per_sim))
            cpu_curves.setdefault(name, []).append((err, cpu_per_sim))
            m = harness.Measurement(seconds=per_sim, wall=sum(res["per_step"]), other_load=res["other_load"],
                                    repeats=1, disturbed=res["other_load"] > harness.DEFAULT_MAX_LOAD, value=None,
                                    runs=())
            rec.record(name, res["particles"], per_sim, error=err, iterations=its, measurement=m,
                       notes={"tol": tol, "dt": f"{dt:.3g}", "unit": "s per simulated s", "boundary": boundary,
                              "cpu_s_per_sim_s": f"{cpu_per_sim:.4g}", **res["applied"]})
            print(f"  {name:25s} tol={tol:7.1e} n={res['particles']:7d} density error {err:8.2e} "
                  f"{per_sim:8.1f} s/sim s (CPU {cpu_per_sim:.1f}), {its:5.1f} iterations/step "
                  f"(other load {res['other_load']:.2f})", flush=True)
    return curves, cpu_curves


def at(points, e):
    """A curve [(error, cost), ...] at error e, interpolated log-log between its measured points
    (no extrapolation), or None outside them."""
    pts = sorted(points)
    for (e0, t0), (e1, t1) in zip(pts, pts[1:]):
        if e0 <= e <= e1 and e1 > e0:
            f = np.log(e / e0) / np.log(e1 / e0)
            return float(np.exp(np.log(t0) + f * (np.log(t1) - np.log(t0))))
    return None


def peer_ratios(curves, peer_cost, errors=(1e-3, 5e-4, 2e-4, 1e-4)):
    """Peer / kinema seconds per simulated second at each error e: kinema's curve at e (at())
    against peer_cost(points, e) of each SPlisHSPlasH curve (None where undefined), the peer at
    its cheapest wall model. Returns [(error, ratio or None, peer name)]."""
    out = []
    for e in errors:
        k = at(curves.get("kinema-dfsph", []), e)
        peers = [(peer_cost(v, e), name) for name, v in curves.items() if name.startswith("splishsplash")]
        peers = [(t, name) for t, name in peers if t is not None]
        if k is None or not peers:
            out.append((e, None, None))
            continue
        t, name = min(peers)
        out.append((e, t / k, name))
    return out


def equal_accuracy_ratios(curves, errors=(1e-3, 5e-4, 2e-4, 1e-4)):
    """At equal measured density error: the peer's curve at e too (no extrapolation)."""
    return peer_ratios(curves, at, errors)


def at_least_as_accurate_ratios(curves, errors=(1e-3, 5e-4, 2e-4, 1e-4)):
    """Against the peer's cheapest measured run whose error is <= e (at least as accurate as
    kinema at e): defined also where the peer's curve does not reach e (its cheapest settings
    already land below it). Where both measures exist they can differ either way (a run just
    above e may be cheaper than the interpolated cost at e)."""
    return peer_ratios(curves, lambda v, e: min((t for err, t in v if err <= e), default=None), errors)


def print_ratios(sizes, results):
    """The issue's targets as ratios of figures from this one run."""
    for n in sizes:
        def ratio(slow, fast):
            # A peer run with several wall models counts with its fastest that passed its checks.
            peer = [v for (m, name), v in results.items() if m == n and (name == slow or name.startswith(slow + "-"))]
            a, b = min(peer, default=None), results.get((n, fast))
            return f"{a[0] / b[0]:.2f}x" if a and b else "n/a"

        k_w, k_d = results.get((n, "kinema-wcsph")), results.get((n, "kinema-dfsph"))
        per_sim = f"{(k_w[0] / k_w[1]) / (k_d[0] / k_d[1]):.2f}x" if k_w and k_d else "n/a"
        print(f"ratios at ~{n} particles (time per step, peer / kinema; targets >= 1.5, 1.5, 2):")
        print(f"  SPlisHSPlasH WCSPH / kinema WCSPH: {ratio('splishsplash-wcsph', 'kinema-wcsph')}")
        print(f"  SPlisHSPlasH DFSPH / kinema DFSPH: {ratio('splishsplash-dfsph', 'kinema-dfsph')}")
        print(f"  Taichi WCSPH / kinema WCSPH:       {ratio('taichi-wcsph', 'kinema-wcsph')}")
        print(f"  kinema per simulated second, WCSPH / DFSPH (target > 1): {per_sim}")


def plot_and_report(csv_path, png_name, benchmark):
    try:
        harness.plot_work_precision(csv_path, OUT / png_name, benchmark=benchmark)
    except Exception as exc:  # the plot is a convenience; the CSV is the record
        print(f"(plot skipped: {exc})")
    print(f"CSV: {csv_path}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--full", action="store_true", help="add ~100k and ~190k particles")
    p.add_argument("--side-by-side", action="store_true",
                   help="the issue's comparison: ~150k particles, kinema and all peers in one run")
    p.add_argument("--no-peers", action="store_true")
    p.add_argument("--neighbors-only", action="store_true",
                   help="only the neighbour search (km.sph.neighbor_pairs against cKDTree, pairs per second)")
    p.add_argument("--sizes", type=int, nargs="+", help="particle counts (overrides the defaults)")
    p.add_argument("--tol", type=float, default=1e-3, help="DFSPH density tolerance (both codes)")
    p.add_argument("--threads", type=int, default=harness.default_threads())
    p.add_argument("--splishsplash-only", action="store_true",
                   help="time only SPlisHSPlasH (kinema's start-up still runs, untimed, to give the dts)")
    p.add_argument("--splishsplash-boundary", choices=("akinci", "volume-map", "both"), default="akinci",
                   help="SPlisHSPlasH's wall model: Akinci samples as kinema (default), its volume maps, or both")
    p.add_argument("--work-precision", action="store_true",
                   help="DFSPH work-precision: kinema's tol and SPlisHSPlasH's maxError swept, both wall models")
    p.add_argument("--two-level", action="store_true",
                   help="--work-precision: also kinema with its coarse correction forced on (the A/B of the two-level solve)")
    p.add_argument("--tols", type=float, nargs="+", help="tolerances of --work-precision (default %s)" % (WP_TOLS,))
    p.add_argument("--loaded", action="store_true",
                   help="on a busy machine: keep the best of 2 tries instead of waiting for quiet")
    args = p.parse_args(argv)
    if args.loaded:
        MEASURE.update(max_tries=2, quiet_timeout=1.0)
    import kinema as km

    km.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    sizes = args.sizes or [10_000, 40_000] + ([100_000, 190_000] if args.full else [])
    if args.side_by_side or args.work_precision:
        sizes = args.sizes or [150_000]
    OUT.mkdir(exist_ok=True)
    if args.work_precision:
        csv_wp = OUT / "sph_dfsph_work_precision.csv"
        rec = harness.Recorder(csv_wp, "sph_dambreak3d_dfsph_work_precision", threads=args.threads)
        print(f"threads {args.threads}, commit {harness.git_commit()}")
        print(f"DFSPH work-precision, 3D dam break, ~{sizes[0]} particles:")
        curves, cpu_curves = bench_work_precision(sizes[0], tuple(args.tols or WP_TOLS), rec, args.threads,
                                                  () if args.no_peers else ("akinci", "volume-map"), args.two_level)
        if args.two_level:
            ab = [(e, at(curves.get("kinema-dfsph", []), e), at(curves.get("kinema-dfsph-two-level", []), e))
                  for e in (1e-3, 5e-4, 2e-4, 1e-4)]
            print("SUMMARY sph two-level A/B (default / two-level kinema DFSPH, s per simulated s at equal "
                  "measured error): " + ", ".join(f"{e:.0e}: {f'{a / b:.2f}x' if a and b else 'n/a'}" for e, a, b in ab))
        print("equal measured density error: SPlisHSPlasH (fastest wall model) / kinema, s per simulated s "
              "(target >= 1.5):")
        ratios = equal_accuracy_ratios(curves)
        for e, ratio, name in ratios:
            print(f"  error {e:7.1e}: " + (f"{ratio:.2f}x ({name})" if ratio else "n/a (outside a measured curve)"))
        strict = at_least_as_accurate_ratios(curves)
        print("SPlisHSPlasH's cheapest run at least as accurate (error <= e) / kinema at e:")
        for e, ratio, name in strict:
            print(f"  error {e:7.1e}: " + (f"{ratio:.2f}x ({name})" if ratio else "n/a"))
        met = [r is not None and r >= 1.5 for _, r, _ in ratios]
        print("SUMMARY sph work-precision (SPlisHSPlasH fastest wall model / kinema DFSPH, target >= 1.5x at every error): "
              + ", ".join(f"{e:.0e}: {f'{r:.2f}x' if r else 'n/a'}" for e, r, _ in ratios)
              + (" -> target met" if all(met) else " -> target NOT met")
              + "; peer's cheapest run at least as accurate / kinema: "
              + ", ".join(f"{e:.0e}: {f'{r:.2f}x' if r else 'n/a'}" for e, r, _ in strict))
        cpu_eq, cpu_strict = equal_accuracy_ratios(cpu_curves), at_least_as_accurate_ratios(cpu_curves)
        print("SUMMARY sph work-precision, CPU seconds (each code's own threads: less disturbed by other load than "
              "the wall time above): equal error "
              + ", ".join(f"{e:.0e}: {f'{r:.2f}x' if r else 'n/a'}" for e, r, _ in cpu_eq)
              + "; peer's cheapest run at least as accurate / kinema: "
              + ", ".join(f"{e:.0e}: {f'{r:.2f}x' if r else 'n/a'}" for e, r, _ in cpu_strict))
        plot_and_report(csv_wp, "sph_dfsph_work_precision.png", "sph_dambreak3d_dfsph_work_precision")
        return 0
    csv_path = OUT / "sph.csv"
    print(f"threads {args.threads}, commit {harness.git_commit()}")
    if not (args.side_by_side or args.splishsplash_only):
        print("neighbour search (radius 2 x spacing):")
        bench_neighbors(sizes, harness.Recorder(csv_path, "sph_neighbors", threads=args.threads))
    if args.neighbors_only:
        return 0
    rec = harness.Recorder(csv_path, "sph_dambreak3d_step", threads=args.threads)
    print("time per step, 3D dam break:")
    results = {}
    walls = ("akinci", "volume-map") if args.splishsplash_boundary == "both" else (args.splishsplash_boundary,)
    if args.splishsplash_only:
        bench_splishsplash(sizes, rec, peer_dts(sizes, args.tol), args.tol, args.threads, results, walls)
        return 0
    dts = bench_kinema(sizes, rec, args.tol, results)
    if not args.no_peers:
        bench_taichi(sizes, rec, dts, args.threads, results)
        bench_splishsplash(sizes, rec, dts, args.tol, args.threads, results, walls)
    print_ratios(sizes, results)
    plot_and_report(csv_path, "sph_step.png", "sph_dambreak3d_step")
    return 0


if __name__ == "__main__":
    sys.exit(main())
