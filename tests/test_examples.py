"""The programs in examples/ run, small, and write what their docstrings promise. Examples that
show one method are smoke-tested beside that method's tests (tests/test_sph.py runs
sph_dam_break_3d.py, ...); test_every_example_is_smoke_tested checks that none is left without one."""

import re
from pathlib import Path

import numpy as np
import pytest

from load_script import load_script

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
PROGRAMS = sorted(p for p in EXAMPLES.glob("*.py") if not p.name.startswith("_"))  # _*.py: shared by them


def load(name):
    return load_script(EXAMPLES / f"{name}.py")


def test_poisson_heat_writes_fields_video_and_study(tmp_path):
    example = load("poisson_heat")
    assert example.main(["--out", str(tmp_path), "--frames", "2", "--size", "16", "--sizes", "16", "32"]) == 0
    for name in ("poisson_potential.png", "heat/frame_0001.png", "heat_final.vti", "work_precision.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    rows = (tmp_path / "work_precision.csv").read_text().splitlines()
    assert len(rows) > 2 and rows[0].startswith("method,n,seconds,error")
    summary = (tmp_path / "summary.txt").read_text()
    residual = float(re.search(r"max\|f - A phi\|/max\|f\|=(\S+)", summary).group(1))
    assert residual < 1e-8, summary  # the solve ran to tol 1e-10 (relative 2-norm) on 16 x 32 cells


def test_smoke_obstacle_runs_in_2d_and_3d(tmp_path):
    example = load("smoke_obstacle")
    f = example.run(tmp_path, (24, 32), frames=2)
    assert (tmp_path / "smoke" / "frame_0001.png").exists() and (tmp_path / "smoke_final.npz").exists()
    assert f.density.max() > 0 and np.abs(f.divergence()).max() < 1e-4
    g = example.run(tmp_path / "3d", (12, 16, 12), frames=1)
    assert g.density.max() > 0


def test_cloth_and_beam_writes_meshes(tmp_path):
    example = load("cloth_and_beam")
    assert example.main(["--out", str(tmp_path), "--frames", "3", "--cloth", "6", "--cells", "5",
                         "--no-video"]) == 0
    assert len(list((tmp_path / "body").glob("*.vtu"))) == 3
    assert len(list((tmp_path / "cloth").glob("*.obj"))) == 3
    obj = (tmp_path / "body" / "frame_0002.obj").read_text().splitlines()
    faces = sum(line.startswith("f ") for line in obj)
    assert faces == 2 * 2 * (5 * 1 + 5 * 1 + 1 * 1)  # the 5 x 1 x 1-cell beam's surface, 2 triangles a face
    assert (tmp_path / "summary.txt").read_text().startswith("frames 3")


@pytest.mark.parametrize("dim", [2, 3])
def test_diff_sph_droplet_hits_its_target(tmp_path, dim):
    """examples/diff_sph_droplet.py, small: the centre of mass's distance to the target falls by
    1 - lr = 0.3 per iteration (the loss by 0.09) and the plots are written."""
    losses = load("diff_sph_droplet").main(["--out", str(tmp_path), "--iterations", "3", "--steps", "60",
                                           "--dim", str(dim)])
    assert len(losses) == 4 and losses[-1] < 2e-3 * losses[0], losses
    for name in ("sph_droplet_loss.png", "sph_droplet_flight.png"):
        assert (tmp_path / name).stat().st_size > 0, name


def test_every_example_is_smoke_tested():
    """Each examples/*.py is named by a test module (here or beside its method's tests)."""
    tests = "\n".join(p.read_text() for p in Path(__file__).parent.glob("test_*.py"))
    untested = [p.name for p in PROGRAMS
                if f'"{p.name}"' not in tests and f'"{p.stem}"' not in tests]
    assert not untested, f"examples without a smoke test: {untested}"


@pytest.mark.parametrize("path", PROGRAMS, ids=lambda p: p.name)
def test_example_documents_its_command(path):
    """Each example's docstring shows the command that runs it from the repository root."""
    doc = path.read_text().split('"""')[1]
    assert f"examples/{path.name}" in doc, f"{path.name}: no 'examples/{path.name}' command in its docstring"


def test_diff_smoke_target_learns(tmp_path):
    """examples/diff_smoke_target.py, tiny: its plots are written and learning lowers the loss."""
    example = load("diff_smoke_target")
    losses, initial, final = example.main(["--out", str(tmp_path), "--cells", "16", "--steps", "8",
                                           "--iterations", "6", "--learning-rate", "1.0"])
    assert final < 0.8 * initial, (initial, final)
    for name in ("loss.png", "frames.png", "smoke_target.npz"):
        assert (tmp_path / name).stat().st_size > 0, name


def test_diff_smoke_puff_3d_learns(tmp_path):
    """examples/diff_smoke_puff_3d.py, tiny: the puff's centre ends nearer the target."""
    example = load("diff_smoke_puff_3d")
    losses, before, after = example.main(["--out", str(tmp_path), "--cells", "8", "--steps", "8",
                                          "--iterations", "5", "--learning-rate", "4.0"])
    assert after < 0.8 * before, (before, after)
    for name in ("loss.png", "puff.png"):
        assert (tmp_path / name).stat().st_size > 0, name
