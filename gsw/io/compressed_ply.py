"""Read and write the PlayCanvas / SuperSplat "compressed PLY" format (``*.compressed.ply``).

A binary PLY with two or three elements:

- ``chunk`` (``ceil(N / 256)`` rows of float32): per chunk of 256 consecutive splats the bounds ``min_x min_y
  min_z max_x max_y max_z``, ``min_scale_x..z max_scale_x..z`` (of the log scales) and, in the 18-property
  variant, ``min_r min_g min_b max_r max_g max_b`` (of the colours ``0.5 + SH_C0 * f_dc``);
- ``vertex`` (``N`` rows of uint32 ``packed_position packed_rotation packed_scale packed_color``):
  position and log scale as 11/10/11-bit unsigned fractions of the chunk's range (x in the top 11 bits),
  the colour as 8/8/8 bits of the chunk's colour range (or of ``[0, 1]`` without it) with 8 bits of
  ``sigmoid(opacity)`` in the low byte, and the unit quaternion ``rot_0..3 = (w, x, y, z)`` as "smallest
  three": 2 bits of the index of the largest component (made positive), then the three others in order, each
  10 bits of ``q * sqrt(1/2) + 0.5``;
- optional ``sh`` (``N`` rows of uchar ``f_rest_0..``, 9, 24 or 45 of them, channel-major like INRIA's):
  ``trunc(256 * (v / 8 + 0.5))`` clamped to 0-255, decoded as ``8 * ((b + 0.5) / 256 - 0.5)`` with bytes 0
  and 255 mapping to -4 and 4.

Fractions are packed as ``floor(t * (2^bits - 1) + 0.5)``; a range under ``1e-5`` packs 0 (its minimum).
Coordinates are PLY's (RDF, like INRIA's), so no axis conversion applies. Writing sorts the splats into Morton
order (:func:`morton_order`) by default so each chunk's bounds are tight, as SuperSplat does.

Example:
    >>> from gsw.io.compressed_ply import load_compressed_ply, save_compressed_ply
    >>> g = load_compressed_ply("scene.compressed.ply")  # doctest: +SKIP
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.constants import SH_C0, SH_COLOR_OFFSET
from gsw.gaussians import Gaussians
from gsw.io.ply import PlyError, _read_header
from gsw.io.splat import ALPHA_EPS

__all__ = ["CompressedPlyError", "load_compressed_ply", "save_compressed_ply", "is_compressed_ply",
           "morton_order", "CHUNK_SIZE", "CHUNK_PROPERTIES", "VERTEX_PROPERTIES"]

CHUNK_SIZE = 256
"""Splats per chunk."""

CHUNK_PROPERTIES = (
    "min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
    "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
    "min_r", "min_g", "min_b", "max_r", "max_g", "max_b",
)
"""Chunk properties in file order (the first 12 are required, the colour bounds optional)."""

VERTEX_PROPERTIES = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
"""Vertex properties (uint32)."""

_SCALE_LIMIT = 20.0  # chunk log-scale bounds are clamped to +-20 (infinite scales happen)
_MIN_RANGE = 1e-5
_SH_COUNTS = {9: 1, 24: 2, 45: 3}


class CompressedPlyError(PlyError):
    """A compressed PLY file is malformed."""


def is_compressed_ply(path: str | os.PathLike) -> bool:
    """Whether a PLY file's header has the compressed layout (a ``chunk`` element and packed vertices).

    Raises:
        PlyError: the header itself is malformed.
    """
    path = Path(path)
    with open(path, "rb") as f:
        header = _read_header(f, path)
    names = {e.name: [p for p, _ in e.properties] for e in header.elements}
    return "chunk" in names and "packed_position" in names.get("vertex", [])


def morton_order(means: torch.Tensor) -> torch.Tensor:
    """Permutation sorting points along a 3-D Morton (Z-order) curve, 10 bits per axis of their bounding box.

    Args:
        means: ``[N, 3]`` positions.

    Returns:
        ``[N]`` int64 permutation (stable for equal codes).
    """
    p = means.detach().double().cpu().numpy()
    if len(p) == 0:
        return torch.zeros(0, dtype=torch.int64)
    lo, hi = p.min(0), p.max(0)
    cell = np.clip(np.floor((p - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023.0), 0, 1023).astype(np.uint64)
    code = np.zeros(len(p), dtype=np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cell[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + 2 - axis)
    return torch.from_numpy(np.argsort(code, kind="stable"))


# ---------------------------------------------------------------------------------------------- reading


def _element_dtype(element, endian: str) -> np.dtype:
    return np.dtype([(name, endian + code) for name, code in element.properties])


def _check_layout(elements: dict, path: Path) -> int:
    """Validates the element layout; returns the SH degree."""
    unknown = sorted(set(elements) - {"chunk", "vertex", "sh"})
    if unknown or "chunk" not in elements or "vertex" not in elements:
        raise CompressedPlyError(f"{path}: a compressed PLY has the elements chunk, vertex and optionally sh; "
                                 f"found {', '.join(elements)}")
    chunk, vertex = elements["chunk"], elements["vertex"]
    chunk_props = [p for p, _ in chunk.properties]
    if chunk_props not in (list(CHUNK_PROPERTIES[:12]), list(CHUNK_PROPERTIES)) or \
            any(code != "f4" for _, code in chunk.properties):
        raise CompressedPlyError(f"{path}: chunk properties must be float {' '.join(CHUNK_PROPERTIES[:12])} "
                                 f"[{' '.join(CHUNK_PROPERTIES[12:])}]; found {' '.join(chunk_props)}")
    if vertex.properties != [(p, "u4") for p in VERTEX_PROPERTIES]:
        found = " ".join(f"{p}:{c}" for p, c in vertex.properties)
        raise CompressedPlyError(f"{path}: vertex properties must be uint {' '.join(VERTEX_PROPERTIES)}; "
                                 f"found {found}")
    if chunk.count != math.ceil(vertex.count / CHUNK_SIZE):
        raise CompressedPlyError(f"{path}: {chunk.count} chunks for {vertex.count} splats "
                                 f"(expected ceil({vertex.count} / {CHUNK_SIZE}))")
    if "sh" not in elements:
        return 0
    sh = elements["sh"]
    names = [p for p, _ in sh.properties]
    if len(names) not in _SH_COUNTS or names != [f"f_rest_{i}" for i in range(len(names))] or \
            any(code != "u1" for _, code in sh.properties):
        raise CompressedPlyError(f"{path}: the sh element must hold uchar f_rest_0..f_rest_(9|24|45 - 1); "
                                 f"found {len(names)} properties")
    if sh.count != vertex.count:
        raise CompressedPlyError(f"{path}: {sh.count} sh rows for {vertex.count} splats")
    return _SH_COUNTS[len(names)]


def _read_elements(path: Path) -> tuple[dict[str, np.ndarray], int]:
    with open(path, "rb") as f:
        header = _read_header(f, path)
        if header.format == "ascii":
            raise CompressedPlyError(f"{path}: an ASCII compressed PLY is not supported (the format is binary)")
        endian = "<" if header.format == "binary_little_endian" else ">"
        elements = {e.name: e for e in header.elements}
        if len(elements) != len(header.elements):
            raise CompressedPlyError(f"{path}: duplicate element names in the header")
        degree = _check_layout(elements, path)
        dtypes = [_element_dtype(e, endian) for e in header.elements]
        expected = sum(e.count * d.itemsize for e, d in zip(header.elements, dtypes))
        f.seek(header.num_bytes)
        raw = f.read(expected + 1)
    if len(raw) < expected:
        raise CompressedPlyError(f"{path}: truncated compressed PLY: {expected} data bytes expected after the "
                                 f"header, found {len(raw)}")
    out, offset = {}, 0
    for element, dtype in zip(header.elements, dtypes):
        out[element.name] = np.frombuffer(raw, dtype=dtype, count=element.count, offset=offset)
        offset += element.count * dtype.itemsize
    return out, degree


def _unpack_fraction(value: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((value >> np.uint32(shift)) & np.uint32((1 << bits) - 1)) / float((1 << bits) - 1)


def _unpack_111011(value: np.ndarray) -> np.ndarray:
    return np.stack([_unpack_fraction(value, 21, 11), _unpack_fraction(value, 11, 10),
                     _unpack_fraction(value, 0, 11)], axis=1)


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    return lo * (1.0 - t) + hi * t


def _unpack_rotation(value: np.ndarray) -> np.ndarray:
    n = len(value)
    largest = (value >> np.uint32(30)).astype(np.int64)
    q = np.zeros((n, 4))
    rows = np.arange(n)
    for j in range(3):  # the first stored component sits in bits 20-29
        index = np.array([[i for i in range(4) if i != k][j] for k in range(4)])[largest]
        q[rows, index] = (_unpack_fraction(value, 20 - 10 * j, 10) - 0.5) * math.sqrt(2.0)
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (q * q).sum(1)))
    return q


def load_compressed_ply(path: str | os.PathLike) -> Gaussians:
    """Load a PlayCanvas / SuperSplat compressed PLY.

    Args:
        path: the file.

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32, in file order (usually Morton order, not the
        order of the model it was made from); opacities are ``logit(clamp(alpha, ALPHA_EPS, 1 - ALPHA_EPS))``.

    Raises:
        CompressedPlyError: wrong elements or properties, inconsistent counts, truncated data, non-finite
            chunk bounds. :class:`~gsw.io.ply.PlyError` for a malformed PLY header.
    """
    path = Path(path)
    data, degree = _read_elements(path)
    chunk, vertex = data["chunk"], data["vertex"]
    n = len(vertex)
    bounds = np.stack([chunk[name].astype(np.float64) for name in chunk.dtype.names], axis=1)
    if not np.isfinite(bounds).all():
        raise CompressedPlyError(f"{path}: non-finite chunk bounds")
    bounds = np.repeat(bounds, CHUNK_SIZE, axis=0)[:n]
    means = _lerp(bounds[:, 0:3], bounds[:, 3:6], _unpack_111011(vertex["packed_position"]))
    log_scales = _lerp(bounds[:, 6:9], bounds[:, 9:12], _unpack_111011(vertex["packed_scale"]))
    color = vertex["packed_color"]
    rgb = np.stack([_unpack_fraction(color, shift, 8) for shift in (24, 16, 8)], axis=1)
    if bounds.shape[1] == 18:
        rgb = _lerp(bounds[:, 12:15], bounds[:, 15:18], rgb)
    alpha = torch.from_numpy(_unpack_fraction(color, 0, 8)).clamp(ALPHA_EPS, 1.0 - ALPHA_EPS)
    k = (degree + 1) ** 2
    sh = np.empty((n, k, 3))
    sh[:, 0] = (rgb - SH_COLOR_OFFSET) / SH_C0
    if degree:
        b = np.stack([data["sh"][f"f_rest_{i}"] for i in range(3 * (k - 1))], axis=1).astype(np.float64)
        v = np.where(b == 0, -4.0, np.where(b == 255, 4.0, ((b + 0.5) / 256.0 - 0.5) * 8.0))
        sh[:, 1:] = v.reshape(n, 3, k - 1).transpose(0, 2, 1)
    return Gaussians(
        means=torch.from_numpy(means).float(),
        log_scales=torch.from_numpy(log_scales).float(),
        quats=torch.from_numpy(_unpack_rotation(vertex["packed_rotation"])).float(),
        opacity_logits=torch.logit(alpha).float(),
        sh=torch.from_numpy(sh).float(),
    )


# ---------------------------------------------------------------------------------------------- writing


def _chunk_bounds(values: np.ndarray, num_chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max of ``[N, C]`` values (the last chunk padded with its last row)."""
    n = len(values)
    padded = np.concatenate([values, np.repeat(values[-1:], num_chunks * CHUNK_SIZE - n, axis=0)])
    blocks = padded.reshape(num_chunks, CHUNK_SIZE, -1)
    return blocks.min(1), blocks.max(1)


