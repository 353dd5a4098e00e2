"""Scanning many images and videos for registered marks: :func:`scan`.

Every image file is one source, every video one source (its frames taken together). Each source is
tested against every registered mark by :func:`gsw.mark.identify.identify` (calibrated p-values,
family-wise error control over the marks); the decoders are loaded once and reused for all sources.
Sources are read ahead on a thread while the previous one is decoded; with Ray installed and many
sources (or a cluster ``address``) they are spread over Ray Data workers instead.
"""

from __future__ import annotations

import glob
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import torch

from gsw.stats import DETECTION_FPR

__all__ = ["RAY_DATA_MIN_SOURCES", "ScanRow", "expand_inputs", "scan", "scan_sources"]

#: Sources from which :func:`scan` uses Ray Data (when installed) rather than one process.
RAY_DATA_MIN_SOURCES = 256


def _suffixes() -> tuple[str, ...]:
    from gsw.data.images import IMAGE_SUFFIXES
    from gsw.io.video import VIDEO_SUFFIXES

    return tuple({s.lower() for s in (*IMAGE_SUFFIXES, *VIDEO_SUFFIXES, ".webp", ".bmp", ".tif", ".tiff")})


def expand_inputs(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """The image and video files of folders (recursively), glob patterns and files, in order, without repeats.

    Raises:
        FileNotFoundError: an input that is neither a file, a folder nor a pattern with matches.
        ValueError: nothing to scan.
    """
    suffixes, out, seen = _suffixes(), [], set()
    for item in inputs:
        text = str(item)
        if Path(text).is_dir():
            found = sorted(p for p in Path(text).rglob("*") if p.is_file() and p.suffix.lower() in suffixes)
        elif Path(text).is_file():
            found = [Path(text)]
        elif any(c in text for c in "*?["):
            found = sorted(Path(p) for p in glob.glob(text, recursive=True)
                           if Path(p).is_file() and Path(p).suffix.lower() in suffixes)
            if not found:
                raise FileNotFoundError(f"no images or videos match {text}")
        else:
            raise FileNotFoundError(f"no such file or folder: {text}")
        for p in found:
            if p.resolve() not in seen:
                seen.add(p.resolve())
                out.append(p)
    if not out:
        raise ValueError(f"no images or videos found in {', '.join(map(str, inputs))}")
    return out


@dataclass
class ScanRow:
    """One source's result (no messages).

    Attributes:
        source: the file.
        images: images (frames) read.
        identified: labels of the identified recipients, most significant first.
        best_label: the most significant mark tested (identified or not).
        best_adjusted_p: its family-wise adjusted p-value.
        best_p: its p-value.
        best_bit_accuracy: its share of message bits read right in the best image.
        error: why the source could not be read ("" when it was).
    """

    source: str
    images: int = 0
    identified: str = ""
    best_label: str = ""
    best_adjusted_p: float | None = None
    best_p: float | None = None
    best_bit_accuracy: float | None = None
    error: str = ""

    def to_dict(self) -> dict[str, Any]:
        """A flat dict (CSV / JSON row)."""
        return asdict(self)


def _decoders(marks: Sequence, device: torch.device | None) -> dict[str, torch.nn.Module]:
    """The shipped decoders of the marks' lengths, loaded once, by their sha256 (what marks record)."""
    from gsw.decoder.zoo import WeightsError, load_decoder
    from gsw.registry import shipped_decoder_sha256

    out = {}
    for k in sorted({m.num_bits for m in marks}):
        try:
            out[shipped_decoder_sha256(k)] = load_decoder(k).to(device or "cpu")
        except WeightsError:
            continue
    return out


def _load(path: Path, frames: int) -> tuple[list[torch.Tensor], str]:
    from gsw.io.video import load_images_or_video

    try:
        return load_images_or_video([path], frames), ""
    except (OSError, ValueError, ImportError, RuntimeError) as err:
        return [], " ".join(str(err).split()) or type(err).__name__


def scan_sources(paths: Sequence[Path], marks: Sequence, *, fpr: float = DETECTION_FPR,
                 device: torch.device | None = None, frames: int = 16,
                 on_row: Callable[[ScanRow], None] | None = None) -> list[ScanRow]:
    """Identifies each source in this process (reading the next one while the current one is decoded).

    Args:
        paths: image / video files.
        marks: the registered marks (:meth:`gsw.registry.Registry.list`).
        fpr: family-wise false-positive rate per source.
        device: where to decode (None: the CPU).
        frames: frames read per video.
        on_row: called after each source (progress).
    """
    from gsw.mark.identify import identify

    decoders = _decoders(marks, device)
    rows = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        loads: Iterator = pool.map(lambda p: _load(p, frames), paths)
        for path, (images, error) in zip(paths, loads):
            row = ScanRow(str(path), len(images), error=error)
            if images:
                res = identify(images, marks, fpr=fpr, decoders=decoders, device=device)
                row.identified = ";".join(res.recipients)
                if res.results:
                    best = res.results[0]
                    row.best_label, row.best_adjusted_p, row.best_p = best.mark.label, best.adjusted_p_value, best.p_value
                    row.best_bit_accuracy = best.best_bit_accuracy
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows


class _RayScanner:  # pragma: no cover - runs in Ray Data workers
    def __init__(self, marks: Sequence, fpr: float, frames: int, gpu: bool) -> None:
        self.marks, self.fpr, self.frames = marks, fpr, frames
        self.device = torch.device("cuda") if gpu else None

    def __call__(self, batch: dict) -> dict:
        rows = scan_sources([Path(p) for p in batch["path"]], self.marks, fpr=self.fpr, device=self.device,
                            frames=self.frames)
        return {k: [getattr(r, k) for r in rows] for k in ScanRow.__dataclass_fields__}


def _scan_ray(paths: Sequence[Path], marks: Sequence, fpr: float, frames: int, gpu: bool, address: str | None,
              workers: int | None) -> list[ScanRow]:
    import ray

    from gsw.fingerprint.run import connect_ray

    started = connect_ray(address)
    try:
        n = workers or max(1, int(ray.cluster_resources().get("GPU" if gpu else "CPU", 1)))
        ds = ray.data.from_items([{"path": str(p)} for p in paths])
        ds = ds.map_batches(_RayScanner, fn_constructor_args=(list(marks), fpr, frames, gpu), batch_size=16,
                            concurrency=n, num_gpus=1 if gpu else 0)
        by_path = {r["source"]: ScanRow(**r) for r in ds.iter_rows()}
    finally:
        if started:
            ray.shutdown()
    return [by_path[str(p)] for p in paths]


def scan(inputs: Sequence[str | os.PathLike], marks: Sequence, *, fpr: float = DETECTION_FPR,
         device: torch.device | None = None, frames: int = 16, use_ray: bool | None = None,
         address: str | None = None, workers: int | None = None,
         on_row: Callable[[ScanRow], None] | None = None) -> list[ScanRow]:
    """Tests every image and video found in ``inputs`` against the registered marks.

    Args:
        inputs: files, folders (searched recursively) and glob patterns.
        marks: the registered marks.
        fpr: family-wise false-positive rate per source.
        device: where to decode (None: the CPU).
        frames: frames read per video.
        use_ray: True: Ray Data; False: this process; None: Ray Data when installed and there are at least
            :data:`RAY_DATA_MIN_SOURCES` sources or an ``address``.
        address: a Ray cluster to join.
        workers: Ray Data workers (default: one per CPU, or per GPU on CUDA).
        on_row: called after each source in this process (progress; not called with Ray).

    Returns:
        One :class:`ScanRow` per source, in input order.

    Raises:
        ValueError: no marks; nothing to scan.
    """
    from gsw.fingerprint.run import SCALE_OUT_HINT, ray_available

    if not marks:
        raise ValueError("the registry holds no marks")
    paths = expand_inputs(inputs)
    want_ray = use_ray if use_ray is not None else bool(address) or len(paths) >= RAY_DATA_MIN_SOURCES
    if want_ray and not ray_available():
        if use_ray or address:
            raise ImportError(SCALE_OUT_HINT.replace("running in one process. ", ""))
        want_ray = False
    if want_ray:
        gpu = device is not None and torch.device(device).type == "cuda"
        return _scan_ray(paths, marks, fpr, frames, gpu, address, workers)
    return scan_sources(paths, marks, fpr=fpr, device=device, frames=frames, on_row=on_row)
