"""A column at rest that fills its closed tank (0.1 m wide, 0.05 m deep, inviscid, gravity), the
set-up of tests/test_sph.py test_column_filling_its_tank_stays_at_rest: does km.sph keep its
energy? Prints one line per case (method, dimension, spacing) with the largest rise of kinetic +
potential energy as a fraction of the available energy (e0 minus the lowest possible state), the
top speed against sqrt(2 g H), the steps whose DFSPH solve stopped at max_iter, the largest
density error of the positions reached, and the largest iteration count.

  python bench/sph/sph_filled_tank.py                       # the six cases of the test, 0.3 s
  python bench/sph/sph_filled_tank.py --dt-scale 0.5        # steps of 0.5 x stable_dt()
  python bench/sph/sph_filled_tank.py --case dfsph 2 0.0025 --series   # one line per step
  python bench/sph/sph_filled_tank.py --walls mirror        # DFSPH's walls="mirror" (the old default)

A gain that does not shrink with the step (--dt-scale) is a force that is not conservative,
not a time-integration error.
"""
import argparse
import time

import numpy as np

import kinema as km

G = 9.81
CASES = [(m, d, s) for m in ("dfsph", "wcsph") for d, s in ((2, 0.0025), (2, 0.005), (3, 0.005))]


def run(method, d, s, duration=0.3, dt_scale=1.0, series=False, walls="shepard"):
    L, H = 0.1, 0.05
    upper = [L] * d
    upper[1] = H
    gravity = [0.0] * d
    gravity[1] = -G
    fluid = km.sph.Fluid(km.sph.block([0] * d, upper, s), s, gravity=gravity, method=method,
                         domain=([0] * d, [L] * d), walls=walls if method == "dfsph" else None)
    mass = fluid.mass

    def energy():
        return fluid.kinetic_energy() + mass * G * fluid.x[:, 1].sum()

    e0 = energy()
    available = e0 - mass * G * (s / 2) * fluid.n
    gain, vmax, unconverged, error, iterations = -np.inf, 0.0, 0, 0.0, 0
    start = time.perf_counter()
    while fluid.time < duration - 1e-12:
        st = fluid.step(min(dt_scale * fluid.stable_dt(), duration - fluid.time))
        step_gain = (energy() - e0) / available
        step_error = fluid.density_error()
        gain, vmax, error = max(gain, step_gain), max(vmax, st.max_speed), max(error, step_error)
        unconverged += not (st.density_converged and st.divergence_converged)
        iterations = max(iterations, st.iterations)
        if series:
            print(f"  t={fluid.time:.4f} dt={st.dt:.2e} it={st.iterations:3d} div_it={st.divergence_iterations:3d} "
                  f"converged={st.density_converged and st.divergence_converged} solver_error={st.density_error:.2e} "
                  f"density_error={step_error:.2e} max_speed={st.max_speed:.3f} gain={step_gain:+.3f}")
    print(f"{method}{' ' + walls if method == 'dfsph' else ''} {d}D s={s} n={fluid.n} steps={fluid.steps} dt_scale={dt_scale}: energy gain {gain:+.3f} of "
          f"available, top speed {vmax:.3f} m/s (sqrt(2 g H) = {np.sqrt(2 * G * H):.3f}), {unconverged} steps at "
          f"max_iter, density error <= {error:.2e}, iterations <= {iterations} "
          f"[{time.perf_counter() - start:.1f} s, {km.get_num_threads()} threads]")
    return gain


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", nargs=3, metavar=("METHOD", "D", "SPACING"))
    parser.add_argument("--duration", type=float, default=0.3)
    parser.add_argument("--dt-scale", type=float, default=1.0)
    parser.add_argument("--series", action="store_true")
    parser.add_argument("--walls", default="shepard", choices=["mirror", "shepard"], help="DFSPH's walls")
    args = parser.parse_args()
    cases = [(args.case[0], int(args.case[1]), float(args.case[2]))] if args.case else CASES
    gains = [run(m, d, s, args.duration, args.dt_scale, args.series, args.walls) for m, d, s in cases]
    print(f"summary: {sum(g >= 0.01 for g in gains)} of {len(gains)} cases gain >= 1% of the available energy")


if __name__ == "__main__":
    main()
