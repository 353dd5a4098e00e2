"""Tests for gsw.io.spz (Niantic .spz files).

Tolerances follow from the bit widths of the format (half a quantisation step, see the module docstring):
positions 2^-(fractional_bits + 1); log scales 1/32 (8 bits over 16 units); alpha 0.5/255; the DC colour
0.5 / (0.15 * 255); SH (b/2 + 0.5) / 128 with bucket b = 2^(8 - bits) (b = 8 for degree 1, 16 above by default);
quaternions in version 3: each of the three smallest components 0.5 * sqrt(1/2) / 511, and the largest, rebuilt
as sqrt(1 - sum of squares) with value >= 1/2, at most 3 times that; in version 2: x, y, z within 0.5 / 127.5 and
w, rebuilt from them, within sqrt(2 sqrt(3) d + 3 d^2) for d = 0.5 / 127.5.
"""

from __future__ import annotations

import gzip
import math
import struct

import numpy as np
import pytest
import torch
from helpers import SHARED_DATA, random_model, require

from gsw.gaussians import Gaussians
from gsw.io import SpzError, load_gaussians, load_ply, load_spz, save_gaussians, save_spz
from gsw.io.spz import SH_FLIP_RUB_RDF, SPZ_COLOR_SCALE, SPZ_MAGIC

FIXTURE = SHARED_DATA / "ply" / "sh3_fixture" / "point_cloud.ply"

DC_LIMIT = 127.5 / (SPZ_COLOR_SCALE * 255)  # colour bytes 0 and 255
SCALE_RANGE = (-10.0, 255 / 16 - 10.0)  # scale bytes 0 and 255


