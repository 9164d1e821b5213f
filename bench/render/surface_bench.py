"""Free-surface reconstruction per frame (km.surface): splashsurf (pysplashsurf) against
scikit-image's marching cubes on the smoothed volume fraction, at 150k SPH particles.

    python bench/render/surface_bench.py              # a ball of ~150k particles and a breaking-wave block of ~150k
    python bench/render/surface_bench.py --quick      # ~20k particles (wiring check)

Particles on a lattice of spacing s = 0.01 m, jittered by 0.05 s (a settled SPH fluid is not a
perfect lattice). Accuracy, measured before a time is recorded: for the ball, the RMS and the
largest distance of the mesh vertices to the sphere of the particles' volume (in spacings) and
the relative volume error against n s^3; the mesh must be closed with the right Euler
characteristic. Both methods at their defaults (cell s / 2). Times by bench/common/harness.py (other
processes' load recorded, disturbed runs retried), best of 3. CSV: bench/out/surface.csv.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"
S = 0.01


def ball(n_target, rng):
    r_cells = (3 * n_target / (4 * np.pi)) ** (1 / 3)
    k = np.arange(-int(r_cells) - 2, int(r_cells) + 3) * S
    x = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) < r_cells * S]
    return x + rng.uniform(-0.05, 0.05, x.shape) * S


def wave(n_target, rng):
    """A block whose height varies as a breaking wave: h(x) = H (0.6 + 0.4 sin(2 pi x / L))."""
    nx = nz = int(round((n_target / 30) ** 0.5 * 1.0))
    ny = 50
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    x = np.stack([i, j, k], -1).reshape(-1, 3) * S
    height = ny * S * (0.6 + 0.4 * np.sin(2 * np.pi * x[:, 0] / (nx * S)) * np.cos(np.pi * x[:, 2] / (nz * S)))
    x = x[x[:, 1] < height]
    return x + rng.uniform(-0.05, 0.05, x.shape) * S


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    km.set_num_threads(args.threads)
    n = 20_000 if args.quick else 150_000
    rng = np.random.default_rng(0)
    rec = harness.Recorder(OUT / "surface.csv", "surface_reconstruction", threads=args.threads)
    print(f"{'case':6s} {'method':15s} {'particles':>9s} {'seconds':>8s} {'load':>5s} {'triangles':>9s} "
          f"{'rms/s':>6s} {'max/s':>6s} {'vol err':>8s}")
    for case, x in (("ball", ball(n, rng)), ("wave", wave(n, rng))):
        for method in km.surface.METHODS:
            m = harness.measure(lambda: km.surface.reconstruct(x, S, method=method), min_of=3, warmup=True)
            mesh = m.value
            closed = mesh.is_closed()
            if not closed:
                raise AssertionError(f"{case}/{method}: mesh not closed; not recording a time")
            rms = mx = vol = float("nan")
            if case == "ball":
                if mesh.euler_characteristic() != 2:
                    raise AssertionError(f"{case}/{method}: Euler characteristic {mesh.euler_characteristic()}")
                r_eq = (3 * len(x) * S**3 / (4 * np.pi)) ** (1 / 3)
                d = np.linalg.norm(mesh.vertices, axis=1) - r_eq
                rms, mx = float(np.sqrt(np.mean(d**2)) / S), float(np.abs(d).max() / S)
                vol = mesh.volume() / (len(x) * S**3) - 1
                if not (rms < 0.5 and abs(vol) < 0.03):
                    raise AssertionError(f"{case}/{method}: rms {rms} s, volume error {vol}; not recording")
            rec.record(method, len(x), m.seconds, error=rms if case == "ball" else None, measurement=m,
                       notes={"case": case, "triangles": len(mesh.triangles), "max_dist_s": f"{mx:.3g}",
                              "volume_error": f"{vol:.3g}"})
            print(f"{case:6s} {method:15s} {len(x):9d} {m.seconds:8.3f} {m.other_load:5.2f} {len(mesh.triangles):9d} "
                  f"{rms:6.3f} {mx:6.3f} {vol:8.4f}" + ("  (disturbed)" if m.disturbed else ""), flush=True)


if __name__ == "__main__":
    main()
