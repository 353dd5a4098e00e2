"""The compiled extension ``gsw._C``, loaded on first use with an error that says what to do.

Only the rasterizer (:mod:`gsw.render`) and :mod:`gsw.constants` need it; the decoder, attacks and
metrics subpackages import without it.

The extension is compiled against one torch (``gsw.build_info()["built_with_torch"]``, recorded by CMake)
and torch has no stable C++ ABI across releases: under another torch major.minor the module typically
fails to load with an undefined symbol. Both cases (it fails to load, or it loads but was built for
another torch) raise an :class:`ImportError` that names the two versions and the rebuild command; the
version is read from a marker in the module file itself when the module cannot be loaded.
"""

from __future__ import annotations

import importlib.util
import mmap
import re
from pathlib import Path

import torch

__all__ = ["_C", "REBUILD_HINT", "built_with_torch", "torch_mismatch_message"]

REBUILD_HINT = "pip install --no-build-isolation --force-reinstall --no-deps .  (in the gsw source tree)"
_MARKER = b"gsw-built-with-torch="


def built_with_torch(path: str | Path) -> str | None:
    """The torch version recorded in the compiled module file ``path`` (None if it has no marker)."""
    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            start = m.find(_MARKER)
            if start < 0:
                return None
            start += len(_MARKER)
            end = m.find(b"\0", start, start + 128)
            return m[start:end if end >= 0 else start + 128].decode("ascii", "replace")
    except (OSError, ValueError):
        return None


def _major_minor(version: str) -> tuple[int, ...] | None:
    m = re.match(r"(\d+)\.(\d+)", version)
    return (int(m.group(1)), int(m.group(2))) if m else None


def torch_mismatch_message(built: str | None, running: str) -> str | None:
    """A message if ``built`` (the torch the extension was compiled against) differs in major.minor from
    the ``running`` torch; None when they match or ``built`` is unknown."""
    if not built or _major_minor(built) is None or _major_minor(built) == _major_minor(running):
        return None
    return (f"gsw's compiled extension (gsw._C) was built against torch {built}, but torch {running} is "
            f"installed; torch extensions must be rebuilt for each torch release. Rebuild gsw against the "
            f"installed torch:\n    {REBUILD_HINT}\nor install the torch it was built for (torch=={built}).")


def _load():
    running = torch.__version__
    try:
        from gsw import _C
    except ImportError as exc:  # pragma: no cover - exercised in a subprocess test
        try:
            spec = importlib.util.find_spec("gsw._C")  # locates the file, does not load it
        except (ImportError, ValueError):
            spec = None
        built = built_with_torch(spec.origin) if spec is not None and spec.origin else None
        mismatch = torch_mismatch_message(built, running)
        if mismatch is not None:
            raise ImportError(f"{mismatch}\n(loading it failed with: {exc})") from exc
        raise ImportError(
            f"gsw's compiled rasterizer extension (gsw._C) could not be loaded: {exc}. Build it against the "
            f"installed torch {running} with `pip install --no-build-isolation .` "
            "(see the README's install section)."
        ) from exc
    mismatch = torch_mismatch_message(_C.build.get("built_with_torch"), running)
    if mismatch is not None:
        raise ImportError(mismatch)
    return _C


_C = _load()
