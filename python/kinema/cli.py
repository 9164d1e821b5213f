"""The ``kinema`` command: run scene files, sweep their parameters, list the examples.

    kinema run SCENE.toml --out DIR [--frames N] [--resume] [--set KEY=VALUE ...] [--quick]
    kinema sweep SCENE.toml --param solver.dt=1e-3,5e-4 [--param ...] --out DIR [--scheduler ADDR]
    kinema view OUT_DIR
    kinema list [--keys]
    kinema show NAME
    kinema info

Every error the user can cause (a scene file, a value, a path, a damaged checkpoint, a full or
read-only disk, a size that does not fit in memory) ends in one line ``kinema: ...`` naming the
key or path and exit status 2; Ctrl-C exits with 130 and a failing simulation with 1.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

EPILOG = """\
examples:
  kinema list                                   the example scenes shipped with kinema
  kinema run smoke_plume --out out/smoke        an example by name (or a path to a .toml)
  kinema run dam_break --out out/dam --frames 30 --set solver.spacing=0.04
  kinema run dam_break --out out/dam --frames 60 --set solver.spacing=0.04 --resume
                                                continue to 60 frames (the same --set)
  kinema sweep vortex_merge --quick --param substeps=1,2,4 --out out/sweep
  kinema sweep soft_body --quick --param "objects[0].youngs_modulus=2e5,5e5" --out out/stiff
                                                (a bare --param KEY is a solver option, or the key of
                                                 the one object that has it)
Ctrl-C stops a run cleanly; --resume continues it bit for bit from DIR/checkpoint.npz. A run
into a folder holding an earlier run replaces it (and says so).
Scene files: `kinema show smoke_plume` prints an example to start from; `kinema list --keys`
lists every table, key, default and unit; the user guide is in the docs/ folder of the source
repository."""


def _overrides(items):
    from kinema.scenes.scene import parse_value

    pairs = []
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY=VALUE (e.g. solver.resolution=[32,48]), got {item!r}")
        pairs.append((key.strip(), parse_value(value.strip())))
    return pairs


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``kinema run: --threads: ...``) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _count(low, high, what):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer {what}, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer {what} ({low}..{high}), got {value}")
        return value
    return parse


def _parser():
    p = _Parser(prog="kinema", description="Run kinema scene files: frames, video and data out.",
                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    def scene_args(q):
        q.add_argument("scene", help="a scene file (.toml) or the name of an example scene")
        q.add_argument("--frames", type=_count(1, 10**6, ">= 1"), default=None,
                       help="total frames including frame 0 (default: duration * fps + 1)")
        q.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="override a scene value, e.g. --set solver.resolution=[64,96] (repeatable)")
        q.add_argument("--quick", action="store_true", help="apply the scene's [quick] table (a short test run)")
        q.add_argument("--threads", type=_count(1, 4096, ">= 1"), default=None, help="OpenMP threads")

    r = sub.add_parser("run", help="run a scene into a folder", description="Run a scene: frames (PNG), "
                       "video (MP4), VTU/PLY/VTI data and a checkpoint in --out.")
    scene_args(r)
    r.add_argument("--out", default=None, help="output folder (default: out/<scene file name>)")
    r.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    r.add_argument("--no-progress", action="store_true", help="no progress bar (the final line is still printed)")
    r.add_argument("--view", action="store_true", help="show the simulation live in a window instead "
                   "(kinema[viewer]; writes no files)")

    s = sub.add_parser("sweep", help="run a scene for every combination of parameter values (Dask)")
    scene_args(s)
    s.add_argument("--param", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a key path and its values, e.g. objects[0].youngs_modulus=1e5,2e5 (a bare KEY is "
                        "a solver option, or the key of the one object that has it); repeat for a grid")
    s.add_argument("--out", default="sweep_output", help="output folder (sweep.csv, sweep.png, run_NNN/)")
    s.add_argument("--scheduler", default=None, help="address of a Dask scheduler (default: a local cluster)")
    s.add_argument("--workers", type=_count(1, 256, ">= 1"), default=2, help="workers of the local cluster")

    v = sub.add_parser("view", help="scrub through a finished run's VTU/PLY/VTI files in a window (kinema[viewer])")
    v.add_argument("out", help="the run's output folder")

    lst = sub.add_parser("list", help="list the example scenes shipped with kinema")
    lst.add_argument("--keys", action="store_true", help="also list every solver's options and object types")
    show = sub.add_parser("show", help="print an example scene file (a template for your own)")
    show.add_argument("name", help="an example scene (kinema list)")
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


def _where(exc):
    """The path of an OSError, with a temporary file's name mapped to the file it stood for."""
    name = exc.filename
    if name is None:
        return ""
    path = Path(str(name))
    m = re.fullmatch(r"\.(.+)\.[^.]+\.tmp", path.name)
    return f"{path.with_name(m.group(1)) if m else path}: "


def main(argv=None):
    args = _parser().parse_args(argv)
    import kinema as km
    from kinema.scenes import SceneError, resolve

    if args.command == "info":
        info = km.build_info()
        info.setdefault("version", km.__version__)
        for key, value in info.items():
            print(f"{key:12s} {value}")
        return 0
    if args.command == "list":
        _list(args.keys)
        return 0
    if args.command == "view":
        from kinema.viewer import cli_view

        return cli_view(args.out)
    try:
        if args.command == "show":
            path = resolve(args.name)
            print(Path(path).read_text(), end="")
            return 0
        if args.threads is not None:
            km.set_num_threads(args.threads)
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
        result = scene.run(out, args.frames, resume=args.resume, progress=not args.no_progress)
        if args.no_progress:
            for note in result.notes:
                print(f"kinema: {note}", file=sys.stderr)
            print(result.summary(), file=sys.stderr)
    except KeyboardInterrupt:
        print("kinema: interrupted; the frames written are kept, continue with --resume", file=sys.stderr)
        return 130
    except (SceneError, ValueError, FileNotFoundError, ImportError) as exc:
        print(f"kinema: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("kinema: out of memory; make the scene smaller (solver.resolution, solver.spacing, "
              "objects[*].resolution or particles, output.width)", file=sys.stderr)
        return 2
    except RecursionError:
        print("kinema: a value is nested too deeply", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"kinema: {_where(exc)}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except km.KinemaError as exc:
        print(f"kinema: the simulation failed: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
