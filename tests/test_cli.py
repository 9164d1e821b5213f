"""The `kinema` command: help, info, list and scene errors through kinema.cli.main in this
process; runs (progress, overrides, Ctrl-C by a real SIGINT, then --resume) as real
subprocesses of the installed console script."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import kinema as km
from kinema.cli import main
from kinema.scenes import output, resolve

KINEMA = Path(sys.executable).with_name("kinema")
needs_script = pytest.mark.skipif(not KINEMA.exists(), reason="the kinema console script is not installed")


def kinema(*args, **kw):
    return subprocess.run([str(KINEMA), *map(str, args)], capture_output=True, text=True, timeout=300, **kw)


def test_help_info_and_list(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    for word in ("run", "sweep", "list", "info", "--resume", "--set"):
        assert word in text, word
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert "threads" in text and "cholmod" in text.lower()
    assert main(["list", "--keys"]) == 0
    text = capsys.readouterr().out
    for name in ("smoke_plume", "dam_break", "hanging_cloth", "soft_body", "vortex_merge", "vortex_sheet"):
        assert name in text, name
    assert 'type = "sph"' in text and "spacing" in text


@needs_script
def test_run_writes_files_and_reports_progress(tmp_path):
    out = kinema("run", "vortex_sheet", "--quick", "--frames", 3, "--out", tmp_path, "--set", "output.vtu=true", "--set", "output.every=1")
    assert out.returncode == 0, out.stderr
    assert "3/3 frames" in out.stderr and "steps/s" in out.stderr and "ETA" in out.stderr
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [f"frame_{k:05d}.png" for k in range(3)]
    assert (tmp_path / "video.mp4").stat().st_size > 0
    assert len(list((tmp_path / "vortices").glob("*.vtu"))) == 3


def test_run_reports_scene_errors(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "x"\nduration = 1\n[solver]\ntype = "vortex"\nsubsteps = 0\n'
                   '[[objects]]\ntype = "sheet"\ncenter = [0, 0]\n')
    assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert f"{bad}: solver.substeps: expected an integer >= 1, got an integer 0" in capsys.readouterr().err
    assert main(["run", "no_such_scene"]) == 2
    assert "examples:" in capsys.readouterr().err
    assert main(["run", "vortex_sheet", "--set", "objects[0].particles=few", "--out", str(tmp_path / "o")]) == 2
    assert "objects[0].particles: expected an integer >= 4, got a string 'few'" in capsys.readouterr().err


@needs_script
def test_ctrl_c_keeps_frames_and_resume_continues(tmp_path):
    args = ["run", "vortex_sheet", "--quick", "--out", tmp_path, "--set", "output.mp4=false"]
    proc = subprocess.Popen([str(KINEMA), *map(str, args), "--frames", "400"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (tmp_path / "frames" / "frame_00003.png").exists():
        assert proc.poll() is None and time.time() < deadline, proc.stderr.read() if proc.poll() else "timeout"
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not list(tmp_path.rglob("*.tmp")), "a temporary file was left behind"
    _, meta = output.load_checkpoint(tmp_path / "checkpoint.npz")
    written = sorted((tmp_path / "frames").iterdir())
    assert len(written) == meta["frame"] + 1 and meta["frame"] >= 3
    total = meta["frame"] + 3
    resumed = kinema(*args, "--frames", total, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert len(list((tmp_path / "frames").iterdir())) == total
    km.Scene.load(resolve("vortex_sheet"), quick=True, overrides=[("output.mp4", False)]).run(
        tmp_path / "straight", total, progress=False)
    a, _ = output.load_checkpoint(tmp_path / "checkpoint.npz")
    b, _ = output.load_checkpoint(tmp_path / "straight" / "checkpoint.npz")
    assert all(np.array_equal(a[k], b[k]) for k in a)