def _pack_fraction(values: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    """Quantise ``values`` (rows matching ``lo``/``hi`` per chunk, repeated) to ``bits`` unsigned bits."""
    span = hi - lo
    t = np.where(span < _MIN_RANGE, 0.0, (values - lo) / np.where(span < _MIN_RANGE, 1.0, span))
    top = (1 << bits) - 1
    return np.clip(np.floor(np.clip(t, 0.0, 1.0) * top + 0.5), 0, top).astype(np.uint32)


def _pack_111011(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    parts = [_pack_fraction(values[:, i], lo[:, i], hi[:, i], bits) for i, bits in enumerate((11, 10, 11))]
    return (parts[0] << np.uint32(21)) | (parts[1] << np.uint32(11)) | parts[2]


def _pack_rotation(quats: np.ndarray) -> np.ndarray:
    q = quats.copy()
    q[np.linalg.norm(q, axis=1) == 0] = (1.0, 0.0, 0.0, 0.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows = np.arange(len(q))
    largest = np.argmax(np.abs(q), axis=1)
    q *= np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    packed = largest.astype(np.uint32)
    for j in range(3):
        index = np.array([[i for i in range(4) if i != k][j] for k in range(4)])[largest]
        value = np.clip(np.floor((q[rows, index] * math.sqrt(0.5) + 0.5) * 1023.0 + 0.5), 0, 1023)
        packed = (packed << np.uint32(10)) | value.astype(np.uint32)
    return packed


def save_compressed_ply(gaussians: Gaussians, path: str | os.PathLike, *, sort: bool = True) -> None:
    """Write a model as a compressed PLY (18-property chunks, SH as the optional ``sh`` element), atomically.

    Args:
        gaussians: the model (any device/dtype/SH degree).
        path: destination file (conventionally ``*.compressed.ply``); its directory must exist.
        sort: write in Morton order (:func:`morton_order`), which keeps chunk bounds tight; with
            ``sort=False`` the model order is kept (``load_compressed_ply(...)[i]`` is ``gaussians[i]``)
            at the cost of coarser positions and scales.

    Raises:
        CompressedPlyError: the model holds NaN/Inf values.
    """
    g = gaussians.detach().to(device="cpu", dtype=torch.float64)
    try:
        g.check_finite()
    except ValueError as exc:
        raise CompressedPlyError(f"refusing to write {path}: {exc}") from None
    if sort:
        g = g[morton_order(g.means)]
    n, k = g.num_gaussians, g.sh.shape[1]
    num_chunks = math.ceil(n / CHUNK_SIZE)
    means, log_scales = g.means.numpy(), g.log_scales.numpy()
    rgb = SH_COLOR_OFFSET + SH_C0 * g.sh[:, 0].numpy()
    chunk = np.zeros((num_chunks, len(CHUNK_PROPERTIES)), dtype="<f4")
    vertex = np.zeros((n, len(VERTEX_PROPERTIES)), dtype="<u4")
    if n:
        repeat = lambda a: np.repeat(a, CHUNK_SIZE, axis=0)[:n]  # noqa: E731
        p_lo, p_hi = _chunk_bounds(means, num_chunks)
        s_lo, s_hi = (np.clip(b, -_SCALE_LIMIT, _SCALE_LIMIT) for b in _chunk_bounds(log_scales, num_chunks))
        c_lo, c_hi = _chunk_bounds(rgb, num_chunks)
        chunk[:] = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], axis=1)
        # Quantise against the float32 bounds the reader will see.
        b = chunk.astype(np.float64)
        vertex[:, 0] = _pack_111011(means, repeat(b[:, 0:3]), repeat(b[:, 3:6]))
        vertex[:, 1] = _pack_rotation(g.quats.numpy())
        vertex[:, 2] = _pack_111011(log_scales, repeat(b[:, 6:9]), repeat(b[:, 9:12]))
        colors = [_pack_fraction(rgb[:, i], repeat(b[:, 12 + i]), repeat(b[:, 15 + i]), 8) for i in range(3)]
        alpha = _pack_fraction(g.opacities.numpy(), np.zeros(n), np.ones(n), 8)
        vertex[:, 3] = (colors[0] << np.uint32(24)) | (colors[1] << np.uint32(16)) | (colors[2] << np.uint32(8)) \
            | alpha
    rest = g.sh[:, 1:].numpy().transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # channel-major like INRIA
    sh = np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)
    lines = ["ply", "format binary_little_endian 1.0", "comment Generated by gsw",
             f"element chunk {num_chunks}", *(f"property float {p}" for p in CHUNK_PROPERTIES),
             f"element vertex {n}", *(f"property uint {p}" for p in VERTEX_PROPERTIES)]
    if k > 1:
        lines += [f"element sh {n}", *(f"property uchar f_rest_{i}" for i in range(3 * (k - 1)))]
    header = "\n".join(lines + ["end_header"]) + "\n"
    with atomic_write(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(chunk.tobytes())
        f.write(vertex.tobytes())
        if k > 1:
            f.write(np.ascontiguousarray(sh).tobytes())
