"""Tests for gsw.io.compressed_ply (PlayCanvas / SuperSplat compressed PLY).

Tolerances follow from the bit widths (half a step of the quantiser, see the module docstring): per chunk of
256 splats, positions and log scales (11, 10, 11 bits for x, y, z) within span / (2 (2^bits - 1)) of the
chunk's span; colours 0.5 / 255 of the chunk's colour span; alpha 0.5 / 255; SH 8 / 256 (codes 0 and 255
decode to -4 and 4, half a step wider); quaternions: the three smallest components within sqrt(2) / 2046, the
largest (>= 1/2, rebuilt from the others) within 3 times that. Float32 storage of the chunk bounds and of
the decoded values adds a few float32 ulps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import SHARED_DATA, random_model, require

from gsw.constants import SH_C0
from gsw.gaussians import Gaussians
from gsw.io import CompressedPlyError, PlyError, load_compressed_ply, load_gaussians, load_ply, model_format, \
    save_compressed_ply, save_gaussians
from gsw.io.compressed_ply import CHUNK_PROPERTIES, CHUNK_SIZE, VERTEX_PROPERTIES, is_compressed_ply, morton_order

FIXTURE = SHARED_DATA / "ply" / "sh3_fixture" / "point_cloud.ply"
EPS32 = float(np.finfo(np.float32).eps)


def chunk_span(values: torch.Tensor) -> torch.Tensor:
    """[N, C] -> per-row span (max - min) of the row's chunk."""
    n = len(values)
    chunks = torch.split(values.double(), CHUNK_SIZE)
    span = torch.cat([(c.max(0).values - c.min(0).values).expand(len(c), -1) for c in chunks])
    assert len(span) == n
    return span


def quat_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a = torch.nn.functional.normalize(a.double(), dim=1)
    b = torch.nn.functional.normalize(b.double(), dim=1)
    return torch.where((a * b).sum(1, keepdim=True) < 0, a + b, a - b).abs()


def check_round_trip(g: Gaussians, h: Gaussians) -> None:
    """``h`` is ``g`` (already in file order) after a compressed-PLY round trip."""
    assert len(h) == len(g) and h.sh_degree == g.sh_degree and h.dtype == torch.float32
    bits = torch.tensor([11, 10, 11], dtype=torch.float64)
    for name in ("means", "log_scales"):
        a, b = getattr(g, name).double(), getattr(h, name).double()
        span = chunk_span(a)
        slack = 4 * EPS32 * a.abs().max()
        tol = torch.where(span < 1e-5, span, span / (2 * (2 ** bits - 1))) + slack
        assert ((b - a).abs() <= tol).all(), name
    rgb_a, rgb_b = 0.5 + SH_C0 * g.sh[:, 0].double(), 0.5 + SH_C0 * h.sh[:, 0].double()
    assert ((rgb_b - rgb_a).abs() <= chunk_span(rgb_a) / 510 + 4 * EPS32 * rgb_a.abs().max()).all()
    assert (h.opacities.double() - g.opacities.double()).abs().max() <= 0.5 / 255 + 1e-6
    step = math.sqrt(2) / 2046
    assert quat_error(g.quats, h.quats).max() <= 3 * step + 1e-6
    if g.sh_degree:
        assert (h.sh[:, 1:].double() - g.sh[:, 1:].double().clamp(-4, 4)).abs().max() <= 8 / 256 + 1e-6


def test_round_trip_on_the_fixture(tmp_path):
    g = load_ply(require(FIXTURE, "shared data"))
    save_compressed_ply(g, tmp_path / "m.compressed.ply")
    h = load_compressed_ply(tmp_path / "m.compressed.ply")
    check_round_trip(g[morton_order(g.means)], h)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_random_models_in_model_order(tmp_path, degree):
    g = random_model(600, degree=degree, seed=degree)
    save_compressed_ply(g, tmp_path / "m.ply", sort=False)
    check_round_trip(g, load_gaussians(tmp_path / "m.ply"))  # detected by its header


def test_morton_order_makes_chunks_tighter():
    means = torch.rand(64 * CHUNK_SIZE, 3, generator=torch.Generator().manual_seed(7))  # 64 chunks in a cube
    order = morton_order(means)
    assert sorted(order.tolist()) == list(range(len(means)))
    # 64 chunks along a Z-order curve are 4x4x4 cells: about a quarter of the cube's side each
    assert chunk_span(means[order]).mean() < 0.5 * chunk_span(means).mean()


def test_file_layout(tmp_path):
    g = random_model(300, degree=2)
    save_gaussians(g, tmp_path / "m.compressed.ply")  # the name chooses the compressed writer
    data = (tmp_path / "m.compressed.ply").read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element chunk 2" in lines and "element vertex 300" in lines and "element sh 300" in lines
    assert [ln.split()[-1] for ln in lines if ln.startswith("property float")] == list(CHUNK_PROPERTIES)
    assert [ln.split()[-1] for ln in lines if ln.startswith("property uint")] == list(VERTEX_PROPERTIES)
    assert sum(ln.startswith("property uchar f_rest_") for ln in lines) == 24
    assert len(body) == 2 * 18 * 4 + 300 * 16 + 300 * 24
    assert model_format(tmp_path / "m.compressed.ply") == "compressed-ply"
    assert is_compressed_ply(tmp_path / "m.compressed.ply")
    save_gaussians(g, tmp_path / "plain.ply")
    assert model_format(tmp_path / "plain.ply") == "ply" and not is_compressed_ply(tmp_path / "plain.ply")


