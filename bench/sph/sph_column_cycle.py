"""The viscous column at rest of tests/test_sph.py (issue 15) under DFSPH, step by step: why it
holds at tol 1e-3 and bounces at looser tolerances (a probe, no timing; its figures are load-free).

    python bench/sph/sph_column_cycle.py --d 2 --tol 2e-3 --series          # one run, per step
    python bench/sph/sph_column_cycle.py --d 2 3 --tol 1e-3 1.3e-3 2e-3 5e-3  # rms speed per tol
    python bench/sph/sph_column_cycle.py --d 2 3 --tol 2e-3 --warm-start 0    # the same, cold solves
    python bench/sph/sph_column_cycle.py --d 2 3 --method wcsph               # WCSPH's column (its walls)
    python bench/sph/sph_column_cycle.py --d 2 3 --tol 1e-3 2e-3 5e-3 --walls mirror  # DFSPH's walls="mirror"

Set-up as the test's column_at_rest: a column of depth 0.5 m (2D: 1 m wide, spacing 0.02; 3D:
0.3 x 0.15 m, spacing 0.025) in a closed tank, nu = 0.01, settled for 0.5 s by zeroing the
velocities every 0.02 s, then 0.5 s free at the steps advance() takes. Printed per run: the rms
speed of the free second half (the test's bound is 0.02 sqrt(2 g H) = 0.063 m/s), the pressure
slope in rho0 g and the density iterations per step (mean / max). With --series, every step
whose density solve ran past 8 iterations and every 5th step: iterations of both solves, the
solver's error, the mean vertical velocity and the mean pressure (hydrostatic mean: rho0 g H / 2
= 2450 Pa).
"""

from __future__ import annotations

import argparse

import numpy as np

G = 9.81
REST = {2: dict(s=0.02, size=[1.0, 0.5]), 3: dict(s=0.025, size=[0.3, 0.5, 0.15])}
SETTLE, FREE = 0.5, 0.5


def run(d, tol, warm_start, divergence_tol, series, method="dfsph", walls="shepard"):
    import kinema as km

    s, size = REST[d]["s"], REST[d]["size"]
    H = size[1]
    box = list(size)
    box[1] = 2 * H
    gravity = [0.0] * d
    gravity[1] = -G
    fluid = km.sph.Fluid(km.sph.block([0] * d, size, s), s, gravity=gravity, method=method, domain=([0] * d, box),
                         viscosity=0.01, tol=tol, warm_start=warm_start, divergence_tol=divergence_tol,
                         walls=walls if method == "dfsph" else None)
    while fluid.time < SETTLE - 1e-9:
        fluid.advance(0.02)
        fluid.v[:] = 0
    end = fluid.time + FREE
    iterations, energies, ys, ps = [], [], [], []
    k = 0
    while fluid.time < end - 1e-12:
        dt = min(fluid.stable_dt(), end - fluid.time)
        st = fluid.step(dt)
        k += 1
        iterations.append(st.iterations)
        energies.append(fluid.kinetic_energy())
        if fluid.time > end - 0.1:
            ys.append(fluid.x[:, 1].copy())
            ps.append(fluid.pressure.copy())
        if series and (k % 5 == 0 or st.iterations > 8):
            print(f"  step {k:4d} t={fluid.time:.3f} s: iterations {st.iterations:3d} + {st.divergence_iterations} "
                  f"(divergence), error {st.density_error:.2e}, mean v_y {fluid.v[:, 1].mean():+.4f} m/s, "
                  f"mean p {fluid.pressure.mean():6.0f} Pa")
    v_rms = np.sqrt(2 * max(energies[len(energies) // 2:]) / (fluid.mass * fluid.n))
    top = np.percentile(fluid.x[:, 1], 99.5) + s / 2
    y, p = np.concatenate(ys), np.concatenate(ps)
    mask = (y > 2 * s) & (y < top - 3 * s)
    slope = np.polyfit(y[mask], p[mask], 1)[0] / (-1000 * G)
    its = np.array(iterations)
    # The bottom row against rho0 g (H - y) (the walls' consistency).
    bottom = y < s
    ratio = np.mean(p[bottom] / (1000 * G * (top - y[bottom])))
    print(f"{method}{' walls=' + walls if method == 'dfsph' else ''} {d}D tol {tol:g} warm_start {warm_start:g} divergence_tol {divergence_tol:g}: rms speed {v_rms:.4f} m/s "
          f"(bound {0.02 * np.sqrt(2 * G * H):.4f}), slope {slope:.3f} rho0 g, density iterations "
          f"{its.mean():.1f} / {its.max()} per step, bottom row {ratio:.2f} rho0 g (H - y)", flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--d", type=int, nargs="+", default=[2], choices=[2, 3])
    p.add_argument("--tol", type=float, nargs="+", default=[1e-3, 2e-3])
    p.add_argument("--warm-start", type=float, default=0.5)
    p.add_argument("--divergence-tol", type=float, default=1e-3)
    p.add_argument("--series", action="store_true", help="print the steps of each run")
    p.add_argument("--method", default="dfsph", choices=["dfsph", "wcsph"], help="wcsph: tol and warm start unused")
    p.add_argument("--walls", default="shepard", choices=["mirror", "shepard"], help="DFSPH's walls")
    args = p.parse_args()
    for d in args.d:
        for tol in args.tol:
            run(d, tol, args.warm_start, args.divergence_tol, args.series, args.method, args.walls)


if __name__ == "__main__":
    main()
