"""Fault suite of the command line's outputs: concurrent runs, SIGTERM / SIGINT / SIGKILL mid-write, a full disk and
a read-only folder. Each case asserts that no output is half-written or mixed, that temporaries are removed (or
swept by the next run) and that every input file is byte-identical (sha256) afterwards."""

from __future__ import annotations

import errno
import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gsw.camera import orbit_cameras, save_inria_cameras
from gsw.cli.main import main
from gsw.data.images import read_image
from gsw.io.ply import save_ply
from helpers import random_model

ROOT = Path(__file__).resolve().parents[1]


def _sha256(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def inputs(tmp_path):
    """A tiny model and cameras in ``tmp_path/in``; after the test, every input byte is checked unchanged."""
    folder = tmp_path / "in"
    folder.mkdir()
    g = random_model(200, degree=0, seed=3)
    save_ply(g, folder / "model.ply")
    save_inria_cameras(orbit_cameras([0.0, 0.0, 0.0], 6.0, 6, width=24, height=24), folder / "cameras.json")
    before = _sha256(folder)
    yield folder
    assert _sha256(folder) == before


def _render_argv(inputs: Path, output: Path, *extra: str) -> list[str]:
    return ["render", str(inputs / "model.ply"), "--output", str(output), "--width", "24", "--height", "24", *extra]


def _gsw(argv: list[str]) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "gsw.cli.main", *argv], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,  # Ctrl-C works even if this shell ignores it:
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _temporaries(parent: Path) -> list[Path]:
    return [p for p in parent.iterdir() if p.name.startswith(".") and ".gsw-" in p.name]


