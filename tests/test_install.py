"""What `pip install .` gives a user: a plain virtual environment (no extras) with the wheel that
scripts/setup.sh built runs every shipped scene, `kinema sweep` without Dask says in one line
what to install, and `kinema --help` points at nothing a pip user lacks. The build must not
write into the source tree (a read-only checkout installs): the configuration is checked by
default, a real build of a copy of the checkout in the slow run."""

import os
import shutil
import subprocess
import sys
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

from kinema.scenes import examples

ROOT = Path(__file__).resolve().parents[1]


def _wheel(tmp_path_factory):
    """The wheel scripts/setup.sh built (build/dist), or one built now from the checkout."""
    given = os.environ.get("KINEMA_WHEEL")
    if given:
        return Path(given)
    found = sorted((ROOT / "build" / "dist").glob("kinema-*.whl"))
    if found:
        return found[-1]
    if not (ROOT / "pyproject.toml").exists():
        pytest.skip("neither a built wheel nor the source tree is available")
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                    str(ROOT)], check=True)
    return next(out.glob("kinema-*.whl"))


def _base_requirements(wheel):
    """The wheel's Requires-Dist lines without extras: what a plain install brings."""
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode().splitlines()
    return sorted(line for line in lines if line.startswith("Requires-Dist:") and "extra ==" not in line)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """A virtual environment with kinema's wheel and its base dependencies only. It is kept in
    build/plain-venv between runs while the wheel's base requirements stay the same (only the
    wheel is reinstalled), so that the test costs its full install once."""
    wheel = _wheel(tmp_path_factory)
    build = ROOT / "build"
    env = build / "plain-venv" if os.access(build, os.W_OK) else tmp_path_factory.mktemp("plain") / "venv"
    stamp = env / "kinema-requirements.txt"
    wanted = "\n".join(_base_requirements(wheel))
    python = str(env / "bin" / "python")
    if not stamp.exists() or stamp.read_text() != wanted:
        shutil.rmtree(env, ignore_errors=True)
        venv.create(env, with_pip=True, symlinks=True)
        pip = subprocess.run([python, "-m", "pip", "install", "-q", str(wheel)], capture_output=True, text=True,
                             timeout=900)
        assert pip.returncode == 0, pip.stderr[-3000:]
        stamp.write_text(wanted)
    else:
        pip = subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", "--force-reinstall", str(wheel)],
                             capture_output=True, text=True, timeout=900)
        assert pip.returncode == 0, pip.stderr[-3000:]
    check = subprocess.run([python, "-m", "pip", "check"], capture_output=True, text=True)
    assert check.returncode == 0, check.stdout
    return env


def run(env, *args, **kw):
    return subprocess.run([str(env / "bin" / "kinema"), *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=kw.pop("cwd", None), **kw)


def test_plain_install_has_no_extras(plain):
    probe = subprocess.run([str(plain / "bin" / "python"), "-c",
                            "import importlib.util as u; print(u.find_spec('dask'), u.find_spec('pytest'))"],
                           capture_output=True, text=True, check=True)
    assert probe.stdout.split() == ["None", "None"], "the plain environment is not plain"


def test_plain_install_runs_every_shipped_scene(plain, tmp_path):
    names = list(examples())
    assert len(names) >= 6
    for name in names:
        out = tmp_path / name
        done = run(plain, "run", name, "--quick", "--frames", 3, "--out", out, "--no-progress",
                   "--set", "output.vtu=true", "--set", "output.vti=true", "--set", "output.every=1")
        assert done.returncode == 0, f"{name}: {done.stderr[-2000:]}"
        assert "done: 3 frames" in done.stderr, done.stderr
        assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{k:05d}.png" for k in range(3)], name
        assert (out / "checkpoint.npz").is_file() and list(out.glob("*.pvd")), name


def test_plain_install_sweep_names_what_to_install(plain, tmp_path):
    done = run(plain, "sweep", "vortex_merge", "--quick", "--param", "substeps=1,2", "--out", tmp_path / "s")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'kinema[sweep]'" in lines[0], done.stderr
    assert not (tmp_path / "s").exists()


def test_help_points_at_nothing_a_pip_user_lacks(plain):
    text = run(plain, "--help").stdout + run(plain, "run", "--help").stdout
    assert "README" not in text and "API.md" not in text
    assert "kinema show" in text and "kinema list --keys" in text
    shown = run(plain, "show", "smoke_plume")
    assert shown.returncode == 0 and "[solver]" in shown.stdout


def test_build_directory_is_outside_the_source_tree():
    """scikit-build-core's build-dir, when set in pyproject.toml, is inside the source tree:
    `pip install .` from a read-only checkout would fail. It must be left unset (a temporary
    folder); scripts/setup.sh passes its own for incremental builds."""
    if not (ROOT / "pyproject.toml").exists():
        pytest.skip("no source tree")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "build-dir" not in config["tool"]["scikit-build"]
    meta = config["project"]
    assert not any(d.startswith("dask") for d in meta["dependencies"])
    for needed in ("numpy", "scipy", "matplotlib", "meshio"):
        assert any(d.startswith(needed) for d in meta["dependencies"]), needed


@pytest.mark.slow
def test_build_writes_nothing_into_the_checkout(tmp_path):
    """pip builds a wheel from a copy of the checkout without adding or changing a file in it
    (as root, file modes cannot stop writes, so the tree is compared before and after).

    The build is a whole one (configure and compile in pip's own temporary build folder), the
    C++ core from scratch: about 8 CPU-minutes, 27 minutes of wall time on 2 cores shared with
    other builds (load 10), without a compiler cache (12.5 minutes at load 4 with ccache in the
    environment, its hits not counted); hence the hour's time limit. The copy
    stands at a fixed place (build/readonly-checkout, made afresh each run) so that a compiler
    cache (CMAKE_CXX_COMPILER_LAUNCHER=ccache in the environment) finds the
    objects of an earlier run: the same sources at the same paths compile to a cache hit."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    build = ROOT / "build"
    src = build / "readonly-checkout" if os.access(build, os.W_OK) else tmp_path / "src"
    shutil.rmtree(src, ignore_errors=True)
    for name in filter(None, files.decode().split("\0")):
        target = src / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if (ROOT / name).is_file():
            target.write_bytes((ROOT / name).read_bytes())

    def snapshot():
        return {str(p.relative_to(src)): p.stat().st_mtime_ns for p in src.rglob("*")}

    before = snapshot()
    for p in src.rglob("*"):
        p.chmod(0o555 if p.is_dir() else 0o444)
    try:
        subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                        "-w", str(tmp_path / "dist"), str(src)], check=True, timeout=3600)
    finally:
        for p in src.rglob("*"):
            p.chmod(0o755 if p.is_dir() else 0o644)
    after = snapshot()
    shutil.rmtree(src, ignore_errors=True)
    assert after == before
    assert list((tmp_path / "dist").glob("kinema-*.whl"))
