"""Two accuracy checks of km.sph as reproducible runs (2D): the dam-break front against Martin and
Moyce (1952) and a viscous column at rest. Prints one line per case.

  python bench/sph/sph_dam_front_and_rest.py dam --method dfsph
  python bench/sph/sph_dam_front_and_rest.py rest --method dfsph
  python bench/sph/sph_dam_front_and_rest.py record after     # both cases, both methods, into
                                                       # bench/out/sph_dam_front_and_rest_after.json
  python bench/sph/sph_dam_front_and_rest.py plot before after        # bench/out/sph_dam_front_and_rest.png
  python bench/sph/sph_dam_front_and_rest.py viscous-spectrum         # largest eigenvalue of the viscosity term

Dam break: the issue's square column a = 0.1 m of 40 x 40 particles in the tank 5a x 2a,
nu = 1e-4, 10 steps of 5e-5 s, then advance() to each time; front = x of the third-farthest
particle + s/2 (the reference data are for a column of height 2a: the issue compares to them).
Column at rest: tank 1 x 1.2 m, water 1 x 0.5 m, spacing 0.02, nu = 0.01, settled for 1 s by
zeroing v every 0.02 s, then 1 s free.
"""
import argparse
import time

import numpy as np

import kinema as km

G = 9.81


def dam(method, n=40, a=0.1, tol=1e-3, warmup=True):
    s = a / n
    x = km.sph.block([0, 0], [a, a], s)
    f = km.sph.Fluid(x, s, method=method, domain=([0, 0], [5 * a, 2 * a]), viscosity=1e-4, tol=tol)
    if warmup:
        for _ in range(10):
            f.step(5e-5)
    out = []
    for T in (0.83, 1.2, 2.0, 2.5):
        f.advance(T / np.sqrt(2 * G / a) - f.time)
        xs = np.sort(f.x[:, 0])
        out.append((T, (xs[-3] + s / 2) / a, np.percentile(f.x[:, 0], 98) / a))
    return out


def rest(method, dim=2, s=0.02, nu=0.01, settle=1.0, free=1.0, width=1.0, depth=0.5, history=None):
    lo, hi = [0] * dim, [width, 1.2] + ([width] if dim == 3 else [])
    up = [width, depth] + ([width] if dim == 3 else [])
    x = km.sph.block([0] * dim, up, s)
    f = km.sph.Fluid(x, s, method=method, domain=(lo, hi), viscosity=nu)
    while f.time < settle - 1e-9:
        f.advance(0.02)
        f.v[:] = 0
    its, steps = [], 0
    t_end = f.time + free
    while f.time < t_end - 1e-12:
        st = f.step(min(f.stable_dt(), t_end - f.time))
        its.append(st["iterations"])
        if history is not None:
            history.append((f.time, f.kinetic_energy(), st["iterations"]))
    f.density_error()
    H = f.x[:, 1].max() + s / 2
    y, p = f.x[:, 1], f.pressure
    if method == "wcsph":
        pass
    mask = (y > 3 * s) & (y < H - 5 * s)
    ref = 1000 * G * (H - y[mask])
    ratio = float(np.median(p[mask] / ref))
    bottom = y < 3 * s
    return dict(ke=f.kinetic_energy(), vmax=float(np.abs(f.v).max()), its=float(np.mean(its)),
                its_max=int(max(its)), p_ratio=ratio,
                p_bottom=float(np.mean(p[bottom]) / (1000 * G * H)), H=H)


