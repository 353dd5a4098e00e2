"""gsw._atomic: temporary names that record their owner, umask permissions, exclusive or replacing commits, no
backups left behind, cleanup on SIGINT and the sweep of dead runs' temporaries."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from gsw._atomic import atomic_output, atomic_write, sweep_stale, temp_path


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def umask():
    """Sets a umask for the test and restores the old one."""
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_new_files_and_folders_respect_the_umask(tmp_path, umask, mask) -> None:
    umask(mask)
    with atomic_write(tmp_path / "a.txt", "w") as f:
        f.write("x")
    with atomic_output(tmp_path / "folder", folder=True, replace=False) as tmp:
        (tmp / "inner.txt").write_text("y")
    with atomic_output(tmp_path / "b.bin", folder=False, replace=False) as tmp:
        with atomic_write(tmp, "wb") as f:
            f.write(b"z")
    assert _mode(tmp_path / "a.txt") == 0o666 & ~mask
    assert _mode(tmp_path / "b.bin") == 0o666 & ~mask
    assert _mode(tmp_path / "folder") == 0o777 & ~mask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.bin", "folder"]


def test_exclusive_write_refuses_a_file_that_appeared(tmp_path) -> None:
    target = tmp_path / "out.txt"
    with pytest.raises(FileExistsError):
        with atomic_write(target, "w", replace=False) as f:
            f.write("mine")
            target.write_text("theirs")  # another writer got there first
    assert target.read_text() == "theirs"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


@pytest.mark.parametrize("folder", [True, False])
def test_exclusive_output_refuses_what_appeared_and_discards_its_temporary(tmp_path, folder) -> None:
    target = tmp_path / ("out" if folder else "out.bin")
    with pytest.raises(FileExistsError, match="appeared while this run was writing"):
        with atomic_output(target, folder=folder, replace=False) as tmp:
            (tmp / "a" if folder else tmp).write_bytes(b"mine")
            target.mkdir()  # even an empty folder is somebody's output
            (target / "theirs").write_bytes(b"theirs")
    assert [p.name for p in target.iterdir()] == ["theirs"]
    assert [p.name for p in tmp_path.iterdir()] == [target.name]


@pytest.mark.parametrize("old_is_dir, new_is_dir", [(False, False), (False, True), (True, False), (True, True)])
def test_replacing_leaves_no_backup(tmp_path, old_is_dir, new_is_dir) -> None:
    target = tmp_path / "out"
    if old_is_dir:
        target.mkdir()
        (target / "old.txt").write_text("old")
    else:
        target.write_text("old")
    with atomic_output(target, folder=new_is_dir, replace=True) as tmp:
        (tmp / "new.txt" if new_is_dir else tmp).write_text("new")
    assert (target / "new.txt" if new_is_dir else target).read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no .out.old, no temporary


def test_a_failed_block_keeps_the_old_output(tmp_path) -> None:
    target = tmp_path / "out"
    target.mkdir()
    (target / "a.txt").write_text("old")
    with pytest.raises(OSError, match="No space left"):
        with atomic_output(target, folder=True, replace=True) as tmp:
            (tmp / "a.txt").write_text("half")
            raise OSError(28, "No space left on device")
    assert (target / "a.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_two_writers_in_threads_exactly_one_wins(tmp_path) -> None:
    target, barrier, outcome = tmp_path / "out", threading.Barrier(2), {}

    def write(name: str) -> None:
        try:
            with atomic_output(target, folder=True, replace=False) as tmp:
                for i in range(20):
                    (tmp / f"{i}.txt").write_text(name)
                barrier.wait(timeout=30)  # both are inside their block before either commits
            outcome[name] = "won"
        except FileExistsError:
            outcome[name] = "refused"

    threads = [threading.Thread(target=write, args=(n,)) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(outcome.values()) == ["refused", "won"]
    winner = next(n for n, o in outcome.items() if o == "won")
    assert {p.read_text() for p in target.iterdir()} == {winner} and len(list(target.iterdir())) == 20
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_sweep_removes_only_gsw_temporaries_of_dead_processes(tmp_path) -> None:
    mine = temp_path(tmp_path / "out")  # this process: alive
    dead = mine.with_name(mine.name.replace(f"-{os.getpid()}-", f"-{_dead_pid()}-"))
    other_host = tmp_path / f".out.gsw-00000000-{_dead_pid()}-0123abcd.tmp"  # another host's: never ours to judge
    foreign = tmp_path / ".out.1234.tmp"  # not a gsw name (e.g. another tool's)
    for p in (mine, dead, foreign):
        p.mkdir()
        (p / "x").write_text("x")
    other_host.write_text("x")
    notices: list[str] = []
    assert sweep_stale(tmp_path, notices.append) == [dead]
    assert not dead.exists() and mine.exists() and foreign.exists() and other_host.exists()
    assert len(notices) == 1 and str(dead) in notices[0] and "interrupted gsw run" in notices[0]


@pytest.fixture
def sigint_default():
    """SIGINT as in an interactive Python (KeyboardInterrupt), whatever the test runner inherited: a job started in
    the background of a non-interactive shell starts with SIGINT ignored."""
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, inherited)


def test_sigint_removes_the_temporary_and_raises_keyboardinterrupt(tmp_path, sigint_default) -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(tmp_path / "out", folder=True, replace=False) as tmp:
            (tmp / "a.txt").write_text("half")
            assert signal.getsignal(signal.SIGINT) is not before  # our handler while a temporary exists
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_an_ignored_sigint_stays_ignored(tmp_path) -> None:
    """A process told to ignore SIGINT (nohup, a background job) keeps ignoring it while a temporary exists."""
    inherited = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with atomic_output(tmp_path / "out", folder=True, replace=False) as tmp:
            (tmp / "a.txt").write_text("whole")
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)  # ignored: the write goes on and commits
        assert (tmp_path / "out" / "a.txt").read_text() == "whole"
    finally:
        signal.signal(signal.SIGINT, inherited)
