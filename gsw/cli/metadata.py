"""``watermark.json``: what `gsw embed` records in the watermarked model folder for the later commands.

It holds the message length, the render background, the embedding resolution, the decoder's fingerprint, the
embedding settings and results and the gsw version, and never the message, the key or the seed (a random message
is drawn from the seed)::

    {"format": 1, "gsw_version": "0.1.0", "num_bits": 32, "background": [1.0, 1.0, 1.0],
     "resolution": {"width": 800, "height": 800}, "decoder": {"num_bits": 32, "fingerprint": "<sha256[:16]>"},
     "embedding": {EmbedConfig fields but seed and background}, "gaussians_in": ..., "gaussians_out": ..., ...}

``resolution`` is null when the embedding views had several sizes.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from gsw._atomic import atomic_write
from gsw.camera import Camera
from gsw.cli.common import reading
from gsw.decoder.zoo import AVAILABLE_BITS
from gsw.stats import ORIGINS, check_origin

__all__ = ["FORMAT", "WATERMARK_FILE", "WatermarkInfo", "at_resolution", "read_watermark_json", "watermark_record",
           "write_watermark_json"]

WATERMARK_FILE = "watermark.json"
#: Version of the file layout (a newer one is refused).
FORMAT = 1


@dataclass(frozen=True)
class WatermarkInfo:
    """What the later commands read back from ``watermark.json``.

    Attributes:
        path: the file.
        num_bits: message length.
        background: RGB render background of the embedding.
        resolution: ``(width, height)`` of the embedding views, or None when they had several sizes.
        decoder: fingerprint of the decoder used (:func:`gsw.eval.grid.decoder_fingerprint`; with ``--readout klein``
            that of :class:`gsw.decoder.KleinReadout` over it).
        gsw_version: the gsw version that embedded the watermark.
        message_origin: "random" (drawn by gsw, or from a key) or "chosen" (given by the user): which test
            ``gsw verify --model`` applies; None when the file predates the field (then the command line says).
    """

    path: Path
    num_bits: int
    background: tuple[float, float, float]
    resolution: tuple[int, int] | None
    decoder: str
    gsw_version: str
    message_origin: str | None = None


def _resolution(cameras: Sequence[Camera]) -> dict[str, int] | None:
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        return None
    (width, height), = sizes
    return {"width": int(width), "height": int(height)}


def watermark_record(*, num_bits: int, background: Sequence[float], cameras: Sequence[Camera], decoder: str,
                     config: Any, stats: Mapping[str, Any], message_origin: str = "random") -> dict[str, Any]:
    """The content of ``watermark.json`` (no message, key or seed; only whether the message was drawn or chosen).

    Args:
        num_bits: message length.
        background: RGB render background.
        cameras: the embedding views (their common size is the embedding resolution).
        decoder: the decoder's fingerprint.
        config: the :class:`~gsw.mark.embed.EmbedConfig` used.
        stats: results to record (Gaussian counts, mean bit accuracy and PSNR, timings).
        message_origin: "random" or "chosen" (:func:`gsw.stats.check_origin`).

    Returns:
        A JSON-able dict.
    """
    import gsw

    settings = asdict(config)
    for secret_or_elsewhere in ("seed", "background"):
        settings.pop(secret_or_elsewhere, None)
    return {"format": FORMAT, "gsw_version": gsw.__version__, "num_bits": int(num_bits),
            "message_origin": check_origin(message_origin),
            "background": [float(v) for v in background], "resolution": _resolution(cameras),
            "decoder": {"num_bits": int(num_bits), "fingerprint": decoder}, "embedding": settings, **stats}


def write_watermark_json(folder: Path, record: Mapping[str, Any]) -> None:
    """Writes ``folder/watermark.json`` atomically."""
    with atomic_write(folder / WATERMARK_FILE, "w") as f:
        json.dump(record, f, indent=2)
        f.write("\n")


def _field(data: Mapping[str, Any], name: str, path: Path) -> Any:
    if name not in data:
        raise ValueError(f"{path}: missing field {name!r}")
    return data[name]


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_watermark_json(folder: str | Path) -> WatermarkInfo | None:
    """Reads ``folder/watermark.json``.

    Args:
        folder: a model folder.

    Returns:
        The recorded :class:`WatermarkInfo`, or None when the folder has no ``watermark.json``.

    Raises:
        ValueError: the file is not valid JSON, is from a newer gsw, or a field is missing or malformed (the
            message names the file and the field).
    """
    path = Path(folder) / WATERMARK_FILE
    if not path.is_file():
        return None
    with reading(path):
        data = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    version = _field(data, "format", path)
    if not isinstance(version, int) or version > FORMAT:
        raise ValueError(f"{path}: format {version!r} is not one this gsw reads (<= {FORMAT}); update gsw")
    num_bits = _field(data, "num_bits", path)
    if num_bits not in AVAILABLE_BITS or isinstance(num_bits, bool):
        raise ValueError(f"{path}: num_bits must be one of {AVAILABLE_BITS}, got {num_bits!r}")
    bg = _field(data, "background", path)
    if not (isinstance(bg, list) and len(bg) == 3 and all(_number(v) and 0 <= v <= 1 for v in bg)):
        raise ValueError(f"{path}: background must be 3 numbers in [0, 1], got {bg!r}")
    res = _field(data, "resolution", path)
    if res is not None and not (isinstance(res, dict) and all(
            isinstance(res.get(k), int) and not isinstance(res.get(k), bool) and res[k] > 0
            for k in ("width", "height"))):
        raise ValueError(f"{path}: resolution must be null or {{\"width\": W, \"height\": H}}, got {res!r}")
    decoder = _field(data, "decoder", path)
    if not isinstance(decoder, dict) or not isinstance(decoder.get("fingerprint"), str):
        raise ValueError(f"{path}: decoder must be {{\"num_bits\": N, \"fingerprint\": \"...\"}}, got {decoder!r}")
    origin = data.get("message_origin")
    if origin is not None and origin not in ORIGINS:
        raise ValueError(f"{path}: message_origin must be one of {', '.join(ORIGINS)}, got {origin!r}")
    return WatermarkInfo(path, num_bits, (float(bg[0]), float(bg[1]), float(bg[2])),
                         None if res is None else (res["width"], res["height"]), decoder["fingerprint"],
                         str(data.get("gsw_version", "unknown")), origin)


def at_resolution(cameras: Sequence[Camera], info: WatermarkInfo) -> list[Camera]:
    """The cameras at the embedding resolution (cameras of another size are rescaled; the others kept).

    Raises:
        ValueError: a camera whose aspect ratio does not scale to the embedding resolution.
    """
    if info.resolution is None:
        return list(cameras)
    width, height = info.resolution
    out = []
    for i, cam in enumerate(cameras):
        if (cam.width, cam.height) != (width, height):
            cam_at = cam.scaled(width / cam.width)
            if (cam_at.width, cam_at.height) != (width, height):
                raise ValueError(f"camera {cam.name or i} is {cam.width}x{cam.height}, which does not scale to the "
                                 f"embedding resolution {width}x{height} ({info.path})")
            cam = cam_at
        out.append(cam)
    return out
