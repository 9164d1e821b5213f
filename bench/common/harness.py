"""Timing harness for kinema's benchmarks: trustworthy wall times on a shared, noisy machine.

Every timed call is measured together with the CPU load that OTHER processes put on the
machine during the timed window, so that a figure taken while a neighbour was compiling is
recognised and measured again instead of being recorded:

    other_load = (busy CPU seconds of the whole machine - CPU seconds of this process) / wall

in cores (0 = nobody else ran, 1 = another process kept one core busy all the time). The
machine's busy time comes from the first line of /proc/stat (user + nice + system + irq +
softirq + steal; steal counts because a hypervisor gave that time to someone else), this
process's own time from ``time.process_time`` plus ``resource.getrusage(RUSAGE_CHILDREN)`` (so
the threads of OpenMP, BLAS or Taichi and any waited-for subprocess count as ours).

/proc/stat advances in clock ticks (10 ms with USER_HZ = 100) per CPU, so the reading of a
window shorter than about 0.1 s is coarse; ``measure`` does not call a run disturbed on the
strength of the tick rounding alone (see ``Run.load_uncertainty``), and such short calls are
better timed with ``min_of`` > 1.

Typical use (scripts in bench/ import this module as ``harness``):

    rec = Recorder("bench/out/poisson.csv", benchmark="poisson3d_dirichlet")
    m = measure(lambda: km.poisson.solve(f, h, tol=1e-6), min_of=3)
    u, info = m.value
    rec.record("kinema-mgpcg", f.shape, m.seconds, error=info.residual,
               iterations=info.iterations, measurement=m)
    plot_work_precision(rec.path, "bench/out/poisson.png", benchmark="poisson3d_dirichlet")
"""

from __future__ import annotations

import csv
import datetime
import os
import resource
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Optional, Sequence, Union

#: A run is disturbed when other processes used more than this many cores during it.
DEFAULT_MAX_LOAD = 0.25
#: Timed runs made at most for one measurement (disturbed runs included).
DEFAULT_MAX_TRIES = 5
#: Before a retry, wait at most this long for the machine to become quiet again [s].
DEFAULT_QUIET_TIMEOUT = 30.0

CSV_COLUMNS = (
    "benchmark",
    "method",
    "size",
    "threads",
    "seconds",
    "error",
    "iterations",
    "other_load",
    "repeats",
    "commit",
    "timestamp",
    "notes",
)

_CLOCK_TICK = 1.0 / os.sysconf("SC_CLK_TCK")
_CPU_COUNT = os.cpu_count() or 1


# ------------------------------------------------------------------ load sampling


@dataclass(frozen=True)
class CpuSample:
    """A snapshot of the machine's busy CPU time and this process's own CPU time.

    machine_busy: CPU seconds all CPUs spent busy since boot (from /proc/stat).
    own: CPU seconds this process (all its threads) and its waited-for children used.
    wall: time.perf_counter() at the snapshot [s].
    """

    machine_busy: float
    own: float
    wall: float


def _machine_busy_seconds() -> float:
    with open("/proc/stat", "rb") as stat:
        fields = stat.readline().split()
    # cpu user nice system idle iowait irq softirq steal guest guest_nice; guest time is
    # already included in user and nice, idle and iowait are the only idle states.
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[1:9])
    return (user + nice + system + irq + softirq + steal) * _CLOCK_TICK


def _own_cpu_seconds() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def sample_cpu() -> CpuSample:
    """Takes a CpuSample now (wall time read last, busy time first, to keep the window tight)."""
    busy = _machine_busy_seconds()
    own = _own_cpu_seconds()
    return CpuSample(machine_busy=busy, own=own, wall=time.perf_counter())


def other_load(before: CpuSample, after: CpuSample) -> float:
    """Cores used by other processes between two samples (never negative)."""
    wall = after.wall - before.wall
    if wall <= 0.0:
        return 0.0
    others = (after.machine_busy - before.machine_busy) - (after.own - before.own)
    return max(0.0, others / wall)


def load_uncertainty(wall: float) -> float:
    """How far tick rounding in /proc/stat can move an other_load reading over `wall` seconds [cores]."""
    return 2.0 * _CPU_COUNT * _CLOCK_TICK / wall if wall > 0.0 else float("inf")


