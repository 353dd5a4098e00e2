"""Shared test helpers (imported by the test modules as `helpers`)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from gsw.gaussians import Gaussians

#: ../shared/data beside the project root (also present in CI).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def require(path: Path, what: str = "test data") -> Path:
    """Returns `path` if it exists; otherwise fails under CI (env CI set) and skips elsewhere."""
    if not Path(path).exists():
        message = f"missing {what}: {path}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return Path(path)


def random_model(n: int, degree: int = 3, seed: int = 0) -> Gaussians:
    """n seeded random Gaussians (unnormalised quaternions, small scales, SH coefficients in [-1, 1))."""
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g) * 2,
        sh=torch.rand(n, (degree + 1) ** 2, 3, generator=g) * 2 - 1,
    )


#: Python source that makes ``import gsw._C`` fail (prepend to ``python -c`` code run in a subprocess).
BLOCK_EXTENSION = """
import importlib.abc, sys
class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "gsw._C":
            raise ImportError("blocked for the test")
sys.meta_path.insert(0, _Block())
"""


def scan_crawl(root: Path) -> list:
    """A crawl for ``gsw scan`` tests in ``root``, returned with its registered marks.

    Files: six 96x96 PNG renders of the built-in scene, two 80x112 JPEG renders (another size), a lossless
    3-frame 96x96 video (FFV1 in Matroska) of one view, an unreadable PNG and an empty video. Marks
    (registry ``root/marks.sqlite``): messages read from the files themselves (so that they identify
    their source without an embedding), of both origins, with and without an embedding size, plus five
    unrelated random messages. Returns the marks (:meth:`gsw.registry.Registry.list`).
    """
    import av
    import numpy as np

    from gsw.data.images import write_image
    from gsw.io.video import load_images_or_video
    from gsw.mark.detect import extract
    from gsw.mark.message import message_to_hex, random_message
    from gsw.registry import open_registry, shipped_decoder_sha256
    from gsw.render.rasterize import rasterize
    from gsw.scenes import default_scene

    def renders(width: int, height: int, n: int) -> list[torch.Tensor]:
        scene = default_scene(width=width, height=height, n_cameras=n, detail=0.3)
        return [rasterize(scene.gaussians, cam, background=scene.background).image.clamp(0, 1)
                for cam in scene.cameras]

    root.mkdir(parents=True, exist_ok=True)
    square = renders(96, 96, 7)
    for i, img in enumerate(square[:6]):
        write_image(root / f"img{i}.png", img)
    for i, img in enumerate(renders(112, 80, 2)):
        write_image(root / f"wide{i}.jpg", img)
    frame = (square[6].permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
    with av.open(str(root / "clip.mkv"), "w") as container:
        stream = container.add_stream("ffv1", rate=10)
        stream.width, stream.height, stream.pix_fmt = 96, 96, "bgr0"
        for _ in range(3):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")))
        container.mux(stream.encode())
    (root / "broken.png").write_bytes(b"not a png")
    (root / "empty.mp4").write_bytes(b"")

    def bits(name: str) -> str:
        return message_to_hex(extract(load_images_or_video([root / name], 16)[0], num_bits=32).bits[0])

    sha = shipped_decoder_sha256(32)
    marks = [dict(label="alice", message=bits("img1.png"), origin="random", width=96, height=96),
             dict(label="bob", message=bits("wide0.jpg"), origin="chosen"),
             dict(label="carol", message=bits("clip.mkv"), origin="random"),
             dict(label="dave", message=bits("img3.png"), origin="chosen", width=96, height=96)]
    marks += [dict(label=f"other{i}", message=message_to_hex(random_message(32, seed=i)), origin="random")
              for i in range(5)]
    with open_registry(root / "marks.sqlite") as reg:
        reg.add_many([dict(m, decoder_sha256=sha) for m in marks])
        return reg.list()


class ReadsOnes(torch.nn.Module):
    """A 32-bit decoder that reads every bit as 1 with logit 5: a message of ones always passes, a random one reads
    about half its bits and never all of them."""

    def __init__(self) -> None:
        super().__init__()
        self.bias = torch.nn.Parameter(torch.full((32,), 5.0))

    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        return self.bias.expand(ll.shape[0], 32) + 0 * ll.mean()