def _wait_for_temporary(proc: subprocess.Popen, parent: Path, timeout: float = 90.0) -> Path:
    """The temporary output folder of ``proc`` once it holds a written image (the run is mid-write)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for tmp in _temporaries(parent):
            if tmp.is_dir() and any(p.suffix == ".png" for p in tmp.iterdir()):
                return tmp
        if proc.poll() is not None:
            raise AssertionError(f"the run ended before it was interrupted: {proc.communicate()}")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError("no temporary output appeared")


def test_concurrent_runs_to_one_output_exactly_one_wins(inputs, tmp_path) -> None:
    out = tmp_path / "out"
    runs = {"white": _gsw(_render_argv(inputs, out, "--white", "--orbit", "40")),
            "black": _gsw(_render_argv(inputs, out, "--black", "--orbit", "30"))}
    results = {name: (proc.communicate(timeout=300)[1], proc.returncode)[::-1] for name, proc in runs.items()}
    assert sorted(rc for rc, _ in results.values()) == [0, 2], results
    winner = next(name for name, (rc, _) in results.items() if rc == 0)
    loser_err = next(err for rc, err in results.values() if rc == 2)
    assert str(out) in loser_err and ("exists" in loser_err or "appeared" in loser_err)
    pngs = sorted(out.iterdir())
    assert len(pngs) == (40 if winner == "white" else 30)  # all of the winner's views and nothing else
    brightness = [float(read_image(p).mean()) for p in pngs]  # tiny Gaussians: the background dominates
    assert all((b > 0.5) == (winner == "white") for b in brightness)  # no view of the loser
    assert _temporaries(tmp_path) == []


def test_signals_mid_write(inputs, tmp_path, capsys) -> None:
    """SIGTERM and SIGINT: no output, temporary removed by the handler; SIGKILL: the next run into the same folder
    sweeps the leftover with a notice and leaves finished outputs alone. The three runs go in parallel."""
    old = tmp_path / "kill" / "old"  # a finished output beside the killed run
    assert main(_render_argv(inputs, old, "--orbit", "2")) == 0
    old_files = _sha256(old)
    runs = {}
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGKILL):
        parent = tmp_path / sig.name.lower().removeprefix("sig")
        parent.mkdir(exist_ok=True)
        runs[sig] = (parent, _gsw(_render_argv(inputs, parent / "out", "--orbit", "20000")))
    leftovers = {}
    for sig, (parent, proc) in runs.items():  # each run is signalled as soon as it is mid-write (a fast GPU
        leftovers[sig] = _wait_for_temporary(proc, parent)  # machine finished a 1,000-view run meanwhile)
        proc.send_signal(sig)
    errors = {sig: proc.communicate(timeout=120)[1] for sig, (_, proc) in runs.items()}
    codes = {sig: proc.returncode for sig, (_, proc) in runs.items()}
    assert codes == {signal.SIGTERM: -signal.SIGTERM, signal.SIGINT: 130, signal.SIGKILL: -signal.SIGKILL}, errors
    assert errors[signal.SIGINT].strip().endswith("gsw render: interrupted")
    for sig, (parent, _) in runs.items():
        assert not (parent / "out").exists()
        assert _temporaries(parent) == ([] if sig != signal.SIGKILL else [leftovers[sig]])  # KILL: no handler
    capsys.readouterr()
    assert main(_render_argv(inputs, tmp_path / "kill" / "next", "--orbit", "2")) == 0
    err = capsys.readouterr().err
    assert f"removed {leftovers[signal.SIGKILL]}" in err and "interrupted gsw run" in err
    assert _temporaries(tmp_path / "kill") == [] and _sha256(old) == old_files


def _fail_fsync_after(monkeypatch, calls: int, err: int) -> None:
    """``os.fsync`` fails with ``err`` from call ``calls + 1`` on (a disk that fills up mid-run)."""
    real, count = os.fsync, [0]

    def fsync(fd: int) -> None:
        count[0] += 1
        if count[0] > calls:
            raise OSError(err, os.strerror(err))
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


@pytest.mark.parametrize("force", [False, True])
def test_disk_full_mid_render_keeps_the_old_output(inputs, tmp_path, monkeypatch, capsys, force) -> None:
    out = tmp_path / "out"
    if force:
        assert main(_render_argv(inputs, out, "--orbit", "3")) == 0
    before = _sha256(out) if force else None
    _fail_fsync_after(monkeypatch, 2, errno.ENOSPC)
    assert main(_render_argv(inputs, out, "--orbit", "6", *(["--force"] if force else []))) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw render: error: ") and "No space left on device" in err
    assert (_sha256(out) == before) if force else not out.exists()
    assert _temporaries(tmp_path) == []


def test_disk_full_during_export_writes_nothing(inputs, tmp_path, monkeypatch, capsys) -> None:
    _fail_fsync_after(monkeypatch, 0, errno.ENOSPC)
    out = tmp_path / "model.splat"
    assert main(["export", str(inputs / "model.ply"), "--output", str(out), "--no-check"]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert not out.exists() and _temporaries(tmp_path) == []


def test_read_only_output_folder(inputs, tmp_path, monkeypatch, capsys) -> None:
    parent = tmp_path / "ro"
    parent.mkdir()
    if os.geteuid() != 0:
        parent.chmod(0o555)
    else:  # root writes anywhere: simulate the read-only file system instead
        real_mkdir = os.mkdir

        def mkdir(path, mode=0o777, *args, **kwargs):
            if Path(path).parent == parent:
                raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
            return real_mkdir(path, mode, *args, **kwargs)

        monkeypatch.setattr(os, "mkdir", mkdir)
    try:
        assert main(_render_argv(inputs, parent / "out", "--orbit", "2")) == 2
        err = capsys.readouterr().err
        assert err.startswith("gsw render: error: ") and str(parent / "out") in err
        assert "Traceback" not in err and list(parent.iterdir()) == []
    finally:
        parent.chmod(0o755)


def test_force_leaves_no_backup_and_outputs_get_normal_permissions(inputs, tmp_path) -> None:
    old_umask = os.umask(0o022)
    try:
        spz, renders = tmp_path / "a.spz", tmp_path / "renders"
        export = ["export", str(inputs / "model.ply"), "--output", str(spz), "--no-check"]
        assert main(export) == 0 and main([*export, "--force"]) == 0  # a file over a file
        assert main(_render_argv(inputs, renders, "--orbit", "2")) == 0
        assert main(_render_argv(inputs, renders, "--orbit", "3", "--force")) == 0  # a folder over a folder
        assert len(list(renders.iterdir())) == 3  # the new output only, nothing of the old one
        assert main(_render_argv(inputs, spz, "--orbit", "1", "--force")) == 0  # a folder over a file
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.spz", "in", "renders"]  # no .NAME.old, no .tmp
        for folder in (spz, renders):
            assert folder.stat().st_mode & 0o777 == 0o755  # readable by others, as the umask says
            assert {p.stat().st_mode & 0o777 for p in folder.iterdir()} == {0o644}
    finally:
        os.umask(old_umask)