def wait_for_quiet(max_load: float = DEFAULT_MAX_LOAD, window: float = 0.5,
                   timeout: float = DEFAULT_QUIET_TIMEOUT) -> float:
    """Sleeps in `window`-second steps until other processes use at most `max_load` cores.

    Returns the load of the last window (possibly still above `max_load` if `timeout` seconds
    passed first). This process sleeps meanwhile, so the reading is purely the neighbours'.
    """
    deadline = time.perf_counter() + timeout
    while True:
        before = sample_cpu()
        time.sleep(window)
        load = other_load(before, sample_cpu())
        if load <= max_load or time.perf_counter() >= deadline:
            return load


# ------------------------------------------------------------------ measuring


@dataclass(frozen=True)
class Run:
    """One timed call: wall [s], other processes' load [cores], and the figure it is ranked by."""

    wall: float
    other_load: float
    figure: float
    disturbed: bool


@dataclass(frozen=True)
class Measurement:
    """The kept run of a measurement and how it was obtained.

    seconds: the figure of the kept run [s] (its wall time unless `measure` got a `figure`).
    wall: wall time of the kept call [s].
    other_load: cores other processes used during the kept call.
    repeats: timed calls made in all, disturbed ones included.
    disturbed: True when every call was disturbed; the least disturbed one was kept.
    value: what the kept call returned.
    runs: every call, in order.
    waited: seconds spent waiting for a quiet machine between calls.
    """

    seconds: float
    wall: float
    other_load: float
    repeats: int
    disturbed: bool
    value: Any = field(repr=False)
    runs: tuple = field(repr=False)
    waited: float = 0.0


def measure(fn: Callable[[], Any], *, min_of: int = 1, max_load: float = DEFAULT_MAX_LOAD,
            max_tries: int = DEFAULT_MAX_TRIES, figure: Optional[Callable[[Any, float], float]] = None,
            warmup: bool = False, quiet_timeout: float = DEFAULT_QUIET_TIMEOUT) -> Measurement:
    """Times `fn()` until `min_of` undisturbed calls were made, and keeps the best of them.

    A call is disturbed when other processes used more than `max_load` cores during it (beyond
    the tick rounding of /proc/stat). A disturbed call is repeated, after waiting up to
    `quiet_timeout` seconds for the machine to calm down, until `min_of` undisturbed calls
    exist or `max_tries` calls were made. The kept call is the undisturbed one with the
    smallest figure (min-of-k); if all were disturbed, the least disturbed one, flagged.

    figure(value, wall) -> seconds picks what is ranked and reported when the wall time of the
    whole call is not the quantity of interest (for instance a solver phase the callee timed
    itself, such as a steady-state solve after a JIT-compiled first one); default: wall.
    warmup: make one untimed call first (page faults, lazy imports, caches).
    Only the kept call's return value is held, so big results do not pile up.
    """
    if min_of < 1:
        raise ValueError(f"min_of: expected an integer >= 1, got {min_of!r}")
    max_tries = max(max_tries, min_of)
    if warmup:
        fn()
    runs = []
    best_value = None
    best_run: Optional[Run] = None
    waited = 0.0
    undisturbed = 0
    while len(runs) < max_tries and undisturbed < min_of:
        before = sample_cpu()
        value = fn()
        after = sample_cpu()
        wall = after.wall - before.wall
        load = other_load(before, after)
        disturbed = load - load_uncertainty(wall) > max_load
        run = Run(wall=wall, other_load=load,
                  figure=wall if figure is None else float(figure(value, wall)), disturbed=disturbed)
        runs.append(run)
        undisturbed += not disturbed
        if best_run is None or _better(run, best_run):
            best_run, best_value = run, value
        del value
        if disturbed and len(runs) < max_tries:
            start = time.perf_counter()
            wait_for_quiet(max_load, timeout=quiet_timeout)
            waited += time.perf_counter() - start
    return Measurement(seconds=best_run.figure, wall=best_run.wall, other_load=best_run.other_load,
                       repeats=len(runs), disturbed=best_run.disturbed, value=best_value,
                       runs=tuple(runs), waited=waited)


