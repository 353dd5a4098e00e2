"""Read and write Niantic's ``.spz`` format (compressed 3DGS models, Scaniverse / web viewers).

An ``.spz`` file (versions 1-3) is one gzip stream holding a 16-byte little-endian header::

    uint32 magic = 0x5053474e ("NGSP")   uint32 version   uint32 num_points
    uint8 sh_degree   uint8 fractional_bits   uint8 flags (0x1 antialiased, 0x2 extensions)   uint8 reserved

then, when ``flags & 0x2``, vendor extension records, then the attributes, each for every point in turn:

- positions: 3 x 24-bit signed fixed point, ``round(p * 2^fractional_bits)`` (version 1: 3 x float16),
- alphas: 1 byte, ``round(255 * sigmoid(opacity_logit))``,
- colours: 3 bytes, ``round(f_dc * 0.15 * 255 + 127.5)`` (the DC SH coefficient, not the RGB),
- scales: 3 bytes, ``round((log_scale + 10) * 16)``,
- rotations: version 3 packs the unit quaternion ``(x, y, z, w)`` as "smallest three" in a little-endian
  uint32: bits 30-31 the index of the largest component (made positive), then the three others in order
  from bit 29 down, each 1 sign bit + a 9-bit magnitude of ``|q_i| / sqrt(1/2)``; versions 1-2 store
  ``x, y, z`` of the quaternion with ``w >= 0`` as ``round(127.5 * q + 127.5)``,
- SH: ``3 * ((d + 1)^2 - 1)`` bytes per point, coefficient-major with the colour channel fastest (the
  :attr:`~gsw.gaussians.Gaussians.sh` layout), ``round(128 * x) + 128`` rounded to buckets of
  ``2^(8 - bits)`` (Niantic's defaults: 5 bits for degree 1, 4 bits above) and decoded as ``(b - 128) / 128``.

SPZ stores RUB coordinates (x right, y up, z back; OpenGL / three.js) while INRIA PLY files are RDF (x right,
y down, z forward). Like Niantic's own PLY converters, reading flips the y and z axes into RDF (positions,
quaternions ``(w, x, -y, -z)`` and the SH coefficients odd in y*z) and writing flips them back, so a model
renders identically from the same :mod:`gsw.camera` cameras after a round trip. Files written without that
conversion (Niantic's library with an ``UNSPECIFIED`` source frame stores a PLY's axes unchanged) load as
stored with ``axes="RDF"``.

Supported: reading versions 1, 2 and 3 (extension records are skipped; the antialiased flag is ignored, gsw
renders without that compensation; an SH degree 4 file is rejected as :class:`~gsw.gaussians.Gaussians` holds
degrees 0-3), writing versions 2 and 3 (default 3). The zstd-based
"NGSP" container of version 4 is not supported and is rejected with a message saying so.

Example:
    >>> from gsw.io.spz import load_spz, save_spz
    >>> g = load_spz("scene.spz")  # doctest: +SKIP
    >>> save_spz(g, "copy.spz", version=2)  # doctest: +SKIP
"""

from __future__ import annotations

import gzip
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.gaussians import Gaussians
from gsw.io.splat import ALPHA_EPS

__all__ = ["SpzError", "load_spz", "save_spz", "SPZ_MAGIC", "SPZ_COLOR_SCALE", "SH_FLIP_RUB_RDF"]

SPZ_MAGIC = 0x5053474E
"""Header magic (the bytes ``NGSP``)."""

SPZ_COLOR_SCALE = 0.15
"""Colour bytes hold ``f_dc * SPZ_COLOR_SCALE * 255 + 127.5``."""

SH_FLIP_RUB_RDF = (-1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0)
"""Sign of SH coefficients 1..15 under the RUB <-> RDF flip ``(x, y, z) -> (x, -y, -z)``."""

_HEADER = struct.Struct("<IIIBBBB")
_FLAG_EXTENSIONS = 0x2
_SQRT1_2 = math.sqrt(0.5)
_MAX_EXTENSION_BYTES = 1 << 20  # extension records are small (camera limits, quantisation parameters)
_AXES = ("RUB", "RDF")


