"""km.contact kernels side by side with the IPC toolkit's Python bindings (``ipctk``, the
``bench`` extra) on the same meshes and positions, values compared before anything is timed.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contact/kernel_bench.py [--quick] [--out bench/out]

Meshes: a frame of the cube pile and of the cloth on the sphere (examples/contact_scenes.py) in
contact. Kernels, both sides single-threaded, one Python call per mesh each:

* distance: the active set (pairs closer than dhat) with its distances (ipctk:
  ``NormalCollisions.build`` and its minimum distance);
* barrier / gradient / hessian: the same plus the barrier energy / its gradient / its Hessian
  (PSD-projected per contact on both sides, ipctk's ``CLAMP``);
* ccd: the largest intersection-free step along 3x one step's displacement (ipctk: its
  additive CCD, as kinema's, and its default Tight-Inclusion CCD).

Accuracy, checked before timing (the run stops on a mismatch):

* distance: kinema's exact minimum distance equals ipctk's to rounding;
* barrier, gradient, hessian: ipctk's ``BarrierPotential`` (the log barrier of Li et al. 2020
  on squared distances, the same edge mollifier with eps_x from the rest positions) gives the
  same energy, gradient and unprojected Hessian to rounding (the pile's vertex-plane terms,
  which ipctk's mesh has no plane for, are added on its side in numpy);
* ccd: every returned step is checked by kinema's exact intersection test and minimum distance.

Work per timed call (like for like): both sides find their candidate pairs inside every call.
ipctk's calls include ``NormalCollisions.build`` (its broad phase from scratch: a new BVH) or,
for CCD, its swept broad phase; kinema's calls run its broad phase too (BroadPhase::find: box
update, tree descents and the pairs' sort), on trees the scene keeps between calls and refits
to each query's boxes, as its solver does between Newton iterations (a kept structure, not a
kept result: no call reuses a previous call's pairs, distances or values). The Hessian calls
return a scipy CSR matrix on both sides.

One summary line per kernel: CPU time per call on both sides (best of 5 x 20 calls; wall time
beside it), their ratio against the 3x target, and the measured difference; then one line with
every ratio and how many meet the target.

A/B against another build (e.g. main's wheel installed with ``pip install --target DIR``): run
the same command with ``PYTHONPATH=DIR`` (the first line printed names the kinema imported).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
from contact_bench import bench_args, cloth, cpu_seconds, kernel_case, pile  # noqa: E402

import harness  # noqa: E402

import kinema as km  # noqa: E402

TARGET = 3.0
C = km._core.contact


def plane_terms(scene, x, dhat):
    """Energy, gradient and minimum distance of kinema's vertex-plane terms (an ipctk mesh has
    no planes)."""
    e, g, dmin = 0.0, np.zeros_like(x), np.inf
    moving = scene.mass > 0
    for point, n in scene.planes:
        s = (x - point) @ n
        dmin = min(dmin, s[moving].min())
        for v in np.flatnonzero(moving & (s > 0) & (s < dhat)):
            b, b1, _ = C.barrier(s[v] ** 2, dhat**2)
            e += b
            g[v] += b1 * 2 * s[v] * n
    return e, g, dmin


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def compare_values(ipctk, scene, mesh, x0, dhat):
    X = np.asfortranarray(x0)
    c = ipctk.NormalCollisions()
    c.build(mesh, X, dhat)
    out = {}
    pe, pg, plane_min = plane_terms(scene, x0, dhat)
    d_ipc = min(np.sqrt(c.compute_minimum_distance(mesh, X)), plane_min)  # ipctk: squared distance
    d_ours = scene.min_distance(x=x0, radius=dhat)
    out["distance"] = abs(d_ours - d_ipc) / d_ipc
    B = ipctk.BarrierPotential(dhat, 1.0)
    out["barrier"] = rel(scene.barrier_energy(x0), B(c, mesh, X) + pe)
    out["gradient"] = rel(scene.barrier_gradient(x0), B.gradient(c, mesh, X).reshape(-1, 3) + pg)
    H_ours = scene.barrier_hessian(x0, project=False)
    H_ours = H_ours.toarray() if hasattr(H_ours, "toarray") else np.asarray(H_ours)
    H_ipc = B.hessian(c, mesh, X, project_hessian_to_psd=ipctk.PSDProjectionMethod.NONE).toarray()
    # The vertex-plane Hessian blocks (rank one along the normal) are the only kinema terms ipctk
    # lacks: compare off the vertices that touch a plane.
    plane = np.zeros(len(x0), bool)
    for point, n in scene.planes:
        s = (x0 - point) @ n
        plane |= (s > 0) & (s < dhat) & (scene.mass > 0)
    keep = np.repeat(~plane, 3)
    out["hessian"] = rel(H_ours[np.ix_(keep, keep)], H_ipc[np.ix_(keep, keep)])
    # The solver's rank-one Hessian against the clamp (a different matrix, not a mismatch).
    P = scene.barrier_hessian(x0, project="clamp").toarray()
    R = scene.barrier_hessian(x0, project="rank-one").toarray()
    out["rank-one"] = float(np.linalg.norm(R - P) / np.linalg.norm(P))
    return out, len(c)


def run(rec, quick):
    import ipctk

    ipctk.set_num_threads(1)
    cases = [("pile 4 cubes n=3", lambda: pile(4, 3), 40), ("cloth 16x16 on sphere", lambda: cloth(16), 10)]
    if quick:
        cases = [("pile 4 cubes n=2", lambda: pile(4, 2), 40), ("cloth 12x12 on sphere", lambda: cloth(12), 10)]
    summary, ratios = [], []
    for label, make, warm in cases:
        scene, dt = make()
        rest = scene.x.copy()  # kinema's rest positions (the edge mollifier's eps_x): the start
        x0, x1 = kernel_case(scene, dt, warm)
        dhat = scene.config.dhat
        mesh = ipctk.CollisionMesh(np.asfortranarray(rest), np.asfortranarray(scene.edges.astype(np.int32)),
                                   np.asfortranarray(scene.faces.astype(np.int32)))
        X = np.asfortranarray(x0)
        diffs, ipc_count = compare_values(ipctk, scene, mesh, x0, dhat)
        # Values agree to rounding (a few hundred pairs summed; the barrier's log near d = 0
        # amplifies the relative rounding of d by dhat^2 / d): 1e-9 relative is far above that
        # and far below any modelling difference.
        print(f"{label}: values against ipctk (max relative difference): "
              + ", ".join(f"{k} {v:.1e}" for k, v in diffs.items()), flush=True)
        for k, v in diffs.items():
            assert k == "rank-one" or v <= 1e-9, (label, k, v)
        ours = scene._core.constraint_count(x0)
        size = f"{label}, {len(x0)} vertices, {len(scene.faces)} faces"
        B = ipctk.BarrierPotential(dhat, 1.0)

        def build():
            c = ipctk.NormalCollisions()
            c.build(mesh, X, dhat)
            return c

        far = x0 + 3 * (x1 - x0)
        F = np.asfortranarray(far)
        t_ours = scene.max_safe_step(far - x0, x=x0)
        t_add = ipctk.compute_collision_free_stepsize(mesh, X, F, narrow_phase_ccd=ipctk.AdditiveCCD())
        t_tight = ipctk.compute_collision_free_stepsize(mesh, X, F)
        for t in (t_ours, t_add, t_tight):
            y = x0 + t * (far - x0)
            assert not scene.intersections(x=y) and scene.min_distance(x=y) > 0, (label, t)
        kernels = {
            "distance": (lambda: scene._core.constraint_count(x0), lambda: build().compute_minimum_distance(mesh, X)),
            "barrier": (lambda: scene.barrier_energy(x0), lambda: B(build(), mesh, X)),
            "gradient": (lambda: scene.barrier_gradient(x0), lambda: B.gradient(build(), mesh, X)),
            "hessian": (lambda: scene.barrier_hessian(x0, project=True),
                        lambda: B.hessian(build(), mesh, X, project_hessian_to_psd=ipctk.PSDProjectionMethod.CLAMP)),
            # the solver's default matrix (not the clamp ipctk computes: see its difference)
            "hessian-rank-one": (lambda: scene.barrier_hessian(x0, project="rank-one"),
                                 lambda: B.hessian(build(), mesh, X,
                                                   project_hessian_to_psd=ipctk.PSDProjectionMethod.CLAMP)),
            "ccd": (lambda: scene.max_safe_step(far - x0, x=x0),
                    lambda: ipctk.compute_collision_free_stepsize(mesh, X, F, narrow_phase_ccd=ipctk.AdditiveCCD())),
            "ccd-vs-tight-inclusion": (lambda: scene.max_safe_step(far - x0, x=x0),
                                       lambda: ipctk.compute_collision_free_stepsize(mesh, X, F)),
        }
        for kernel, (ours_fn, theirs_fn) in kernels.items():
            mo = harness.measure(ours_fn, min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
            mt = harness.measure(theirs_fn, min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
            co, ct = cpu_seconds(ours_fn), cpu_seconds(theirs_fn)
            if kernel == "hessian-rank-one":
                acc = f"rank-one vs clamp |R - P|_F / |P|_F {diffs['rank-one']:.1e}"
            elif kernel.startswith("ccd"):
                acc = f"t kinema {t_ours:.4f}, ipctk {t_tight if 'tight' in kernel else t_add:.4f}, both intersection-free"
            else:
                acc = f"max rel diff {diffs[kernel]:.1e}"
            notes = {"cpu_ms": f"{co * 1e3:.4f}", "pairs": ours, "accuracy": acc}
            rec.record(f"kinema-{kernel}", size, mo.seconds, measurement=mo, notes=notes)
            rec.record(f"ipctk-{kernel}", size, mt.seconds, measurement=mt,
                       notes={"cpu_ms": f"{ct * 1e3:.4f}", "collisions": ipc_count})
            line = (f"{label:22s} {kernel:22s} kinema {co * 1e3:7.3f} ms cpu ({mo.seconds * 1e3:7.3f} wall)  "
                    f"ipctk {ct * 1e3:7.3f} ms cpu ({mt.seconds * 1e3:7.3f} wall)  ratio {ct / co:5.2f}x cpu "
                    f"({mt.seconds / mo.seconds:5.2f}x wall) {'met' if ct / co >= TARGET else 'NOT met'} "
                    f"| {acc} | load {max(mo.other_load, mt.other_load):.2f}")
            print(line, flush=True)
            summary.append(line)
            ratios.append((label.split()[0], kernel, ct / co))
    print("\nsummary (target: kinema >= 3x faster than ipctk, CPU time):")
    for line in summary:
        print(line)
    # One line: every kernel's CPU-time ratio (ipctk / kinema) at equal values (checked above).
    met = sum(r >= TARGET for _, _, r in ratios)
    print(f"summary: kinema/ipctk cpu ratio (target {TARGET:g}x, values equal to rounding): "
          + ", ".join(f"{case} {kernel} {r:.2f}x" for case, kernel, r in ratios)
          + f"; {met}/{len(ratios)} met")


def main(argv=None):
    args = bench_args(__doc__, argv)
    rec = harness.Recorder(args.out / "contact_kernels.csv", benchmark="contact-kernels")
    print(f"commit {harness.git_commit()}  threads 1  kinema {km.__file__}")
    run(rec, args.quick)


if __name__ == "__main__":
    main()
