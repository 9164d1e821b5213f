"""The ``kinema`` command: run scene files, sweep their parameters, list the examples.

    kinema run SCENE.toml --out DIR [--frames N] [--resume] [--set KEY=VALUE ...] [--quick]
    kinema sweep SCENE.toml --param solver.dt=1e-3,5e-4 [--param ...] --out DIR [--scheduler ADDR]
    kinema view OUT_DIR
    kinema list [--keys]
    kinema info
"""

from __future__ import annotations

import argparse
import sys

EPILOG = """\
examples:
  kinema list                                   the example scenes shipped with kinema
  kinema run smoke_plume --out out/smoke        an example by name (or a path to a .toml)
  kinema run dam_break --out out/dam --frames 30 --set solver.spacing=0.04
  kinema run dam_break --out out/dam --frames 60 --resume    continue to 60 frames
  kinema sweep vortex_merge --quick --param substeps=1,2,4 --out out/sweep
Ctrl-C stops a run cleanly; --resume continues it bit for bit from DIR/checkpoint.npz.
Scene file format: README.md, section "Scenes"."""


def _overrides(items):
    from kinema.scenes.scene import parse_value

    pairs = []
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"kinema: --set expects KEY=VALUE (e.g. solver.resolution=[32,48]), got {item!r}")
        pairs.append((key.strip(), parse_value(value.strip())))
    return pairs


def _parser():
    p = argparse.ArgumentParser(prog="kinema", description="Run kinema scene files: frames, video and data out.",
                                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def scene_args(q):
        q.add_argument("scene", help="a scene file (.toml) or the name of an example scene")
        q.add_argument("--frames", type=int, default=None,
                       help="total frames including frame 0 (default: duration * fps + 1)")
        q.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="override a scene value, e.g. --set solver.resolution=[64,96] (repeatable)")
        q.add_argument("--quick", action="store_true", help="apply the scene's [quick] table (a short test run)")
        q.add_argument("--threads", type=int, default=None, help="OpenMP threads")

    r = sub.add_parser("run", help="run a scene into a folder", description="Run a scene: frames (PNG), "
                       "video (MP4), VTU/PLY/VTI data and a checkpoint in --out.")
    scene_args(r)
    r.add_argument("--out", default=None, help="output folder (default: out/<scene file name>)")
    r.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--view", action="store_true", help="show the simulation live in a window instead "
                   "(kinema[viewer]; writes no files)")

    s = sub.add_parser("sweep", help="run a scene for every combination of parameter values (Dask)")
    scene_args(s)
    s.add_argument("--param", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a key path and its values (a bare key means solver.KEY); repeat for a grid")
    s.add_argument("--out", default="sweep_output", help="output folder (sweep.csv, sweep.png, run_NNN/)")
    s.add_argument("--scheduler", default=None, help="address of a Dask scheduler (default: a local cluster)")
    s.add_argument("--workers", type=int, default=2, help="workers of the local cluster")

    v = sub.add_parser("view", help="scrub through a finished run's VTU/PLY/VTI files in a window (kinema[viewer])")
    v.add_argument("out", help="the run's output folder")

    lst = sub.add_parser("list", help="list the example scenes shipped with kinema")
    lst.add_argument("--keys", action="store_true", help="also list every solver's options and object types")
    sub.add_parser("info", help="how kinema was built (compiler, OpenMP, Eigen, CHOLMOD, BLAS) and threads")
    return p


def _list(keys):
    from kinema.scenes import adapters, examples
    from kinema.scenes.scene import Scene
    from kinema.scenes.schema import describe

    for name, path in examples().items():
        scene = Scene.load(path)
        desc = scene.config["scene"]["description"]
        print(f"{name:16s} {scene.solver:10s} {desc}")
        print(f"{'':16s} {path}")
    if keys:
        for name in adapters.ADAPTERS:
            mod = adapters.load(name)
            print(f"\n[solver] type = \"{name}\"")
            print("\n".join(describe(mod.SOLVER)))
            for kind, table in mod.OBJECTS.items():
                print(f"  [[objects]] type = \"{kind}\": {table.doc}")
                print("\n".join(describe(table, "    ")))


def main(argv=None):
    args = _parser().parse_args(argv)
    import kinema as km
    from kinema.scenes import SceneError, resolve

    if args.command == "info":
        for key, value in km.build_info().items():
            print(f"{key:12s} {value}")
        print(f"{'version':12s} {km.__version__}")
        return 0
    if args.command == "list":
        _list(args.keys)
        return 0
    if args.command == "view":
        from kinema.viewer import cli_view

        return cli_view(args.out)
    if args.threads is not None:
        km.set_num_threads(args.threads)
    try:
        path = resolve(args.scene)
        overrides = _overrides(args.set)
        if args.command == "sweep":
            from kinema.scenes.sweep import parse_param, sweep

            params = dict(parse_param(p) for p in args.param)
            sweep(path, params, args.out, frames=args.frames, quick=args.quick, overrides=overrides,
                  scheduler=args.scheduler, workers=args.workers, log=lambda m: print(m, file=sys.stderr))
            return 0
        scene = km.Scene.load(path, overrides=overrides, quick=args.quick)
        if args.view:
            from kinema.viewer import cli_view

            return cli_view(scene)
        out = args.out or f"out/{path.stem}"
        scene.run(out, args.frames, resume=args.resume, progress=not args.no_progress)
    except (SceneError, ValueError, FileNotFoundError) as exc:
        print(f"kinema: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"kinema: interrupted; the frames written are kept, continue with --resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
