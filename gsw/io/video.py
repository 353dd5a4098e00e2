"""Video frames for detection and identification (PyAV, an optional dependency: ``pip install gsw[video]``).

:func:`read_video` decodes a video file and keeps N frames spread evenly over it (the centres of N equal
segments, so fades at both ends are avoided) or every k-th frame, as ``[3, H, W]`` float32 RGB in
``[0, 1]``. Only the kept frames are converted to RGB; the frame count comes from the container (or from
counting packets, which decodes nothing). Whatever the container or codec, an unreadable, empty, truncated
or non-video file raises :class:`VideoError` naming the file.

:func:`load_images_or_video` reads what a detection command is given: image files and video files mixed,
videos by suffix (:data:`VIDEO_SUFFIXES`).

Example:
    >>> from gsw.io.video import read_video
    >>> clip = read_video("leak.mp4", frames=8)  # doctest: +SKIP
    >>> len(clip.images), clip.images[0].shape   # doctest: +SKIP
    (8, torch.Size([3, 1080, 1920]))
"""

from __future__ import annotations

import glob
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import torch
from torch import Tensor

from gsw.data.images import to_unit

__all__ = ["DEFAULT_FRAMES", "VIDEO_SUFFIXES", "VideoError", "VideoFrames", "expand_inputs", "is_video", "read_video",
           "load_images_or_video", "load_named_images_or_video"]

#: Frames kept per video by default.
DEFAULT_FRAMES = 16
#: File suffixes read as videos (lower case); anything else is read as an image.
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".mkv", ".webm", ".avi", ".mpg", ".mpeg", ".ts", ".flv", ".wmv")
#: A container whose decodable frames fall short of (duration x frame rate) by more than this share is truncated.
_TRUNCATION_SLACK = 0.1


class VideoError(ValueError):
    """A video file cannot be read: not a video, no video stream, empty, truncated or damaged."""


@dataclass
class VideoFrames:
    """Frames read from one video.

    Attributes:
        path: the file.
        images: [3, H, W] float32 RGB frames in [0, 1], in stream order.
        indices: their 0-based frame numbers.
        num_frames: frames in the video.
        fps: average frame rate (None when the container does not say).
    """

    path: Path
    images: list[Tensor]
    indices: list[int]
    num_frames: int
    fps: float | None


def _require_av() -> ModuleType:
    try:
        import av
    except ImportError:
        raise ImportError("reading videos needs PyAV: pip install av (or pip install 'gsw[video]')") from None
    return av


def is_video(path: str | os.PathLike) -> bool:
    """Whether ``path`` is read as a video (its suffix is in :data:`VIDEO_SUFFIXES`)."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def _open(av: ModuleType, path: Path) -> Any:
    try:
        return av.open(str(path), mode="r")
    except av.error.FFmpegError as err:
        raise VideoError(f"{path} is not a readable video ({err.strerror or err})") from None


def _video_stream(container: Any, path: Path) -> Any:
    if not container.streams.video:
        raise VideoError(f"{path} has no video stream")
    return container.streams.video[0]


def _count_frames(av: ModuleType, container: Any, stream: Any, path: Path) -> int:
    """Frames of ``stream``: the container's count, else its packets (demuxed, not decoded)."""
    if stream.frames and stream.frames > 0:
        return int(stream.frames)
    try:
        return sum(1 for packet in container.demux(stream) if packet.size)
    except av.error.FFmpegError as err:
        raise VideoError(f"{path} is damaged: demuxing failed ({err.strerror or err})") from None


def _expected_frames(container: Any, stream: Any) -> int | None:
    """Frames announced by the header (duration x average rate), or None when it does not say."""
    if not container.duration or not stream.average_rate:
        return None
    return int(container.duration / 1_000_000 * float(stream.average_rate))