def _flips(axes: str, num_rest: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sign flips (positions ``[3]``, quaternions ``(w, x, y, z)`` ``[4]``, SH rest ``[num_rest, 1]``) between
    the file's axes and RDF; the flip is its own inverse."""
    if axes not in _AXES:
        raise ValueError(f"axes must be one of {_AXES}, got {axes!r}")
    if axes == "RDF":
        return np.ones(3), np.ones(4), np.ones((num_rest, 1))
    return (np.array([1.0, -1.0, -1.0]), np.array([1.0, 1.0, -1.0, -1.0]),
            np.asarray(SH_FLIP_RUB_RDF[:num_rest])[:, None])


class SpzError(ValueError):
    """An ``.spz`` file is malformed or of an unsupported version."""


def _point_bytes(version: int, sh_degree: int) -> int:
    position = 6 if version == 1 else 9
    rotation = 4 if version >= 3 else 3
    return position + 1 + 3 + 3 + rotation + 3 * ((sh_degree + 1) ** 2 - 1)


def _inflate(raw: bytes, path: Path) -> tuple[tuple[int, ...], bytes]:
    """Decompresses the header, checks it, then at most the bytes it announces (bounded memory)."""
    if raw[:4] == b"NGSP":
        raise SpzError(f"{path}: SPZ version 4 container (uncompressed NGSP header, zstd payload) is not "
                       "supported; supported: SPZ versions 1-3 (one gzip stream)")
    if raw[:2] != b"\x1f\x8b":
        raise SpzError(f"{path}: not an .spz file (no gzip stream: starts with {raw[:4]!r})")
    stream = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = stream.decompress(raw, _HEADER.size)
        if len(head) < _HEADER.size:
            raise SpzError(f"{path}: truncated .spz: {len(head)} bytes after decompression, the header needs "
                           f"{_HEADER.size}")
        fields = _HEADER.unpack(head)
        magic, version, n, degree, frac, flags, _ = fields
        if magic != SPZ_MAGIC:
            raise SpzError(f"{path}: bad .spz magic 0x{magic:08x} (expected 0x{SPZ_MAGIC:08x}, 'NGSP')")
        if version not in (1, 2, 3):
            raise SpzError(f"{path}: unsupported .spz version {version} (supported: 1, 2, 3)")
        if degree > 3:
            raise SpzError(f"{path}: SH degree {degree} is not supported (gsw models hold SH degrees 0-3)")
        if frac > 24:
            raise SpzError(f"{path}: fractional_bits {frac} exceeds the 24-bit positions")
        expected = n * _point_bytes(version, degree)
        limit = expected + (_MAX_EXTENSION_BYTES if flags & _FLAG_EXTENSIONS else 0)
        body = stream.decompress(stream.unconsumed_tail, limit + 1)
    except zlib.error as exc:
        raise SpzError(f"{path}: corrupt gzip stream ({exc})") from None
    if len(body) > limit:
        raise SpzError(f"{path}: more data than the header announces ({n} points, SH degree {degree})")
    if not stream.eof and len(body) < limit:
        raise SpzError(f"{path}: truncated gzip stream (ended before its end-of-stream marker)")
    extra = len(body) - expected
    if extra < 0:
        raise SpzError(f"{path}: truncated .spz data: {n} points need {expected} bytes after the header, "
                       f"found {len(body)}")
    if extra and not flags & _FLAG_EXTENSIONS:
        raise SpzError(f"{path}: {extra} unexpected bytes after the {n} points")
    return fields, body[extra:]  # extension records precede the attributes; they are skipped


def _unpack_smallest_three(packed: np.ndarray) -> np.ndarray:
    """``[N, 4]`` bytes -> ``[N, 4]`` unit quaternions ``(x, y, z, w)``."""
    comp = packed.astype(np.uint32)
    comp = comp[:, 0] | (comp[:, 1] << 8) | (comp[:, 2] << 16) | (comp[:, 3] << 24)
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((len(comp), 4))
    slot = np.arange(4)
    for j in range(3):  # the three stored components, last one in the lowest bits
        value = _SQRT1_2 * (comp >> (10 * j) & 511) / 511.0
        value = np.where((comp >> (10 * j + 9)) & 1, -value, value)
        # component j from the end among the indices other than `largest`
        index = np.array([[i for i in slot if i != k][2 - j] for k in range(4)])[largest]
        q[np.arange(len(comp)), index] = value
    q[np.arange(len(comp)), largest] = np.sqrt(np.maximum(0.0, 1.0 - (q * q).sum(1)))
    return q


def _pack_smallest_three(q: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit quaternions ``(x, y, z, w)`` -> ``[N, 4]`` bytes."""
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(n), largest] < 0
    comp = largest.astype(np.uint32)
    for j in range(3):  # first stored component ends in the highest bits
        index = np.array([[i for i in range(4) if i != k][j] for k in range(4)])[largest]
        value = q[np.arange(n), index]
        sign = ((value < 0) ^ negate).astype(np.uint32)
        mag = np.minimum(np.floor(511.0 * np.abs(value) / _SQRT1_2 + 0.5), 511).astype(np.uint32)
        comp = (comp << 10) | (sign << 9) | mag
    return comp.astype("<u4").view(np.uint8).reshape(n, 4)


def _decode(fields: tuple[int, ...], body: bytes, axes: str) -> Gaussians:
    _, version, n, degree, frac, _, _ = fields
    k = (degree + 1) ** 2
    data = np.frombuffer(body, dtype=np.uint8)
    offset = 0

    def take(size: int) -> np.ndarray:
        nonlocal offset
        out = data[offset : offset + n * size].reshape(n, size)
        offset += n * size
        return out

    if version == 1:
        positions = take(6).copy().view("<f2").astype(np.float64)
    else:
        raw = take(9).reshape(n, 3, 3).astype(np.int32)
        fixed = raw[..., 0] | (raw[..., 1] << 8) | (raw[..., 2] << 16)
        fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
        positions = fixed / float(1 << frac)
    alphas = take(1)[:, 0] / 255.0
    colors = take(3)
    scales = take(3)
    if version >= 3:
        xyzw = _unpack_smallest_three(take(4))
    else:
        xyz = take(3) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(1)))[:, None]], axis=1)
    sh_rest = (take(3 * (k - 1)).reshape(n, k - 1, 3) - 128.0) / 128.0
    sh = np.concatenate([((colors / 255.0 - 0.5) / SPZ_COLOR_SCALE)[:, None], sh_rest], axis=1)
    flip_p, flip_q, flip_sh = _flips(axes, k - 1)
    positions = positions * flip_p
    quats = np.stack([xyzw[:, 3], xyzw[:, 0], xyzw[:, 1], xyzw[:, 2]], axis=1) * flip_q
    sh[:, 1:] *= flip_sh
    alpha = torch.from_numpy(alphas).clamp(ALPHA_EPS, 1.0 - ALPHA_EPS)
    return Gaussians(
        means=torch.from_numpy(positions).float(),
        log_scales=torch.from_numpy(scales / 16.0 - 10.0).float(),
        quats=torch.from_numpy(quats).float(),
        opacity_logits=torch.logit(alpha).float(),
        sh=torch.from_numpy(sh).float(),
    )


def load_spz(path: str | os.PathLike, *, axes: str = "RUB") -> Gaussians:
    """Load an ``.spz`` file (versions 1-3).

    Args:
        path: the ``.spz`` file.
        axes: the file's axes: ``"RUB"`` (the SPZ specification; converted to RDF) or ``"RDF"`` (files
            holding a PLY's axes; loaded as stored).

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32, in file order, converted to the INRIA/PLY
        (RDF) axes. Opacities decode as ``logit(clamp(alpha, ALPHA_EPS, 1 - ALPHA_EPS))`` (alpha bytes 0 and
        255 stay finite); quaternions are unit length up to quantisation.

    Raises:
        SpzError: not a gzip stream, bad magic, unsupported version (including the version 4 container) or
            SH degree, truncated or oversized data, or non-finite decoded values.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    fields, body = _inflate(path.read_bytes(), path)
    g = _decode(fields, body, axes)
    try:
        return g.check_finite()
    except ValueError as exc:
        raise SpzError(f"{path}: {exc}") from None


def _fractional_bits(positions: np.ndarray, requested: int | None, path: str | os.PathLike) -> int:
    """Niantic's 12 fractional bits, fewer when a coordinate would overflow the 24-bit range."""
    largest = float(np.abs(positions).max(initial=0.0))
    fits = lambda bits: round(largest * (1 << bits)) <= (1 << 23) - 1  # noqa: E731
    if requested is not None:
        if not 0 <= requested <= 23:
            raise SpzError(f"refusing to write {path}: fractional_bits must be in 0..23, got {requested}")
        if not fits(requested):
            raise SpzError(f"refusing to write {path}: |coordinate| {largest:g} overflows 24-bit fixed point "
                           f"with {requested} fractional bits")
        return requested
    for bits in range(12, -1, -1):
        if fits(bits):
            return bits
    raise SpzError(f"refusing to write {path}: |coordinate| {largest:g} exceeds the SPZ range (2^23)")


def _quantise_sh(values: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.clip(np.rint(values * 128.0) + 128.0, 0, 255)
    return np.clip((q + bucket // 2) // bucket * bucket, 0, 255).astype(np.uint8)


def _u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def save_spz(gaussians: Gaussians, path: str | os.PathLike, *, version: int = 3, sh1_bits: int = 5,
             sh_rest_bits: int = 4, fractional_bits: int | None = None, axes: str = "RUB",
             compresslevel: int = 6) -> None:
    """Write a model as an ``.spz`` file, atomically.

    Args:
        gaussians: the model (any device/dtype, SH degree 0-3), INRIA/PLY (RDF) axes.
        path: destination file; its directory must exist.
        version: 3 (smallest-three quaternions, 32 bits) or 2 (``x, y, z`` bytes, for older readers).
        sh1_bits: precision of the degree-1 SH coefficients, 1-8 (Niantic's default 5).
        sh_rest_bits: precision of the degree-2 and 3 coefficients, 1-8 (default 4).
        fractional_bits: fixed-point fraction bits of the positions; default 12 (Niantic's, 1/4096 units),
            fewer when a coordinate beyond 2048 would overflow.
        axes: the file's axes, ``"RUB"`` (the specification: y and z flipped from the model's RDF) or ``"RDF"``.
        compresslevel: the gzip level, 0-9. The default 6 (zlib's) wrote a 163k-Gaussian model in 0.7 s against
            3.5 s at 9, 5.6 % larger (BENCHMARKS.md 8a); the level changes only the file's size, never what it holds.

    Raises:
        SpzError: NaN/Inf values, a bad option, or positions beyond the 24-bit range.
    """
    if version not in (2, 3):
        raise SpzError(f"refusing to write {path}: .spz version must be 2 or 3, got {version}")
    if compresslevel not in range(10):
        raise SpzError(f"refusing to write {path}: compresslevel must be in 0..9, got {compresslevel!r}")
    for name, bits in (("sh1_bits", sh1_bits), ("sh_rest_bits", sh_rest_bits)):
        if not 1 <= bits <= 8:
            raise SpzError(f"refusing to write {path}: {name} must be in 1..8, got {bits}")
    g = gaussians.detach().to(device="cpu", dtype=torch.float64)
    try:
        g.check_finite()
    except ValueError as exc:
        raise SpzError(f"refusing to write {path}: {exc}") from None
    n, k = g.num_gaussians, g.sh.shape[1]
    flip_p, flip_q, flip_sh = _flips(axes, k - 1)
    positions = g.means.numpy() * flip_p
    frac = _fractional_bits(positions, fractional_bits, path)
    fixed = np.rint(positions * (1 << frac)).astype(np.int64) & 0xFFFFFF
    position_bytes = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, fixed >> 16], axis=-1).astype(np.uint8)
    wxyz = g.quats.numpy().copy()
    wxyz[np.linalg.norm(wxyz, axis=1) == 0] = (1.0, 0.0, 0.0, 0.0)  # a zero quaternion: identity
    wxyz /= np.linalg.norm(wxyz, axis=1, keepdims=True)
    wxyz *= flip_q
    xyzw = np.stack([wxyz[:, 1], wxyz[:, 2], wxyz[:, 3], wxyz[:, 0]], axis=1)
    if version == 3:
        rotations = _pack_smallest_three(xyzw)
    else:
        xyzw *= np.where(xyzw[:, 3:] < 0, -1.0, 1.0)
        rotations = _u8(xyzw[:, :3] * 127.5 + 127.5)
    sh_rest = g.sh[:, 1:].numpy() * flip_sh
    sh_bytes = np.concatenate([_quantise_sh(sh_rest[:, :3], sh1_bits), _quantise_sh(sh_rest[:, 3:], sh_rest_bits)],
                              axis=1)
    header = _HEADER.pack(SPZ_MAGIC, version, n, g.sh_degree, frac, 0, 0)
    parts = [
        position_bytes,
        _u8(g.opacities.numpy() * 255.0),
        _u8(g.sh[:, 0].numpy() * (SPZ_COLOR_SCALE * 255.0) + 127.5),
        _u8((g.log_scales.numpy() + 10.0) * 16.0),
        rotations,
        sh_bytes,
    ]
    payload = header + b"".join(np.ascontiguousarray(p).tobytes() for p in parts)
    with atomic_write(path, "wb") as f:
        f.write(gzip.compress(payload, compresslevel=compresslevel, mtime=0))
