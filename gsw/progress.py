"""A minimal progress bar on stderr (no tqdm dependency)."""

from __future__ import annotations

import sys
import time
from typing import IO, Any

__all__ = ["Progress"]


def _fmt_time(seconds: float) -> str:
    seconds = int(max(0, seconds))
    m, s = divmod(seconds, 60)
    h, m = divmod(m, 60)
    return f"{h:d}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


class Progress:
    """``[####----] 120/3000 00:12<04:50 loss=0.031 psnr=24.1 n=51234`` on one refreshed stderr line.

    Args:
        total: number of steps.
        desc: prefix.
        enabled: print nothing when false.
        stream: output stream (default ``sys.stderr``).
        min_interval: seconds between redraws.
        width: bar width in characters.

    Example:
        >>> with Progress(3, enabled=False) as bar:
        ...     for _ in range(3):
        ...         bar.update(loss=0.1)
    """

    def __init__(self, total: int, desc: str = "", *, enabled: bool = True, stream: IO[str] | None = None,
                 min_interval: float = 0.5, width: int = 24) -> None:
        self.total, self.desc, self.enabled = int(total), desc, enabled
        self.stream = stream if stream is not None else sys.stderr
        self.min_interval, self.width = min_interval, width
        self.n = 0
        self.start = time.perf_counter()
        self._last = -1e9
        self._drawn_n = -1
        self.postfix: dict[str, Any] = {}
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    @property
    def due(self) -> bool:
        """Whether the next :meth:`update` of one step redraws the bar: callers can skip computing (or, on a GPU,
        reading back) key/values that would not be shown."""
        return self.enabled and (time.perf_counter() - self._last >= self.min_interval or self.n + 1 >= self.total)

    def update(self, steps: int = 1, /, **postfix: Any) -> None:
        """Advance by ``steps`` and set the displayed key/values."""
        self.n += steps
        self.postfix.update(postfix)
        now = time.perf_counter()
        if self.enabled and (now - self._last >= self.min_interval or self.n >= self.total):
            self._last = now
            self._draw(now, final=False)

    def write(self, message: str) -> None:
        """Print a line above the bar."""
        if self.enabled:
            self.stream.write(("\r\033[K" if self._tty else "") + message + "\n")
            self.stream.flush()

    def _draw(self, now: float, final: bool) -> None:
        frac = self.n / self.total if self.total else 1.0
        filled = int(round(self.width * min(1.0, frac)))
        elapsed = now - self.start
        eta = elapsed / self.n * (self.total - self.n) if self.n else 0.0
        fields = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.postfix.items())
        line = (f"{self.desc + ' ' if self.desc else ''}[{'#' * filled}{'-' * (self.width - filled)}] "
                f"{self.n}/{self.total} {_fmt_time(elapsed)}<{_fmt_time(eta)} {fields}")
        if self._tty:
            self.stream.write("\r\033[K" + line + ("\n" if final else ""))
        elif not (final and self._drawn_n == self.n):  # a log file: one line per new state
            self.stream.write(line + "\n")
        self._drawn_n = self.n
        self.stream.flush()

    def close(self) -> None:
        """Draw the final state."""
        if self.enabled:
            self._draw(time.perf_counter(), final=True)
            self.enabled = False

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
