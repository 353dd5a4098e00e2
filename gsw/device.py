"""The one device rule of gsw: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` to a usable :class:`torch.device`.

Every place that takes a device name (training, embedding, the evaluation grid, 2-D image embedding, the
``--device`` option of the command line) resolves it with :func:`resolve_device`.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Iterator

import torch

__all__ = ["DEVICE_CHOICES", "constant", "cudnn_flags", "deterministic", "parse_device", "resolve_device"]

#: How a device is named (the ``--device`` help of the command line).
DEVICE_CHOICES = "auto|cpu|cuda|cuda:N"

_DEVICE_HELP = "device must be 'auto', 'cpu', 'cuda' or 'cuda:N'"


def parse_device(device: str | torch.device) -> torch.device:
    """``device`` as a CPU or CUDA :class:`torch.device`, without checking that it is usable.

    Args:
        device: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a :class:`torch.device` (not ``"auto"``).

    Raises:
        ValueError: not a CPU or CUDA device.
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"{_DEVICE_HELP}, got {device!r}") from exc
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{_DEVICE_HELP} (gsw's rasterizer has CPU and CUDA backends), got {device!r}")
    return dev


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """The device to compute on, checked to be usable.

    Args:
        device: ``"auto"`` (the current CUDA device when gsw was built with CUDA and torch sees a GPU, else the
            CPU), ``"cpu"``, ``"cuda"`` (the current CUDA device), ``"cuda:N"`` or a :class:`torch.device`.

    Returns:
        ``cpu`` or ``cuda:N`` (always with an index).

    Raises:
        ValueError: ``device`` is not a CPU or CUDA device.
        RuntimeError: a CUDA device was requested but gsw was built without CUDA (``gsw.build_info()["cuda"]``
            is false), torch sees no usable GPU, or the index is out of range.

    Example:
        >>> from gsw.device import resolve_device
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    import gsw  # gsw.build_info loads the compiled extension: only when a device is resolved

    if str(device) == "auto":
        return resolve_device("cuda" if gsw.build_info()["cuda_available"] else "cpu")
    dev = parse_device(device)
    if dev.type == "cpu":
        return dev
    if not gsw.build_info()["cuda"]:
        raise RuntimeError(f"device {str(device)!r} requested but gsw was built without CUDA "
                           "(gsw.build_info()['cuda'] is False); rebuild gsw with CUDA or use device='cpu'")
    if not torch.cuda.is_available():
        raise RuntimeError(f"device {str(device)!r} requested but torch.cuda.is_available() is False (torch "
                           f"{torch.__version__}, CUDA runtime {torch.version.cuda}); use device='cpu'")
    index = torch.cuda.current_device() if dev.index is None else dev.index
    if index >= torch.cuda.device_count():
        raise RuntimeError(f"device {str(device)!r} requested but torch sees {torch.cuda.device_count()} "
                           "CUDA device(s)")
    return torch.device("cuda", index)


@contextlib.contextmanager
def cudnn_flags(**flags: bool) -> Iterator[None]:
    """Inside: the given ``torch.backends.cudnn`` flags (e.g. ``deterministic=True``, ``allow_tf32=False``), each
    restored on exit (the others untouched)."""
    cudnn = torch.backends.cudnn
    saved = {name: getattr(cudnn, name) for name in flags}
    for name, value in flags.items():
        setattr(cudnn, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(cudnn, name, value)


def deterministic() -> contextlib.AbstractContextManager[None]:
    """Inside: cuDNN picks deterministic convolution algorithms and no autotuning (the decoder's and LPIPS's
    convolutions), restored on exit. With gsw's rasterizer, whose backward sums in a fixed order on both
    backends, the same inputs then give the same bits on every run and every GPU of one model (what
    fingerprinting relies on: a copy does not depend on which worker or how many GPUs made it).
    """
    return cudnn_flags(deterministic=True, benchmark=False)


@functools.lru_cache(maxsize=64)
def constant(values: float | tuple[float, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``torch.tensor(values)`` made on ``device`` once and cached (a 0-d tensor for a number): a host-to-device copy
    of a new tensor waits for the device, a synchronisation on every call where a per-render or per-image constant
    is built. Read-only by convention; made outside any inference mode, so that later autograd may save it."""
    with torch.inference_mode(False):
        return torch.tensor(values, dtype=dtype, device=device)