def quat_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-component |a - b| of unit quaternions, with the sign of b chosen to match a ([N, 4])."""
    a = torch.nn.functional.normalize(a.double(), dim=1)
    b = torch.nn.functional.normalize(b.double(), dim=1)
    sign = torch.where((a * b).sum(1, keepdim=True) < 0, -1.0, 1.0)
    return (a - sign * b).abs()


def sh_tolerance(bits: int) -> float:
    return ((1 << (8 - bits)) / 2 + 0.5) / 128


def header(path) -> tuple:
    return struct.unpack("<IIIBBBB", gzip.decompress(path.read_bytes())[:16])


def spz_bytes(version: int, n: int, degree: int, body: bytes, frac: int = 12, flags: int = 0) -> bytes:
    return gzip.compress(struct.pack("<IIIBBBB", SPZ_MAGIC, version, n, degree, frac, flags, 0) + body)


def check_round_trip(g: Gaussians, h: Gaussians, *, version: int, frac: int = 12) -> None:
    assert len(h) == len(g) and h.sh_degree == g.sh_degree and h.dtype == torch.float32
    g, h = g.to(dtype=torch.float64), h.to(dtype=torch.float64)
    assert (h.means - g.means).abs().max() <= 2.0 ** -(frac + 1) + 1e-9
    assert (h.log_scales - g.log_scales.clamp(*SCALE_RANGE)).abs().max() <= 1 / 32 + 1e-6
    assert (h.opacities - g.opacities).abs().max() <= 0.5 / 255 + 1e-6
    dc = g.sh[:, 0].clamp(-DC_LIMIT, DC_LIMIT)
    assert (h.sh[:, 0] - dc).abs().max() <= 0.5 / (SPZ_COLOR_SCALE * 255) + 1e-6
    rest = g.sh[:, 1:].clamp(-1.0, 127 / 128)
    if g.sh_degree > 0:
        assert (h.sh[:, 1:4] - rest[:, :3]).abs().max() <= sh_tolerance(5) + 1e-6
    if g.sh_degree > 1:
        assert (h.sh[:, 4:] - rest[:, 3:]).abs().max() <= sh_tolerance(4) + 1e-6
    err = quat_error(g.quats, h.quats)
    if version == 3:
        step = 0.5 * math.sqrt(0.5) / 511
        assert err.max() <= 3 * step + 1e-6
        assert err.max() > 0  # quantised, not stored exactly
    else:
        d = 0.5 / 127.5
        signed = torch.nn.functional.normalize(g.quats.double(), dim=1)
        signed = torch.where(signed[:, :1] < 0, -signed, signed)
        assert (signed[:, 1:] - h.quats[:, 1:]).abs().max() <= d + 1e-6
        assert (signed[:, 0] - h.quats[:, 0]).abs().max() <= math.sqrt(2 * math.sqrt(3) * d + 3 * d * d) + 1e-6


@pytest.mark.parametrize("version", [2, 3])
def test_round_trip_on_the_fixture(tmp_path, version):
    g = load_ply(require(FIXTURE, "shared data"))
    save_spz(g, tmp_path / "m.spz", version=version)
    assert header(tmp_path / "m.spz") == (SPZ_MAGIC, version, len(g), 3, 12, 0, 0)
    check_round_trip(g, load_spz(tmp_path / "m.spz"), version=version)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_random_models(tmp_path, degree):
    g = random_model(700, degree=degree, seed=degree)
    save_gaussians(g, tmp_path / "m.spz")  # by extension
    raw = gzip.decompress((tmp_path / "m.spz").read_bytes())
    assert len(raw) == 16 + 700 * (9 + 1 + 3 + 3 + 4 + 3 * ((degree + 1) ** 2 - 1))
    check_round_trip(g, load_gaussians(tmp_path / "m.spz"), version=3)


def test_full_precision_sh_and_large_coordinates(tmp_path):
    g = random_model(300, degree=3, seed=5)
    g = Gaussians(g.means * 2000.0, g.log_scales, g.quats, g.opacity_logits, g.sh)  # beyond +-2048
    save_spz(g, tmp_path / "m.spz", sh1_bits=8, sh_rest_bits=8)
    frac = header(tmp_path / "m.spz")[4]
    largest = float(g.means.abs().max())
    assert frac < 12 and round(largest * 2 ** frac) < 2 ** 23 <= round(largest * 2 ** (frac + 1))
    h = load_spz(tmp_path / "m.spz")
    assert (h.means.double() - g.means.double()).abs().max() <= 2.0 ** -(frac + 1) + 1e-9
    assert (h.sh[:, 1:] - g.sh[:, 1:].clamp(-1, 127 / 128)).abs().max() <= sh_tolerance(8) + 1e-6
    with pytest.raises(SpzError, match="overflows"):
        save_spz(g, tmp_path / "x.spz", fractional_bits=12)
    far = Gaussians(g.means * 1e4, g.log_scales, g.quats, g.opacity_logits, g.sh)
    with pytest.raises(SpzError, match="exceeds the SPZ range"):
        save_spz(far, tmp_path / "x.spz")
    assert not (tmp_path / "x.spz").exists()


def test_files_are_in_rub_coordinates(tmp_path):
    """SPZ stores RUB: y and z of positions and quaternions are flipped w.r.t. the PLY (RDF) model."""
    q = torch.nn.functional.normalize(torch.tensor([[0.9, 0.1, 0.3, -0.2]]), dim=1)
    sh = torch.zeros(1, 4, 3)
    sh[0, 1:, 0] = torch.tensor([0.25, 0.5, -0.75])  # red: the three degree-1 coefficients
    g = Gaussians(torch.tensor([[1.0, 2.0, -3.0]]), torch.zeros(1, 3), q, torch.zeros(1), sh)
    save_spz(g, tmp_path / "m.spz", version=2, sh1_bits=8)
    raw = np.frombuffer(gzip.decompress((tmp_path / "m.spz").read_bytes())[16:], dtype=np.uint8)
    fixed = [int.from_bytes(bytes(raw[3 * i : 3 * i + 3]), "little", signed=True) for i in range(3)]
    assert fixed == [4096, -2 * 4096, 3 * 4096]
    xyz = raw[9 + 1 + 3 + 3 : 9 + 1 + 3 + 3 + 3] / 127.5 - 1.0  # version 2 stores x, y, z with w >= 0
    np.testing.assert_allclose(xyz, [q[0, 1], -q[0, 2], -q[0, 3]], atol=0.5 / 127.5)
    sh_red = (raw[9 + 1 + 3 + 3 + 3 :: 3][:3].astype(float) - 128) / 128
    np.testing.assert_allclose(sh_red, [-0.25, -0.5, -0.75], atol=0.5 / 128)  # flips of y, z: [-1, -1, +1]
    torch.testing.assert_close(load_spz(tmp_path / "m.spz").means, g.means)
    # legacy files holding the PLY's axes: axes="RDF" stores and loads them unflipped
    save_spz(g, tmp_path / "rdf.spz", version=2, sh1_bits=8, axes="RDF")
    raw = np.frombuffer(gzip.decompress((tmp_path / "rdf.spz").read_bytes())[16:], dtype=np.uint8)
    assert int.from_bytes(bytes(raw[3:6]), "little", signed=True) == 2 * 4096
    legacy, flipped = load_spz(tmp_path / "rdf.spz", axes="RDF"), load_spz(tmp_path / "rdf.spz")
    torch.testing.assert_close(legacy.means, g.means)
    torch.testing.assert_close(flipped.means, g.means * torch.tensor([1.0, -1.0, -1.0]))
    torch.testing.assert_close(flipped.quats, legacy.quats * torch.tensor([1.0, 1.0, -1.0, -1.0]))
    torch.testing.assert_close(flipped.sh[0, 1:, 0], legacy.sh[0, 1:, 0] * torch.tensor([-1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="axes must be one of"):
        load_spz(tmp_path / "rdf.spz", axes="LUF")


def test_sh_flip_table_matches_the_basis():
    from gsw.render._reference import reference_sh_basis

    dirs = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64), dim=1)
    flipped = dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    ratio = reference_sh_basis(3, flipped)[:, 1:] / reference_sh_basis(3, dirs)[:, 1:]
    torch.testing.assert_close(ratio, torch.tensor(SH_FLIP_RUB_RDF, dtype=torch.float64).expand(64, 15))


def test_decodes_hand_made_files(tmp_path):
    # version 3, one point: largest component w (index 3), x = +sqrt(1/2) * 511/511, y = 0, z = -sqrt(1/2) * 0/511
    comp = (3 << 30) | (511 << 20) | (0 << 10) | (1 << 9)
    body = (bytes([0x00, 0x10, 0x00]) + bytes([0x00, 0xF0, 0xFF]) + bytes([0x00, 0x00, 0x80])  # 1, -1, -2048
            + bytes([255]) + bytes([128, 255, 0]) + bytes([160, 0, 255]) + struct.pack("<I", comp))
    (tmp_path / "a.spz").write_bytes(spz_bytes(3, 1, 0, body))
    g = load_spz(tmp_path / "a.spz")
    torch.testing.assert_close(g.means, torch.tensor([[1.0, 1.0, 2048.0]]))  # y, z flipped into RDF
    torch.testing.assert_close(g.log_scales, torch.tensor([[0.0, -10.0, 255 / 16 - 10]]))
    assert torch.isfinite(g.opacity_logits).all() and g.opacities.item() > 0.999
    dc = (torch.tensor([128, 255, 0]) / 255 - 0.5) / SPZ_COLOR_SCALE
    torch.testing.assert_close(g.sh[0, 0], dc.float())
    s = math.sqrt(0.5)
    torch.testing.assert_close(g.quats, torch.tensor([[s, s, 0.0, 0.0]]), atol=1e-6, rtol=0)  # (w, x, -y, -z)
    # version 1: float16 positions and version-2 quaternions
    body = (np.array([1.5, -2.0, 0.25], dtype="<f2").tobytes() + bytes([0]) + bytes([128] * 3) + bytes([160] * 3)
            + bytes([128, 128, 255]))
    (tmp_path / "b.spz").write_bytes(spz_bytes(1, 1, 0, body))
    g = load_spz(tmp_path / "b.spz")
    torch.testing.assert_close(g.means, torch.tensor([[1.5, 2.0, -0.25]]))
    assert torch.isfinite(g.opacity_logits).all() and g.opacities.item() < 1e-3
    # bytes (128, 128, 255): x = y = 0.5 / 127.5, z = 1, so w = 0; into RDF (w, x, -y, -z)
    torch.testing.assert_close(g.quats, torch.tensor([[0.0, 0.0, 0.0, -1.0]]), atol=1 / 127.5, rtol=0)


def test_extension_records_are_skipped(tmp_path):
    g = random_model(40, degree=1, seed=3)
    save_spz(g, tmp_path / "plain.spz")
    raw = gzip.decompress((tmp_path / "plain.spz").read_bytes())
    head = bytearray(raw[:16])
    head[14] |= 0x2
    extension = struct.pack("<IIfff", 0xADBE0002, 12, 0.1, 0.2, 3.0)
    (tmp_path / "ext.spz").write_bytes(gzip.compress(bytes(head) + extension + raw[16:]))
    a, b = load_spz(tmp_path / "plain.spz"), load_spz(tmp_path / "ext.spz")
    for name, t in a.parameters().items():
        assert torch.equal(t, b.parameters()[name]), name


def test_rejects_malformed_files(tmp_path):
    g = random_model(10, degree=1)
    save_spz(g, tmp_path / "ok.spz")
    raw = gzip.decompress((tmp_path / "ok.spz").read_bytes())
    cases = {
        "not.spz": (b"hello world", "not an .spz file"),
        "v4.spz": (b"NGSP\x04\x00\x00\x00" + bytes(24), "version 4"),
        "magic.spz": (gzip.compress(b"XXXX" + raw[4:]), "bad .spz magic"),
        "version.spz": (gzip.compress(raw[:4] + struct.pack("<I", 7) + raw[8:]), "unsupported .spz version 7"),
        "degree.spz": (gzip.compress(raw[:12] + bytes([4]) + raw[13:]), "SH degree 4"),
        "short.spz": (gzip.compress(raw[:-5]), "truncated .spz data"),
        "long.spz": (gzip.compress(raw + b"\0\0"), "more data than the header"),
        "header.spz": (gzip.compress(raw[:10]), "truncated .spz"),
        "gzip.spz": ((tmp_path / "ok.spz").read_bytes()[:-30], "truncated gzip|corrupt gzip"),
    }
    for name, (content, match) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(SpzError, match=match):
            load_spz(tmp_path / name)
    with pytest.raises(FileNotFoundError):
        load_spz(tmp_path / "missing.spz")


def test_rejects_bad_models_and_options(tmp_path):
    g = random_model(5)
    bad = Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits.clone().fill_(float("nan")), g.sh)
    with pytest.raises(SpzError, match="opacity_logits"):
        save_spz(bad, tmp_path / "a.spz")
    with pytest.raises(SpzError, match="version must be 2 or 3"):
        save_spz(g, tmp_path / "a.spz", version=1)
    with pytest.raises(SpzError, match="sh1_bits"):
        save_spz(g, tmp_path / "a.spz", sh1_bits=9)
    with pytest.raises(SpzError, match="compresslevel"):
        save_spz(g, tmp_path / "a.spz", compresslevel=10)
    assert not list(tmp_path.iterdir())


def test_compression_level_changes_only_the_size(tmp_path):
    g = random_model(400, degree=3, seed=3)
    for level in (0, 1, 6, 9):
        save_spz(g, tmp_path / f"m{level}.spz", compresslevel=level)
    payloads = {level: gzip.decompress((tmp_path / f"m{level}.spz").read_bytes()) for level in (0, 1, 6, 9)}
    assert len(set(payloads.values())) == 1
    sizes = [(tmp_path / f"m{level}.spz").stat().st_size for level in (0, 9)]
    assert sizes[1] < sizes[0]  # level 0 stores, 9 deflates


def test_zero_quaternion_and_empty_model(tmp_path):
    g = random_model(3, degree=0)
    g.quats[1] = 0.0
    save_spz(g, tmp_path / "z.spz")
    torch.testing.assert_close(load_spz(tmp_path / "z.spz").quats[1], torch.tensor([1.0, 0.0, 0.0, 0.0]))
    save_spz(Gaussians.empty(2), tmp_path / "e.spz")
    e = load_spz(tmp_path / "e.spz")
    assert len(e) == 0 and e.sh_degree == 2