def _wanted(total: int, frames: int | None, every: int | None) -> list[int]:
    if every is not None:
        return list(range(0, total, every))
    if frames is None or frames >= total:
        return list(range(total))
    return [(2 * i + 1) * total // (2 * frames) for i in range(frames)]  # centres of equal segments


def _check_args(path: Path, frames: int | None, every: int | None) -> None:
    for name, value in (("frames", frames), ("every", every)):
        if value is not None and (not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if not path.exists():
        raise FileNotFoundError(f"video not found: {path}")
    if not path.is_file():
        raise VideoError(f"{path} is not a file")
    if path.stat().st_size == 0:
        raise VideoError(f"{path} is empty (0 bytes)")


def _decode(av: ModuleType, path: Path, wanted: list[int], keep_uint8: bool) -> tuple[list[Tensor], int]:
    """The frames at the sorted ``wanted`` indices (float32 in [0, 1], or uint8 0..255 with ``keep_uint8``),
    and how many frames were decoded to reach them."""
    keep, images, seen = set(wanted), [], 0
    with _open(av, path) as container:
        stream = _video_stream(container, path)
        stream.thread_type = "AUTO"
        try:
            for frame in container.decode(stream):
                if seen in keep:
                    rgb = torch.from_numpy(frame.to_ndarray(format="rgb24")).permute(2, 0, 1)  # [3, H, W] uint8
                    images.append(rgb if keep_uint8 else to_unit(rgb))
                seen += 1
                if seen > wanted[-1]:
                    break
        except av.error.FFmpegError as err:
            raise VideoError(f"{path} is damaged: decoding failed after {seen} frames "
                             f"({err.strerror or err})") from None
    return images, seen


def read_video(path: str | os.PathLike, frames: int | None = DEFAULT_FRAMES, *,
               every: int | None = None, keep_uint8: bool = False) -> VideoFrames:
    """Decodes frames of a video file.

    Args:
        path: any container/codec FFmpeg (as bundled with PyAV) reads: mp4, mkv, webm, mov, avi, ...
        frames: keep this many frames spread evenly (all of them when the video is shorter; None: every
            frame). Ignored when ``every`` is given.
        every: keep every ``every``-th frame (0, k, 2k, ...) instead.
        keep_uint8: keep the frames as their [3, H, W] uint8 samples (channel-first views of the decoded
            [H, W, 3] arrays; :func:`gsw.data.images.to_unit` makes them the float32 frames bitwise).

    Returns:
        A :class:`VideoFrames` with the kept frames as [3, H, W] float32 RGB in [0, 1] (uint8 with
        ``keep_uint8``).

    Raises:
        ImportError: PyAV is not installed (``pip install av``).
        FileNotFoundError: the file does not exist.
        VideoError: a zero-byte file, not a video, no video stream, no frames, or truncated/damaged.
        ValueError: ``frames`` or ``every`` not a positive integer.
    """
    av = _require_av()
    path = Path(path)
    _check_args(path, frames, every)
    with _open(av, path) as container:
        stream = _video_stream(container, path)
        total = _count_frames(av, container, stream, path)
        expected = _expected_frames(container, stream)
        fps = float(stream.average_rate) if stream.average_rate else None
    if total == 0:
        raise VideoError(f"{path} holds no video frames")
    if expected is not None and total < (1.0 - _TRUNCATION_SLACK) * expected - 1:
        raise VideoError(f"{path} is truncated or damaged: {total} frames present, its header announces "
                         f"about {expected}")
    wanted = _wanted(total, frames, every)
    images, seen = _decode(av, path, wanted, keep_uint8)
    if len(images) < len(wanted):
        raise VideoError(f"{path} is truncated or damaged: only {seen} of {total} frames could be decoded")
    return VideoFrames(path, images, wanted, total, fps)


def _suffixes() -> tuple[str, ...]:
    """The suffixes (lower case) of the files a folder or a glob pattern yields: images and videos."""
    from gsw.data.images import IMAGE_SUFFIXES

    return tuple({s.lower() for s in (*IMAGE_SUFFIXES, *VIDEO_SUFFIXES, ".bmp", ".tif", ".tiff")})


def expand_inputs(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """The image and video files of folders (recursively, by suffix), glob patterns and files, in order, without
    repeats; a file given by name is kept whatever its suffix.

    Raises:
        FileNotFoundError: an input that is neither a file, a folder nor a pattern with matches.
        ValueError: nothing found.
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


def load_named_images_or_video(paths: Sequence[str | os.PathLike], frames: int | None = DEFAULT_FRAMES, *,
                               every: int | None = None, keep_uint8: bool = False) -> list[tuple[str, Tensor]]:
    """(name, [3, H, W] image in [0, 1]) for every image file and every kept frame of every video.

    Args:
        paths: image files (PNG, JPEG, ...; alpha composited on black, as renders are) and video files
            (by suffix, :data:`VIDEO_SUFFIXES`), mixed; a folder stands for its image and video files
            (:func:`expand_inputs`: recursively, sorted).
        frames, every: frames kept per video (:func:`read_video`).
        keep_uint8: 8-bit images without alpha and video frames as uint8 0..255 (a quarter of the memory and
            no conversion here; :func:`gsw.data.images.to_unit` where they are used gives the float32 images
            bitwise); the others float32.

    Returns:
        One entry per image and per kept frame, in order; a frame is named ``"<path>#<frame number>"``.

    Raises:
        FileNotFoundError: a missing file. ValueError (:class:`VideoError` for videos): an unreadable one, or
            a folder without images or videos.
        ImportError: a video without PyAV installed.
    """
    from gsw.data.images import read_rgb

    if not paths:
        raise ValueError("no images or videos given")
    out: list[tuple[str, Tensor]] = []
    for p in [f for p in paths for f in (expand_inputs([p]) if Path(p).is_dir() else [p])]:
        if is_video(p):
            clip = read_video(p, frames, every=every, keep_uint8=keep_uint8)
            out += [(f"{p}#{i}", img) for i, img in zip(clip.indices, clip.images)]
        else:
            out.append((str(p), read_rgb(p, keep_uint8=keep_uint8)))
    return out


def load_images_or_video(paths: Sequence[str | os.PathLike], frames: int | None = DEFAULT_FRAMES, *,
                         every: int | None = None, keep_uint8: bool = False) -> list[Tensor]:
    """The [3, H, W] images of :func:`load_named_images_or_video`, without their names."""
    return [img for _, img in load_named_images_or_video(paths, frames, every=every, keep_uint8=keep_uint8)]
