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
    # view: a folder that is neither a run nor a scene is one line and status 2, no traceback
    assert main(["view", str(tmp_path / "no_such_run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("kinema: ") and "no_such_run" in err and "Traceback" not in err


@needs_script
def test_ctrl_c_keeps_frames_and_resume_continues(tmp_path):
    args = ["run", "vortex_sheet", "--quick", "--out", tmp_path, "--set", "output.mp4=false"]
    proc = subprocess.Popen([str(KINEMA), *map(str, args), "--frames", "100000"], stdout=subprocess.PIPE,
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


def _run_in(tmp_path, *args):
    return kinema("run", "vortex_sheet", "--quick", "--out", tmp_path, "--set", "output.mp4=false", *args)


@needs_script
def test_a_second_run_replaces_the_first_and_says_so(tmp_path):
    first = _run_in(tmp_path, "--frames", 5, "--set", "output.vtu=true")
    assert first.returncode == 0, first.stderr
    assert len(list((tmp_path / "frames").iterdir())) == 5
    second = _run_in(tmp_path, "--frames", 3)
    assert second.returncode == 0, second.stderr
    assert "held an earlier run" in second.stderr.splitlines()[0]
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [f"frame_{k:05d}.png" for k in range(3)]
    assert not list(tmp_path.glob("vortices/*.vtu")) and not (tmp_path / "vortices.pvd").exists()
    _, meta = output.load_checkpoint(tmp_path / "checkpoint.npz")
    assert meta["frame"] == 2
    # A folder with anything else is refused, and left alone.
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    refused = kinema("run", "vortex_sheet", "--quick", "--out", mine, "--frames", 2)
    assert refused.returncode == 2 and "is not empty and holds no kinema run" in refused.stderr
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


@needs_script
def test_example_name_beside_a_folder_of_that_name(tmp_path):
    (tmp_path / "vortex_sheet").mkdir()
    done = kinema("run", "vortex_sheet", "--quick", "--frames", 2, "--out", "o", "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    folder = kinema("run", "other", cwd=tmp_path / "o")
    assert "no such file, nor an example scene" in folder.stderr
    (tmp_path / "sub").mkdir()
    folder = kinema("run", "sub", cwd=tmp_path)
    assert folder.returncode == 2 and "sub: is a folder, expected a scene file" in folder.stderr


@needs_script
def test_outputs_follow_the_umask(tmp_path):
    done = subprocess.run(["sh", "-c", f"umask 022 && exec {KINEMA} run vortex_sheet --quick --frames 2 "
                           f"--out {tmp_path} --set output.vtu=true --no-progress"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(files) >= 6
    for p in files:
        assert p.stat().st_mode & 0o777 == 0o644, p


@needs_script
def test_no_ffmpeg_is_said_and_no_progress_keeps_the_final_line(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    env = {**os.environ, "PATH": str(bin_dir)}  # no ffmpeg on the PATH
    done = subprocess.run([str(KINEMA), "run", "vortex_sheet", "--quick", "--frames", "3", "--out", str(tmp_path / "o"),
                           "--no-progress"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 2, lines
    assert "ffmpeg not found: no video.mp4" in lines[0]
    assert lines[1].startswith("done: 3 frames") and str(tmp_path / "o") in lines[1]
    assert not (tmp_path / "o" / "video.mp4").exists()


def test_invalid_scene_creates_no_folder(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "x"\nduration = 1\n[solver]\ntype = "massspring"\n'
                   '[[objects]]\ntype = "mesh"\nfile = "missing.obj"\nstiffness = 1.0\n')
    assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "objects[0].file" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_info_prints_each_key_once(capsys):
    assert main(["info"]) == 0
    keys = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert keys.count("version") == 1 and len(keys) == len(set(keys))


def test_resume_as_the_help_shows_it_repeats_the_set_options(tmp_path, capsys):
    # `kinema --help` and the scenes guide continue a run made with --set by the same --set and
    # --resume; without the --set the checkpoint is refused with that advice.
    out = str(tmp_path / "run")
    first = ["run", "vortex_sheet", "--quick", "--set", "solver.substeps=1", "--out", out, "--no-progress"]
    assert main([*first, "--frames", "2"]) == 0
    capsys.readouterr()
    assert main(["run", "vortex_sheet", "--quick", "--out", out, "--frames", "3", "--resume"]) == 2
    assert "--set options of the run that wrote it" in capsys.readouterr().err
    assert main([*first, "--frames", "3", "--resume"]) == 0
    assert (tmp_path / "run" / "frames" / "frame_00002.png").exists()