def best_of(fn: Callable[[], Any], reps: int) -> float:
    """The shortest wall time [s] of ``reps`` calls of ``fn`` (for short kernels timed in a loop,
    where measure()'s load bookkeeping would cost more than the call)."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def combine(measurements) -> Measurement:
    """One Measurement from several of the same call (for instance taken in rounds alternated
    with a peer's, so that a drift of the machine's speed over minutes cannot favour either):
    the kept run is chosen among all their kept runs as `measure` chooses; repeats, runs and
    waiting add up."""
    measurements = list(measurements)
    if not measurements:
        raise ValueError("measurements: expected at least one Measurement")
    best = measurements[0]
    for m in measurements[1:]:
        if _better(Run(m.wall, m.other_load, m.seconds, m.disturbed),
                   Run(best.wall, best.other_load, best.seconds, best.disturbed)):
            best = m
    return Measurement(seconds=best.seconds, wall=best.wall, other_load=best.other_load,
                       repeats=sum(m.repeats for m in measurements), disturbed=best.disturbed,
                       value=best.value, runs=tuple(r for m in measurements for r in m.runs),
                       waited=sum(m.waited for m in measurements))


def with_cpu(fn: Callable[[], Any]) -> Callable[[], tuple]:
    """fn wrapped to return (fn's value, CPU seconds this process used during the call): all its
    threads (OpenMP, BLAS, a peer's thread pool) and waited-for children. A second figure, the
    work done, which other processes' load disturbs far less than the wall time (with one thread
    it is the wall time a quiet machine would give; with several, spin-waiting inflates it)."""
    def run():
        start = _own_cpu_seconds()
        value = fn()
        return value, _own_cpu_seconds() - start
    return run


def _better(run: Run, best: Run) -> bool:
    if run.disturbed != best.disturbed:
        return not run.disturbed
    if run.disturbed:
        return run.other_load < best.other_load
    return run.figure < best.figure


def run_google_benchmark(binary: Union[str, Path], benchmark_filter: str = ".", *,
                         repetitions: int = 3, interleave: bool = False,
                         max_load: float = DEFAULT_MAX_LOAD,
                         max_tries: int = DEFAULT_MAX_TRIES) -> Measurement:
    """Runs a Google Benchmark program under `measure` and returns its parsed JSON report.

    The whole program run is one timed window, repeated when other processes loaded the
    machine. measurement.value is the list of per-repetition entries of the report (aggregate
    rows dropped), each a dict with 'name', 'real_time', 'time_unit' and the counters, e.g.
    'bytes_per_second', 'GB' (a rate) for the STREAM triad of bench/cpp/bench_stream.cpp.
    measurement.seconds is the wall time of the kept program run, not of one benchmark.
    With `interleave`, the repetitions of all selected benchmarks run in one random order
    (Google Benchmark's random interleaving), so that figures meant to be compared as a ratio
    sample the same stretch of a drifting host rather than consecutive blocks of it.
    """
    import json

    command = [str(binary), f"--benchmark_filter={benchmark_filter}", "--benchmark_format=json",
               f"--benchmark_repetitions={int(repetitions)}"]
    if interleave:
        command.append("--benchmark_enable_random_interleaving=true")

    def run():
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        return [b for b in json.loads(done.stdout)["benchmarks"] if b.get("run_type") != "aggregate"]

    return measure(run, max_load=max_load, max_tries=max_tries)


# ------------------------------------------------------------------ provenance


def default_threads() -> int:
    """Thread count a kinema figure runs with: kinema.get_num_threads(), else OMP_NUM_THREADS, else the CPUs."""
    try:
        import kinema

        return int(kinema.get_num_threads())
    except (ImportError, AttributeError):
        pass
    env = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    return int(env) if env.isdigit() and int(env) > 0 else _CPU_COUNT


def git_commit(path: Union[str, Path, None] = None) -> str:
    """Short hash of the checkout holding `path` (default: this file), '+dirty' if tracked files changed."""
    where = Path(path) if path is not None else Path(__file__).resolve().parent
    if where.is_file():
        where = where.parent
    try:
        head = subprocess.run(["git", "-C", str(where), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(where), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if status else "")


def format_size(size: Union[int, str, Sequence[int]]) -> str:
    """(1024, 1024) -> '1024x1024'; strings and integers pass through."""
    if isinstance(size, str):
        return size
    if isinstance(size, Iterable):
        return "x".join(str(int(n)) for n in size)
    return str(int(size))


def format_notes(notes: Union[None, str, Mapping[str, Any]]) -> str:
    """{'setup': 1.25, 'bc': 'dirichlet'} -> 'setup=1.25; bc=dirichlet' (floats to 4 significant digits)."""
    if notes is None:
        return ""
    if isinstance(notes, str):
        return notes
    parts = []
    for key, value in notes.items():
        parts.append(f"{key}={value:.4g}" if isinstance(value, float) else f"{key}={value}")
    return "; ".join(parts)


# ------------------------------------------------------------------ CSV


class Recorder:
    """Appends benchmark figures to a CSV file with the columns of CSV_COLUMNS.

    path: CSV file (created with a header, parent folders too, if missing).
    benchmark: name written in the `benchmark` column of every row.
    threads: default thread count of the rows (default: default_threads()).
    The commit is read once, when the recorder is made.
    """

    def __init__(self, path: Union[str, Path], benchmark: str, threads: Optional[int] = None):
        self.path = Path(path)
        self.benchmark = benchmark
        self.threads = default_threads() if threads is None else int(threads)
        self.commit = git_commit()
        if self.path.exists() and self.path.stat().st_size > 0:
            with open(self.path, newline="") as existing:
                header = next(csv.reader(existing), None)
            if header is not None and tuple(header) != CSV_COLUMNS:
                raise ValueError(f"path: {self.path} has columns {header}, expected {list(CSV_COLUMNS)}")

    def record(self, method: str, size, seconds: float, *, error: Optional[float] = None,
               iterations: Optional[int] = None, threads: Optional[int] = None,
               measurement: Optional[Measurement] = None, notes=None) -> dict:
        """Appends one row and returns it. other_load and repeats come from `measurement`.

        A measurement whose calls were all disturbed is still recorded, with 'disturbed' in its
        notes, so that the reader sees the figure is not trustworthy.
        """
        note_text = format_notes(notes)
        if measurement is not None and measurement.disturbed:
            note_text = "; ".join(filter(None, ["disturbed", note_text]))
        row = {
            "benchmark": self.benchmark,
            "method": method,
            "size": format_size(size),
            "threads": self.threads if threads is None else int(threads),
            "seconds": f"{seconds:.6g}",
            "error": "" if error is None else f"{error:.6g}",
            "iterations": "" if iterations is None else int(iterations),
            "other_load": "" if measurement is None else f"{measurement.other_load:.3f}",
            "repeats": 1 if measurement is None else measurement.repeats,
            "commit": self.commit,
            "timestamp": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "notes": note_text,
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        new_file = not self.path.exists() or self.path.stat().st_size == 0
        with open(self.path, "a", newline="") as out:
            writer = csv.DictWriter(out, fieldnames=CSV_COLUMNS)
            if new_file:
                writer.writeheader()
            writer.writerow(row)
        return row


def read_rows(path: Union[str, Path]) -> list:
    """The rows of a benchmark CSV as dicts of strings."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ------------------------------------------------------------------ plotting


def plot_work_precision(csv_path: Union[str, Path], out_path: Union[str, Path], *,
                        benchmark: Optional[str] = None, size: Optional[str] = None,
                        title: Optional[str] = None) -> Path:
    """Work-precision plot: wall time against achieved error, log-log, one series per method.

    Rows without an error are skipped; rows are filtered by `benchmark` and `size` when given.
    When the remaining rows span several sizes, each (method, size) pair is its own series.
    The title names the benchmark, the thread counts and the commits the figures came from.
    Written with matplotlib's Agg backend (no display needed); returns the image path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in read_rows(csv_path)
            if r["error"] and (benchmark is None or r["benchmark"] == benchmark)
            and (size is None or r["size"] == size)]
    if not rows:
        raise ValueError(f"csv_path: no rows with an error in {csv_path} "
                         f"for benchmark={benchmark!r}, size={size!r}")
    several_sizes = len({r["size"] for r in rows}) > 1
    series: dict = {}
    for r in rows:
        label = f"{r['method']} {r['size']}" if several_sizes else r["method"]
        series.setdefault(label, []).append((float(r["error"]), float(r["seconds"])))

    fig, ax = plt.subplots(figsize=(7, 5))
    for label, points in sorted(series.items()):
        points.sort()
        ax.loglog([p[0] for p in points], [p[1] for p in points], "o-", label=label)
    ax.set_xlabel("error")
    ax.set_ylabel("wall time [s]")
    ax.invert_xaxis()  # more accuracy to the right
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    threads = ",".join(sorted({r["threads"] for r in rows}))
    commits = ",".join(sorted({r["commit"] for r in rows}))
    names = ",".join(sorted({r["benchmark"] for r in rows}))
    heading = title or f"{names}" + (f" {size}" if size else "")
    ax.set_title(f"{heading}\nthreads {threads}, commit {commits}", fontsize="medium")
    fig.tight_layout()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