def write_one_splat(path, *, position: int, rotation: int, scale: int, color: int, chunk: list[float],
                    sh: list[int] | None = None) -> None:
    props = CHUNK_PROPERTIES[: len(chunk)]
    head = ["ply", "format binary_little_endian 1.0", "element chunk 1", *(f"property float {p}" for p in props),
            "element vertex 1", *(f"property uint {p}" for p in VERTEX_PROPERTIES)]
    if sh is not None:
        head += ["element sh 1", *(f"property uchar f_rest_{i}" for i in range(len(sh)))]
    body = np.array(chunk, "<f4").tobytes() + np.array([position, rotation, scale, color], "<u4").tobytes()
    body += bytes(sh or [])
    path.write_bytes(("\n".join(head) + "\nend_header\n").encode() + body)


def test_decodes_a_hand_made_file(tmp_path):
    chunk = [0, 10, -4, 2, 20, 4, -1, -2, -3, 1, 2, 3]  # 12-property chunk: colours in [0, 1]
    position = (2047 << 21) | (0 << 11) | 1023  # x = max, y = min, z = 1023/2047 of the span
    rotation = (0 << 30) | (512 << 20) | (1023 << 10) | 0  # largest w; x ~ 0, y = +sqrt(1/2), z = -sqrt(1/2)
    scale = (0 << 21) | (1023 << 11) | 2047
    color = (255 << 24) | (0 << 16) | (51 << 8) | 255
    sh = [0, 255] + [128] * 7
    write_one_splat(tmp_path / "a.ply", position=position, rotation=rotation, scale=scale, color=color, chunk=chunk,
                    sh=sh)
    g = load_gaussians(tmp_path / "a.ply")
    torch.testing.assert_close(g.means, torch.tensor([[2.0, 10.0, -4 + 8 * 1023 / 2047]]))
    torch.testing.assert_close(g.log_scales, torch.tensor([[-1.0, 2.0, 3.0]]))
    torch.testing.assert_close(0.5 + SH_C0 * g.sh[0, 0], torch.tensor([1.0, 0.0, 0.2]))
    assert torch.isfinite(g.opacity_logits).all() and g.opacities.item() > 0.999
    s = math.sqrt(0.5)
    x = (512 / 1023 - 0.5) * math.sqrt(2)
    torch.testing.assert_close(g.quats, torch.tensor([[0.0, x, s, -s]]), atol=1e-6, rtol=0)  # w: sqrt(max(0, .))
    sh_red = g.sh[0, 1:, 0]  # f_rest_0..2 are red
    torch.testing.assert_close(sh_red, torch.tensor([-4.0, 4.0, 8 * (128.5 / 256 - 0.5)]))


def test_rejects_malformed_files(tmp_path):
    ok = dict(position=0, rotation=3 << 30, scale=0, color=0, chunk=[0.0] * 12)
    write_one_splat(tmp_path / "good.ply", **ok)
    assert len(load_compressed_ply(tmp_path / "good.ply")) == 1
    write_one_splat(tmp_path / "sh.ply", **ok, sh=[0] * 5)
    with pytest.raises(CompressedPlyError, match="f_rest"):
        load_compressed_ply(tmp_path / "sh.ply")
    write_one_splat(tmp_path / "chunk.ply", **{**ok, "chunk": [0.0] * 10})
    with pytest.raises(CompressedPlyError, match="chunk properties"):
        load_compressed_ply(tmp_path / "chunk.ply")
    data = (tmp_path / "good.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(data[:-3])
    with pytest.raises(CompressedPlyError, match="truncated"):
        load_compressed_ply(tmp_path / "short.ply")
    (tmp_path / "count.ply").write_bytes(data.replace(b"element chunk 1", b"element chunk 2"))
    with pytest.raises(CompressedPlyError, match="2 chunks for 1 splats"):
        load_compressed_ply(tmp_path / "count.ply")
    (tmp_path / "ascii.ply").write_bytes(data.replace(b"binary_little_endian", b"ascii"))
    with pytest.raises(CompressedPlyError, match="ASCII"):
        load_compressed_ply(tmp_path / "ascii.ply")
    (tmp_path / "nan.ply").write_bytes(data[: -16 - 48] + np.array([np.nan] * 12, "<f4").tobytes() + data[-16:])
    with pytest.raises(CompressedPlyError, match="non-finite"):
        load_compressed_ply(tmp_path / "nan.ply")
    save_gaussians(random_model(4), tmp_path / "inria.ply")
    with pytest.raises(CompressedPlyError, match="elements chunk, vertex"):
        load_compressed_ply(tmp_path / "inria.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(PlyError):
        load_gaussians(tmp_path / "junk.ply")
    bad = random_model(4)
    bad.means[0, 0] = float("inf")
    with pytest.raises(CompressedPlyError, match="means"):
        save_compressed_ply(bad, tmp_path / "bad.compressed.ply")
    assert not (tmp_path / "bad.compressed.ply").exists()


def test_empty_model(tmp_path):
    save_compressed_ply(Gaussians.empty(1), tmp_path / "e.compressed.ply")
    e = load_compressed_ply(tmp_path / "e.compressed.ply")
    assert len(e) == 0 and e.sh_degree == 1