def viscous_spectrum(d, jitter, n=8, seed=0):
    """Largest |eigenvalue| of the viscosity term (kernels.h viscosity_term, nu = 1, spacing 1)
    on a periodic lattice of n^d particles displaced by jitter spacings at random."""
    s, h = 1.0, 2.0
    idx = np.array(np.meshgrid(*[np.arange(n)] * d, indexing="ij")).reshape(d, -1).T
    x = idx * s + jitter * np.random.default_rng(seed).standard_normal((n**d, d))
    N, L = len(x), n * s
    A = np.zeros((N * d, N * d))
    for i in range(N):
        dx = x[i] - x
        dx -= np.round(dx / L) * L
        r = np.linalg.norm(dx, axis=1)
        for j in np.nonzero((r < h) & (r > 0))[0]:
            g = km.sph.kernel(r[j], h, d, 1) / r[j] * dx[j]
            M = 2 * (d + 2) * s**d / (r[j] ** 2 + 0.01 * h * h) * np.outer(g, dx[j])
            A[i * d:i * d + d, i * d:i * d + d] += M
            A[i * d:i * d + d, j * d:j * d + d] -= M
    return float(np.max(np.abs(np.linalg.eigvals(A))))


def record(label):
    import json
    from pathlib import Path

    out = {"label": label, "commit": label}
    for method in ("wcsph", "dfsph"):
        out[f"dam_{method}"] = dam(method)
        hist = []
        out[f"rest_{method}"] = rest(method, history=hist)
        out[f"rest_{method}"]["H"] = float(out[f"rest_{method}"]["H"])
        out[f"history_{method}"] = hist
    path = Path(__file__).resolve().parents[1] / "out" / f"sph_dam_front_and_rest_{label}.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out))
    print(f"wrote {path}")


def plot(labels):
    import json
    from pathlib import Path

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(__file__).resolve().parents[1] / "out"
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    mm = km.sph.martin_moyce()
    a1.plot(mm[:, 0], mm[:, 1], "ks", label="Martin & Moyce 1952")
    for label, style in zip(labels, ("--", "-")):
        data = json.loads((out / f"sph_dam_front_and_rest_{label}.json").read_text())
        for method, color in (("wcsph", "C0"), ("dfsph", "C3")):
            T, Z, _ = np.array(data[f"dam_{method}"]).T
            a1.plot(T, Z, style, color=color, marker="o", label=f"{method} {label}")
            t, ke, _ = np.array(data[f"history_{method}"]).T
            a2.semilogy(t, np.maximum(ke, 1e-6), style, color=color, label=f"{method} {label}")
    a1.set_xlabel("T = t sqrt(2g/a)")
    a1.set_ylabel("front Z = z/a")
    a1.set_title("2D dam break (issue 15 set-up)")
    a1.legend(fontsize=8)
    a2.set_xlabel("t [s] (free after 1 s of settling)")
    a2.set_ylabel("kinetic energy [J per m]")
    a2.set_title("2D viscous column at rest, nu = 0.01")
    a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "sph_dam_front_and_rest.png", dpi=90)
    print(f"wrote {out / 'sph_dam_front_and_rest.png'}")


if __name__ == "__main__":
    import sys

    if len(sys.argv) > 1 and sys.argv[1] == "record":
        record(sys.argv[2] if len(sys.argv) > 2 else "after")
        sys.exit(0)
    if len(sys.argv) > 1 and sys.argv[1] == "plot":
        plot(sys.argv[2:])
        sys.exit(0)
    if len(sys.argv) > 1 and sys.argv[1] == "viscous-spectrum":
        for d, n in ((2, 10), (3, 6)):
            for jitter in (0.0, 0.1, 0.2):
                lam = max(viscous_spectrum(d, jitter, n, seed) for seed in range(2))
                print(f"{d}D, displacements {jitter:.1f} spacing: lambda_max = {lam:.2f} nu/s^2, "
                      f"forward Euler bound dt < {2 / lam:.3f} s^2/nu")
        sys.exit(0)
    ap = argparse.ArgumentParser()
    ap.add_argument("case", choices=["dam", "rest"])
    ap.add_argument("--method", default="dfsph")
    ap.add_argument("--dim", type=int, default=2)
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--no-warmup", action="store_true")
    args = ap.parse_args()
    t0 = time.time()
    if args.case == "dam":
        for T, Z, Z98 in dam(args.method, tol=args.tol, warmup=not args.no_warmup):
            print(f"{args.method} T={T:.2f} Z={Z:.3f} Z98={Z98:.3f}")
    else:
        print(args.method, rest(args.method, args.dim))
    print(f"{time.time() - t0:.1f} s")
