"""Atomic outputs: files and folders are written under a temporary name next to the target, then renamed.

Conventions shared by every writer of gsw:

* Temporary names are ``.<target name>.gsw-<host>-<pid>-<random>.tmp`` (:func:`temp_path`): the owner's host tag
  and process id are in the name, so a later run can tell an orphan (its owner is dead) from a live write and
  :func:`sweep_stale` removes only gsw's own orphans, with a notice.
* Temporaries are removed on an exception and on SIGINT / SIGTERM (the handler removes them, then hands the
  signal to the previous handler: ``KeyboardInterrupt``, or death by the signal, exit status 128 + signal).
  SIGKILL cannot be caught: its leftovers are swept by the next run into the same folder.
* New files get ``0666 & ~umask`` and new folders ``0777 & ~umask``, like any file the user creates.
* A commit either replaces the target (``replace=True``) or refuses a target that exists by then
  (``replace=False``: exclusive creation, :class:`FileExistsError`, the temporary is discarded). A replaced folder
  is first renamed to a temporary name and removed after the new one is in place: no ``.NAME.old`` is left.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import os
import re
import secrets
import shutil
import signal
import socket
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Callable, Iterator

__all__ = ["atomic_output", "atomic_write", "commit", "remove_path", "sweep_stale", "temp_path"]

_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
#: gsw's temporary names (see the module docstring); nothing else is ever swept.
_TEMP_RE = re.compile(r"^\..+\.gsw-(?P<host>[0-9a-f]{8})-(?P<pid>\d+)-[0-9a-f]{8}\.tmp$")
_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def temp_path(target: str | os.PathLike) -> Path:
    """A fresh temporary name next to ``target`` that records this process (not created)."""
    target = Path(target)
    return target.with_name(f".{target.name}.gsw-{_HOST}-{os.getpid()}-{secrets.token_hex(4)}.tmp")


def remove_path(path: Path) -> None:
    """Removes a file, link or folder tree; a missing path is fine."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    except FileNotFoundError:
        pass


# ------------------------------------------------------------------------------------------------ signals

_live: dict[Path, None] = {}  # temporaries of this process, in creation order
_previous: dict[int, Any] = {}  # signal -> the handler in place before ours
_lock = threading.Lock()


def _on_signal(signum: int, frame: Any) -> None:
    """Removes this process's temporaries, then lets the previous handler (or the default action) act."""
    for path in reversed(list(_live)):
        remove_path(path)
    _live.clear()
    previous = _previous.get(signum, signal.SIG_DFL)
    _restore_handlers()
    if callable(previous):
        previous(signum, frame)  # e.g. KeyboardInterrupt
    else:
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)  # dies by the signal: exit status 128 + signum


def _install_handlers() -> None:
    if threading.current_thread() is not threading.main_thread():
        return  # only the main thread may set handlers; an exception still cleans up
    for sig in _SIGNALS:
        previous = signal.getsignal(sig)
        if previous in (signal.SIG_IGN, None) or previous is _on_signal:
            continue
        _previous[sig] = previous
        signal.signal(sig, _on_signal)


def _restore_handlers() -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    for sig, previous in list(_previous.items()):
        if signal.getsignal(sig) is _on_signal:
            signal.signal(sig, previous)
        del _previous[sig]


def _register(path: Path) -> None:
    with _lock:
        _live[path] = None
        if len(_live) == 1:
            _install_handlers()


def _unregister(path: Path) -> None:
    with _lock:
        _live.pop(path, None)
        if not _live:
            _restore_handlers()


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT / SIGTERM wait until the block ends (a commit is never cut between its two renames)."""
    mask = getattr(signal, "pthread_sigmask", None)
    if mask is None:
        yield
        return
    old = mask(signal.SIG_BLOCK, _SIGNALS)
    try:
        yield
    finally:
        mask(signal.SIG_SETMASK, old)


# ------------------------------------------------------------------------------------------------ commit


def _renameat2_noreplace(src: Path, dst: Path) -> bool:
    """``rename(src, dst)`` failing if ``dst`` exists (Linux ``renameat2``); False where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    fn = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if fn is None:
        return False
    at_fdcwd, rename_noreplace = -100, 1
    if fn(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), rename_noreplace) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(dst))


def _rename_noreplace(src: Path, dst: Path) -> None:
    """Moves ``src`` to ``dst`` only if ``dst`` does not exist (:class:`FileExistsError` otherwise)."""
    try:
        if _renameat2_noreplace(src, dst):
            return
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, "exists", str(dst)) from None
    if src.is_dir():
        os.mkdir(dst)  # claim the name (exclusive), then replace the empty claim
        os.rename(src, dst)
    else:
        os.link(src, dst)  # exclusive
        os.unlink(src)


