"""Issue 15's two symptoms as reproducible runs (2D): the dam-break front against Martin and
Moyce (1952) and a viscous column at rest. Prints one line per case.

  python bench/sph_issue15.py dam --method dfsph
  python bench/sph_issue15.py rest --method dfsph
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


def rest(method, dim=2, s=0.02, nu=0.01, settle=1.0, free=1.0, width=1.0, depth=0.5):
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


if __name__ == "__main__":
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
