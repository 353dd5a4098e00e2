"""Video frames through PyAV: frame selection, shape and range, and every kind of broken file."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gsw.data.images import to_unit, write_image
from gsw.io.video import (VideoError, expand_inputs, is_video, load_images_or_video, load_named_images_or_video,
                          read_video)

av = pytest.importorskip("av")

N, W, H = 10, 64, 48
#: (suffix, encoder, pixel format): h264 in mp4 first; the others ship in PyAV's bundled FFmpeg too.
CODECS = [(".mp4", "libx264", "yuv420p"), (".mkv", "ffv1", "yuv444p"), (".avi", "mpeg4", "yuv420p")]


def _encoder_available(name: str) -> bool:
    try:
        av.codec.Codec(name, "w")
    except Exception:  # noqa: BLE001 - UnknownCodecError and friends
        return False
    return True


def write_video(path: Path, frames: list[np.ndarray], codec: str = "", pix_fmt: str = "", rate: int = 10,
                options: dict | None = None) -> Path:
    """Encodes [H, W, 3] uint8 frames (the first available of CODECS when ``codec`` is empty)."""
    if not codec:
        suffix, codec, pix_fmt = next(c for c in CODECS if _encoder_available(c[1]))
        path = path.with_suffix(suffix)
    with av.open(str(path), "w", options=options or {}) as container:
        stream = container.add_stream(codec, rate=rate)
        stream.width, stream.height, stream.pix_fmt = frames[0].shape[1], frames[0].shape[0], pix_fmt
        for arr in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")))
        container.mux(stream.encode())
    return path


def _ramp(n: int = N) -> list[np.ndarray]:
    """Frame i is flat grey 20 i mod 256 (for i < 13 its number can be read back from its brightness)."""
    return [np.full((H, W, 3), 20 * i % 256, np.uint8) for i in range(n)]


@pytest.mark.parametrize("suffix,codec,pix_fmt", CODECS)
def test_frames_are_rgb_in_unit_range_and_evenly_spread(tmp_path, suffix, codec, pix_fmt) -> None:
    if not _encoder_available(codec):
        pytest.skip(f"PyAV's FFmpeg has no {codec} encoder")
    path = write_video(tmp_path / f"clip{suffix}", _ramp(), codec, pix_fmt)
    clip = read_video(path, frames=4)
    assert clip.num_frames == N and clip.fps == pytest.approx(10.0) and clip.path == path
    assert clip.indices == [1, 3, 6, 8]  # centres of 4 equal segments of 10 frames
    assert len(clip.images) == 4
    for i, img in zip(clip.indices, clip.images):
        assert img.shape == (3, H, W) and img.dtype == torch.float32
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
        assert float(img.mean()) * 255 == pytest.approx(20 * i, abs=4)  # the right frame, decoded
    assert read_video(path, every=3).indices == [0, 3, 6, 9]
    assert read_video(path, frames=None).indices == list(range(N))
    assert read_video(path, frames=50).indices == list(range(N))  # a short video gives all it has
    assert read_video(path, frames=1).indices == [5]


def test_lossless_video_round_trips_exactly(tmp_path) -> None:
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(3)]
    path = write_video(tmp_path / "clip.mkv", frames, "ffv1", "bgr0")
    clip = read_video(path, frames=None)
    for arr, img in zip(frames, clip.images):
        assert torch.equal((img * 255).round().to(torch.uint8).permute(1, 2, 0), torch.from_numpy(arr))
    raw = read_video(path, frames=None, keep_uint8=True)
    for arr, img, u8 in zip(frames, clip.images, raw.images):
        assert u8.dtype == torch.uint8 and u8.shape == img.shape
        assert torch.equal(u8.permute(1, 2, 0), torch.from_numpy(arr)) and torch.equal(to_unit(u8), img)


def test_zero_byte_file(tmp_path) -> None:
    path = tmp_path / "empty.mp4"
    path.touch()
    with pytest.raises(VideoError, match=f"{path} is empty"):
        read_video(path)


def test_text_file_named_mp4(tmp_path) -> None:
    path = tmp_path / "notes.mp4"
    path.write_text("not a video at all\n" * 50)
    with pytest.raises(VideoError, match=f"{path} is not a readable video"):
        read_video(path)


def test_truncated_mp4_index_at_the_end(tmp_path) -> None:
    data = write_video(tmp_path / "clip", _ramp(30)).read_bytes()  # moov written last: the index is lost
    path = tmp_path / "cut.mp4"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(VideoError, match=f"{path}"):
        read_video(path)


def test_truncated_mp4_index_first(tmp_path) -> None:
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(30)]  # noise: large packets
    full = write_video(tmp_path / "full.mp4", frames, "mpeg4", "yuv420p", options={"movflags": "faststart"})
    path = tmp_path / "cut.mp4"
    path.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    with pytest.raises(VideoError, match=f"{path} is truncated or damaged: only \\d+ of 30 frames"):
        read_video(path, frames=30)


def test_truncated_mkv(tmp_path) -> None:
    full = write_video(tmp_path / "full.mkv", _ramp(20), "ffv1", "yuv444p")
    path = tmp_path / "cut.mkv"
    path.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    with pytest.raises(VideoError, match=f"{path} is truncated or damaged"):
        read_video(path)


def test_no_video_stream(tmp_path) -> None:
    path = tmp_path / "sound.mkv"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("pcm_s16le", rate=8000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 800), np.int16), format="s16", layout="mono")
        frame.sample_rate = 8000
        container.mux(stream.encode(frame))
        container.mux(stream.encode())
    with pytest.raises(VideoError, match=f"{path} has no video stream"):
        read_video(path)


def test_missing_file_and_bad_arguments(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="video not found: .*nope.mp4"):
        read_video(tmp_path / "nope.mp4")
    path = write_video(tmp_path / "clip", _ramp())
    with pytest.raises(ValueError, match="frames must be a positive integer"):
        read_video(path, frames=0)
    with pytest.raises(ValueError, match="every must be a positive integer"):
        read_video(path, every=-2)


def test_missing_pyav_says_how_to_install(tmp_path, monkeypatch) -> None:
    path = write_video(tmp_path / "clip", _ramp())
    monkeypatch.setitem(sys.modules, "av", None)  # import av -> ImportError
    with pytest.raises(ImportError, match="pip install av"):
        read_video(path)


def test_images_and_videos_mixed(tmp_path) -> None:
    video = write_video(tmp_path / "clip", _ramp())
    rgba = torch.rand(4, 40, 40)
    write_image(tmp_path / "poster.png", rgba)
    named = load_named_images_or_video([tmp_path / "poster.png", video], frames=3)
    assert [n for n, _ in named] == [str(tmp_path / "poster.png")] + [f"{video}#{i}" for i in (1, 5, 8)]
    poster = named[0][1]
    assert poster.shape == (3, 40, 40)  # alpha composited on black
    q = (rgba * 255).round() / 255
    assert torch.allclose(poster, q[:3] * q[3:], atol=1e-6)
    images = load_images_or_video([video], every=5)
    assert len(images) == 2 and all(img.shape == (3, H, W) for img in images)
    assert is_video("A.MP4") and is_video("b.webm") and not is_video("c.png")
    with pytest.raises(ValueError, match="no images or videos"):
        load_images_or_video([])


def test_a_folder_stands_for_its_images_and_videos(tmp_path) -> None:
    """A folder is read as its image and video files, recursively and sorted, other files skipped; an empty one,
    a missing path and a pattern without matches are errors naming them."""
    leak = tmp_path / "leak"
    (leak / "clips").mkdir(parents=True)
    video = write_video(leak / "clips" / "clip", _ramp())
    write_image(leak / "b.png", torch.rand(3, 24, 24))
    write_image(leak / "a.PNG", torch.rand(3, 24, 24))
    (leak / "notes.txt").write_text("not an image")
    named = load_named_images_or_video([leak], frames=2)
    assert [n for n, _ in named] == [str(leak / "a.PNG"), str(leak / "b.png")] + [f"{video}#{i}" for i in (2, 7)]
    # a folder and a file in it are read once; a file named explicitly is kept whatever its suffix
    assert expand_inputs([leak, leak / "b.png", leak / "notes.txt"]) == [
        leak / "a.PNG", leak / "b.png", Path(video), leak / "notes.txt"]
    assert expand_inputs([str(leak / "*.png")]) == [leak / "b.png"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=f"no images or videos found in {tmp_path / 'empty'}"):
        load_named_images_or_video([tmp_path / "empty"])
    with pytest.raises(FileNotFoundError, match="no such file or folder"):
        expand_inputs([tmp_path / "missing"])
    with pytest.raises(FileNotFoundError, match="no images or videos match"):
        expand_inputs([str(tmp_path / "*.jpg")])