def commit(tmp: Path, target: Path, *, replace: bool) -> None:
    """Puts the finished ``tmp`` at ``target``.

    Args:
        tmp: the finished temporary file or folder (beside ``target``).
        target: the destination.
        replace: replace whatever ``target`` holds by then; otherwise a ``target`` that exists is an error.

    Raises:
        FileExistsError: ``target`` exists and not ``replace`` (``tmp`` is left for the caller to remove).
    """
    with _signals_deferred():
        if not replace:
            _rename_noreplace(tmp, target)
        elif not (tmp.is_dir() or (target.is_dir() and not target.is_symlink())):
            os.replace(tmp, target)  # a file over a file (or nothing): one atomic step
        else:
            backup = temp_path(target)
            _register(backup)
            try:
                if target.exists() or target.is_symlink():
                    os.rename(target, backup)
                try:
                    _rename_noreplace(tmp, target)
                except BaseException:
                    if backup.exists():
                        os.rename(backup, target)
                    raise
                remove_path(backup)
            finally:
                _unregister(backup)
        _fsync_dir(target.parent)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ------------------------------------------------------------------------------------------------ writers


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale(folder: str | os.PathLike, notice: Callable[[str], None] | None = None) -> list[Path]:
    """Removes gsw temporaries in ``folder`` whose owner process (on this host) is dead.

    Args:
        folder: the folder to look in (not recursive).
        notice: called with one line per removed path (default: printed on stderr).

    Returns:
        The removed paths.
    """
    folder = Path(folder)
    removed: list[Path] = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return removed
    for path in entries:
        m = _TEMP_RE.match(path.name)
        if m is None or m["host"] != _HOST or _pid_alive(int(m["pid"])):
            continue
        remove_path(path)
        removed.append(path)
        line = f"gsw: removed {path}, left by an interrupted gsw run (process {m['pid']} is gone)"
        (notice or (lambda s: print(s, file=sys.stderr)))(line)
    return removed


@contextmanager
def atomic_output(target: str | os.PathLike, *, folder: bool, replace: bool) -> Iterator[Path]:
    """A new empty temporary folder beside ``target``, or a file path inside one; committed on success.

    Stale temporaries of dead gsw runs in the target's folder are swept first (with a notice). The
    temporary is removed on an exception or SIGINT / SIGTERM, and when the commit is refused.

    Args:
        target: the output path (its folder is created if missing).
        folder: yield a new folder (``0777 & ~umask``) that becomes ``target``; otherwise the path
            ``<temporary folder>/<target name>`` (same suffix, for writers that choose the format by it) of the
            file that the block creates and that becomes ``target``.
        replace: see :func:`commit`.

    Yields:
        The temporary path to write.

    Raises:
        FileExistsError: ``target`` appeared while the block ran and not ``replace``.
    """
    target = Path(target)
    parent = target.parent if str(target.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(parent)
    tmp = temp_path(target)
    _register(tmp)
    try:
        os.mkdir(tmp, 0o777)
        written = tmp if folder else tmp / target.name
        yield written
        if not folder and not written.is_file():
            raise FileNotFoundError(f"nothing was written to {target}")
        try:
            commit(written, target, replace=replace)
        except FileExistsError:
            raise FileExistsError(f"output {target} appeared while this run was writing it (another run?); it was "
                                  "not replaced and this run's result was discarded (pass --force to replace)"
                                  ) from None
    except OSError as err:  # name the output, not its temporary (a full disk, a read-only folder)
        if err.errno is None or (err.filename is not None and str(tmp) not in str(err.filename)):
            raise
        raise type(err)(err.errno, f"cannot write {target}: {err.strerror} (nothing was written)") from err
    finally:
        remove_path(tmp)
        _unregister(tmp)


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb", *, replace: bool = True) -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success it atomically replaces ``path``.

    Readers never see a partially written file: either the old content or the new one. On an exception
    (or SIGINT / SIGTERM) the temporary file is removed and ``path`` is left untouched.

    Args:
        path: destination file (its directory must exist).
        mode: ``"wb"`` or ``"w"`` (text, UTF-8).
        replace: False: refuse (:class:`FileExistsError`) a ``path`` that exists when the write ends.

    Yields:
        The open temporary file (``0666 & ~umask`` once in place).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"directory does not exist: {directory}")
    tmp = temp_path(path)
    _register(tmp)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        with os.fdopen(fd, mode, **({} if mode == "wb" else {"encoding": "utf-8", "newline": "\n"})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        commit(tmp, path, replace=replace)
    except OSError as err:
        if err.errno is not None and err.filename is None:  # e.g. ENOSPC from write/fsync: name the file
            err.filename = str(path)
        raise
    finally:
        remove_path(tmp)
        _unregister(tmp)
