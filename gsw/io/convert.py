"""Format conversion as a model transformation, and what it does to a watermark.

:func:`format_round_trip` writes a model in a format and reads it back: the model a viewer of that format
would show (quantised by ``.spz`` / compressed PLY, reduced to SH degree 0 by ``.splat``), usable as a model
attack. :func:`check_conversion` measures the watermark's bit accuracy on the same views before and after.

Example:
    >>> from gsw.io.convert import check_conversion, format_round_trip, orbit_views
    >>> after = format_round_trip(g, "spz")  # doctest: +SKIP
    >>> check = check_conversion(g, after, orbit_views(g), "key:secret", num_bits=32)  # doctest: +SKIP
    >>> check.drop_points  # doctest: +SKIP
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch

from gsw.camera import Camera, orbit_cameras
from gsw.gaussians import Gaussians
from gsw.io.formats import WRITABLE_FORMATS, load_model, save_model

__all__ = ["FORMAT_SUFFIXES", "format_round_trip", "orbit_views", "ConversionCheck", "check_conversion",
           "WARN_DROP_POINTS"]

#: File name ending of each writable format.
FORMAT_SUFFIXES = {"ply": ".ply", "compressed-ply": ".compressed.ply", "splat": ".splat", "spz": ".spz"}

WARN_DROP_POINTS = 1.0
"""A conversion that lowers the mean bit accuracy by more than this many percentage points deserves a warning."""


def format_round_trip(gaussians: Gaussians, fmt: str) -> Gaussians:
    """The model after saving it as ``fmt`` (each writer's defaults) and loading it back.

    Args:
        gaussians: the model.
        fmt: one of :data:`~gsw.io.formats.WRITABLE_FORMATS`.

    Returns:
        The reloaded model (CPU, float32; compressed PLY returns it in its Morton order).
    """
    if fmt not in WRITABLE_FORMATS:
        raise ValueError(f"unknown model format {fmt!r}; writable: {', '.join(WRITABLE_FORMATS)}")
    with tempfile.TemporaryDirectory(prefix="gsw-convert-") as tmp:
        path = Path(tmp) / f"model{FORMAT_SUFFIXES[fmt]}"
        save_model(gaussians, path, fmt)
        return load_model(path, fmt)


def orbit_views(gaussians: Gaussians, n: int = 4, size: int = 256) -> list[Camera]:
    """``n`` cameras on an orbit around the model: centred on the median position, at 3x the median distance
    from it, 30 degrees above the ``z = const`` plane.

    Args:
        gaussians: the model.
        n: number of views.
        size: image width and height, pixels.
    """
    means = gaussians.means.detach().double().cpu()
    if len(means) == 0:
        raise ValueError("cannot place orbit views around an empty model")
    center = means.median(dim=0).values
    radius = max(float(3.0 * (means - center).norm(dim=1).median()), 1e-3)
    return orbit_cameras(center.tolist(), radius, n, width=size, height=size)


@dataclass
class ConversionCheck:
    """Bit accuracy of a watermark before and after a conversion, per view.

    Attributes:
        before: ``V`` bit accuracies of the original model's renders, in ``[0, 1]``.
        after: ``V`` bit accuracies of the converted model's renders.
    """

    before: list[float]
    after: list[float]

    @property
    def mean_before(self) -> float:
        """Mean bit accuracy before."""
        return sum(self.before) / len(self.before)

    @property
    def mean_after(self) -> float:
        """Mean bit accuracy after."""
        return sum(self.after) / len(self.after)

    @property
    def drop_points(self) -> float:
        """Drop of the mean bit accuracy, percentage points (negative: it rose)."""
        return 100.0 * (self.mean_before - self.mean_after)

    def dropped(self, threshold_points: float = WARN_DROP_POINTS) -> bool:
        """Whether the mean bit accuracy fell by more than ``threshold_points``."""
        return self.drop_points > threshold_points


def check_conversion(original: Gaussians, converted: Gaussians, cameras: Sequence[Camera], message, *,
                     num_bits: int | None = None, background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     decoder: torch.nn.Module | None = None) -> ConversionCheck:
    """Bit accuracy of ``message`` in renders of both models from the same cameras.

    Args:
        original: the model before the conversion.
        converted: the model after it.
        cameras: the views.
        message: the watermark (bits, hex or ``"key:<secret>"``, see :func:`gsw.mark.message.as_message`).
        num_bits: message length (required for a key).
        background: render background.
        decoder: a custom decoder (default: the shipped one for ``num_bits``).

    Returns:
        The :class:`ConversionCheck`.
    """
    from gsw.mark.detect import verify  # noqa: PLC0415 - rendering and decoders load on demand

    before = verify((original, list(cameras)), message, num_bits=num_bits, background=background, decoder=decoder)
    after = verify((converted, list(cameras)), message, num_bits=num_bits, background=background, decoder=decoder)
    return ConversionCheck(before.bit_accuracy, after.bit_accuracy)
