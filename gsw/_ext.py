"""The compiled extension ``gsw._C``, loaded on first use with an error that says what to do.

Only the rasterizer (:mod:`gsw.render`) and :mod:`gsw.constants` need it; the decoder, attacks and
metrics subpackages import without it.
"""

from __future__ import annotations

import torch  # noqa: F401  (loads libtorch/libc10 before the extension)

try:
    from gsw import _C
except ImportError as exc:  # pragma: no cover - exercised in a subprocess test
    raise ImportError(
        f"gsw's compiled rasterizer extension (gsw._C) could not be loaded: {exc}. Build it against the "
        f"installed torch {torch.__version__} with `pip install --no-build-isolation .` "
        "(see the README's install section)."
    ) from exc

__all__ = ["_C"]
