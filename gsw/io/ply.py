"""Read and write 3DGS models as PLY files in the INRIA layout.

The INRIA layout is one ``vertex`` element of float32 properties, in this order when written::

    x y z [nx ny nz] f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (for degree 3: ``f_rest_0..14`` red, ``15..29`` green, ``30..44`` blue) while
:attr:`Gaussians.sh` is coefficient-major ``[N, K, 3]``; the conversion is a pure reshape/transpose, so a
save/load round trip is bit-exact. ``opacity`` is a logit, ``scale_*`` are logs and ``rot_*`` is an
unnormalised ``(w, x, y, z)`` quaternion, exactly like the :class:`~gsw.gaussians.Gaussians` fields.

Reading accepts SH degree 0-3, files with or without normals, any property order, ``binary_little_endian``,
``binary_big_endian`` and ``ascii`` formats, and any scalar property type (converted to float32). Normals
are ignored on load (NaN normals included). Other elements may come before or after ``vertex`` when they
have no list properties (or no records).

Reading is strict about the amount of data, so that a wrong count in the header cannot drop or invent
Gaussians: the file must end exactly where the header says (binary) or hold exactly the declared number
of records plus blank lines (ASCII); a shorter file is "truncated", a longer one has "trailing data".
NaN/Inf in any property that is used and a model of 0 Gaussians are errors by default.

Example:
    >>> from gsw.io import load_ply, save_ply
    >>> g = load_ply("point_cloud.ply")  # doctest: +SKIP
    >>> save_ply(g, "copy.ply")  # doctest: +SKIP
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.gaussians import Gaussians, num_coeffs_to_sh_degree

__all__ = ["PlyError", "load_ply", "save_ply"]

_SCALAR_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": ""}
_MAX_HEADER_BYTES = 1 << 20

_REQUIRED = (
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
_NORMALS = ("nx", "ny", "nz")
_F_REST = re.compile(r"f_rest_(\d+)")
_F_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest properties -> SH degree


class PlyError(ValueError):
    """A PLY file is malformed or is not a 3DGS model in the INRIA layout."""


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type code)
    has_list: bool = False


@dataclass
class _Header:
    format: str
    elements: list[_Element]
    num_bytes: int


# ---------------------------------------------------------------------------------------------- reading


def _read_header(f, path: Path) -> _Header:
    first = f.readline(16)
    if first.rstrip(b"\r\n") != b"ply":
        raise PlyError(f"{path}: not a PLY file (first line is {first[:16]!r}, expected b'ply')")
    num_bytes = len(first)
    fmt: str | None = None
    elements: list[_Element] = []
    lineno = 1
    while True:
        line = f.readline(_MAX_HEADER_BYTES)
        lineno += 1
        num_bytes += len(line)
        if not line:
            raise PlyError(f"{path}: bad PLY header: reached end of file before 'end_header'")
        if num_bytes > _MAX_HEADER_BYTES:
            raise PlyError(f"{path}: bad PLY header: no 'end_header' in the first {_MAX_HEADER_BYTES} bytes")
        try:
            words = line.decode("ascii").split()
        except UnicodeDecodeError:
            raise PlyError(f"{path}: bad PLY header: line {lineno} is not ASCII") from None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) != 3:
                raise PlyError(f"{path}: bad PLY header: line {lineno}: expected 'format <type> 1.0'")
            if words[1] not in _FORMATS or words[2] != "1.0":
                raise PlyError(
                    f"{path}: unsupported PLY format '{words[1]} {words[2]}' "
                    f"(supported: {', '.join(_FORMATS)} with version 1.0)"
                )
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"{path}: bad PLY header: line {lineno}: expected 'element <name> <count>'")
            if any(e.name == words[1] for e in elements):
                raise PlyError(f"{path}: bad PLY header: line {lineno}: duplicate element '{words[1]}'")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise PlyError(f"{path}: bad PLY header: line {lineno}: property before any element")
            element = elements[-1]
            if len(words) == 5 and words[1] == "list" and words[2] in _SCALAR_TYPES and words[3] in _SCALAR_TYPES:
                element.has_list = True
                name, code = words[4], "list"
            elif len(words) == 3 and words[1] in _SCALAR_TYPES:
                name, code = words[2], _SCALAR_TYPES[words[1]]
            else:
                raise PlyError(f"{path}: bad PLY header: line {lineno}: cannot parse {line.decode().strip()!r}")
            if any(name == p for p, _ in element.properties):
                raise PlyError(f"{path}: bad PLY header: duplicate property '{name}' in element '{element.name}'")
            element.properties.append((name, code))
        else:
            raise PlyError(f"{path}: bad PLY header: line {lineno}: unknown keyword {key!r}")
    if fmt is None:
        raise PlyError(f"{path}: bad PLY header: missing 'format' line")
    return _Header(fmt, elements, num_bytes)


def _column_plan(vertex: _Element, path: Path, strict: bool) -> tuple[list[str], int]:
    """Names of the columns to read (INRIA order, f_rest sorted) and the SH degree."""
    names = [p for p, _ in vertex.properties]
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise PlyError(f"{path}: missing required vertex properties: {', '.join(missing)}")
    rest = sorted(int(m.group(1)) for p in names if (m := _F_REST.fullmatch(p)))
    if len(rest) not in _F_REST_COUNTS:
        raise PlyError(
            f"{path}: found {len(rest)} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0, 1, 2 or 3)"
        )
    if rest != list(range(len(rest))):
        unexpected = [f"f_rest_{i}" for i in rest if i >= len(rest)]
        absent = [f"f_rest_{i}" for i in range(len(rest)) if i not in rest]
        raise PlyError(
            f"{path}: f_rest properties must be f_rest_0..f_rest_{len(rest) - 1}; "
            f"missing: {', '.join(absent)}; unexpected: {', '.join(unexpected)}"
        )
    rest_names = [f"f_rest_{i}" for i in rest]
    known = set(_REQUIRED) | set(_NORMALS) | set(rest_names)
    unknown = [p for p in names if p not in known]
    if strict and unknown:
        raise PlyError(f"{path}: unknown vertex properties (strict=True): {', '.join(unknown)}")
    if vertex.has_list:
        lists = [p for p, code in vertex.properties if code == "list"]
        raise PlyError(f"{path}: list properties in the vertex element are not supported: {', '.join(lists)}")
    wanted = list(_REQUIRED[:6]) + rest_names + list(_REQUIRED[6:])
    return wanted, _F_REST_COUNTS[len(rest)]


def _binary_offsets(header: _Header, vertex_index: int, path: Path) -> tuple[int, int]:
    """Byte offset of the vertex data and the exact file size the header implies."""
    endian = _FORMATS[header.format]
    offset, total = header.num_bytes, header.num_bytes
    for i, element in enumerate(header.elements):
        if element.has_list and element.count:
            where = "before" if i < vertex_index else "after"
            raise PlyError(
                f"{path}: element '{element.name}' ({where} 'vertex') has list properties and {element.count} "
                "records; cannot check the vertex data against the file size (not a 3DGS model?)"
            )
        size = 0 if element.has_list else element.count * np.dtype([(p, endian + c) for p, c in element.properties]).itemsize
        if i < vertex_index:
            offset += size
        total += size
    return offset, total


def _read_binary(f, header: _Header, vertex_index: int, path: Path) -> np.ndarray:
    endian = _FORMATS[header.format]
    offset, total = _binary_offsets(header, vertex_index, path)
    vertex = header.elements[vertex_index]
    dtype = np.dtype([(p, endian + c) for p, c in vertex.properties])
    expected = vertex.count * dtype.itemsize
    size = os.fstat(f.fileno()).st_size
    if size < total:
        raise PlyError(
            f"{path}: truncated PLY data: the header declares {total - header.num_bytes} bytes of data "
            f"({vertex.count} vertices x {dtype.itemsize} bytes = {expected} bytes expected for 'vertex'), "
            f"but only {size - header.num_bytes} bytes are present"
        )
    if size > total:
        extra = size - total
        raise PlyError(
            f"{path}: {extra} bytes of trailing data after the {total - header.num_bytes} bytes the header declares "
            f"(element vertex {vertex.count} x {dtype.itemsize} bytes; {extra / dtype.itemsize:g} more vertices' worth): "
            "the header's vertex count does not match the data"
        )
    f.seek(offset)
    if all(c == "f4" for _, c in vertex.properties):
        # Fast path (the INRIA layout): read straight into one float32 matrix.
        data = np.empty((vertex.count, len(vertex.properties)), dtype=endian + "f4")
        if f.readinto(data.reshape(-1).view(np.uint8)) != expected:
            raise PlyError(f"{path}: short read of the vertex data")
        return data if data.dtype.isnative else data.astype(np.float32)
    records = np.frombuffer(f.read(expected), dtype=dtype)
    out = np.empty((vertex.count, len(vertex.properties)), dtype=np.float32)
    for i, (name, _) in enumerate(vertex.properties):
        with np.errstate(over="ignore"):  # float64 beyond float32 range becomes inf, reported by the caller
            out[:, i] = records[name]
    return out


def _read_ascii(f, header: _Header, vertex_index: int, path: Path) -> np.ndarray:
    f.seek(header.num_bytes)
    raw = f.read()
    lines = raw.splitlines()
    skip = sum(e.count for e in header.elements[:vertex_index])
    total = sum(e.count for e in header.elements)
    vertex = header.elements[vertex_index]
    rows = lines[skip : skip + vertex.count]
    if len(lines) < total:
        raise PlyError(
            f"{path}: truncated ASCII PLY data: the header declares {total} record lines "
            f"(element vertex {vertex.count}), found {len(lines)}"
        )
    extra = [i for i, line in enumerate(lines[total:]) if line.strip()]
    if extra:
        raise PlyError(
            f"{path}: {len(extra)} lines of trailing data after the {total} record lines the header declares "
            f"(element vertex {vertex.count}): the header's vertex count does not match the data"
        )
    if total and not raw.rstrip(b" \t\x0b\x0c").endswith((b"\n", b"\r")):
        raise PlyError(f"{path}: truncated ASCII PLY data: the last record line has no line break")
    num_props = len(vertex.properties)
    tokens = [row.split() for row in rows]
    wrong = next((i for i, t in enumerate(tokens) if len(t) != num_props), None)
    if wrong is not None:
        raise PlyError(
            f"{path}: malformed ASCII PLY data: vertex {wrong} has {len(tokens[wrong])} values, "
            f"expected {num_props}"
        )
    try:
        values = np.array([v for t in tokens for v in t]).astype(np.float64)
    except ValueError as exc:
        raise PlyError(f"{path}: malformed ASCII PLY data: {exc}") from None
    with np.errstate(over="ignore"):
        return values.astype(np.float32).reshape(vertex.count, num_props)


def _check_finite(data: np.ndarray, wanted: list[str], position: dict[str, int], path: Path) -> None:
    if np.isfinite(data).all():
        return
    used = [position[p] for p in wanted]
    bad = np.count_nonzero(~np.isfinite(data[:, used]), axis=0)
    if bad.any():
        details = ", ".join(f"{wanted[i]} ({bad[i]})" for i in np.flatnonzero(bad))
        raise PlyError(f"{path}: non-finite (NaN/Inf) values in properties: {details}")


def load_ply(
    path: str | os.PathLike, *, allow_nonfinite: bool = False, allow_empty: bool = False, strict: bool = False
) -> Gaussians:
    """Load a 3DGS model from an INRIA-layout PLY file.

    Args:
        path: the ``.ply`` file.
        allow_nonfinite: accept NaN/Inf values instead of raising.
        allow_empty: accept a model of 0 Gaussians instead of raising.
        strict: also reject unknown vertex properties (by default they are ignored).

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32; ``sh`` is ``[N, (d+1)^2, 3]`` with the SH
        degree ``d`` given by the number of ``f_rest_*`` properties. Normals are dropped.

    Raises:
        PlyError: the path is a directory or not a PLY, has an unsupported format or a bad header, lacks a
            required property, has a wrong number of ``f_rest_*`` properties, holds less data (truncated) or
            more data (trailing data) than the header declares, holds NaN/Inf values (unless
            ``allow_nonfinite``) or 0 Gaussians (unless ``allow_empty``); the message names the problem.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if path.is_dir():
        raise PlyError(f"{path}: is a directory, not a PLY file")
    with open(path, "rb") as f:
        header = _read_header(f, path)
        vertex_index = next((i for i, e in enumerate(header.elements) if e.name == "vertex"), None)
        if vertex_index is None:
            raise PlyError(f"{path}: no 'vertex' element in the PLY header")
        vertex = header.elements[vertex_index]
        wanted, degree = _column_plan(vertex, path, strict)
        if header.format == "ascii":
            data = _read_ascii(f, header, vertex_index, path)
        else:
            data = _read_binary(f, header, vertex_index, path)
    if vertex.count == 0 and not allow_empty:
        raise PlyError(f"{path}: the model has 0 Gaussians (element vertex 0); pass allow_empty=True to load it")
    position = {p: i for i, (p, _) in enumerate(vertex.properties)}
    if not allow_nonfinite:
        _check_finite(data, wanted, position, path)

    def columns(*names: str) -> np.ndarray:
        return _take_columns(data, [position[p] for p in names])

    n, k = vertex.count, (degree + 1) ** 2
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0] = columns("f_dc_0", "f_dc_1", "f_dc_2")
    sh[:, 1:] = columns(*(f"f_rest_{i}" for i in range(3 * (k - 1)))).reshape(n, 3, k - 1).transpose(0, 2, 1)
    return Gaussians(
        means=torch.from_numpy(np.ascontiguousarray(columns("x", "y", "z"))),
        log_scales=torch.from_numpy(np.ascontiguousarray(columns("scale_0", "scale_1", "scale_2"))),
        quats=torch.from_numpy(np.ascontiguousarray(columns("rot_0", "rot_1", "rot_2", "rot_3"))),
        opacity_logits=torch.from_numpy(np.ascontiguousarray(columns("opacity")[:, 0])),
        sh=torch.from_numpy(sh),
    )


def _take_columns(data: np.ndarray, index: list[int]) -> np.ndarray:
    """``data[:, index]`` as float32; a strided view when the columns are consecutive."""
    if index and index == list(range(index[0], index[0] + len(index))):
        out = data[:, index[0] : index[0] + len(index)]
    else:
        out = data[:, index]
    return out.astype(np.float32, copy=False)


# ---------------------------------------------------------------------------------------------- writing


def ply_property_names(sh_degree: int, normals: bool = True) -> list[str]:
    """Vertex property names of the INRIA layout, in file order.

    Args:
        sh_degree: SH degree in ``0..3``.
        normals: include ``nx ny nz``.

    Returns:
        ``["x", "y", "z", ("nx", "ny", "nz",) "f_dc_0", ..., "rot_3"]``.
    """
    num_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z"]
        + (list(_NORMALS) if normals else [])
        + ["f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def save_ply(
    gaussians: Gaussians,
    path: str | os.PathLike,
    *,
    normals: bool = True,
    allow_nonfinite: bool = False,
) -> None:
    """Write a model as a binary little-endian float32 PLY in the INRIA layout, atomically.

    The file is written to a temporary file in the same directory and then moved over ``path``
    (``os.replace``), so an existing file is replaced all at once or not at all.

    Args:
        gaussians: the model (any device/dtype; written as float32).
        path: destination ``.ply`` file; its directory must exist.
        normals: write ``nx ny nz`` (zeros) like the INRIA code does.
        allow_nonfinite: write NaN/Inf values instead of raising.

    Raises:
        PlyError: if the model holds NaN/Inf values and ``allow_nonfinite`` is false.
    """
    g = gaussians.detach().to(device="cpu", dtype=torch.float32)
    if not allow_nonfinite:
        try:
            g.check_finite()
        except ValueError as exc:
            raise PlyError(f"refusing to write {path}: {exc}") from None
    n, k = g.num_gaussians, g.sh.shape[1]
    names = ply_property_names(num_coeffs_to_sh_degree(k), normals)
    data = np.zeros((n, len(names)), dtype="<f4")  # normals stay zero
    j = 6 if normals else 3
    data[:, 0:3] = g.means.numpy()
    data[:, j : j + 3] = g.sh[:, 0].numpy()
    data[:, j + 3 : j + 3 * k] = g.sh[:, 1:].numpy().transpose(0, 2, 1).reshape(n, 3 * (k - 1))
    j += 3 * k
    data[:, j] = g.opacity_logits.numpy()
    data[:, j + 1 : j + 4] = g.log_scales.numpy()
    data[:, j + 4 : j + 8] = g.quats.numpy()
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        + "".join(f"property float {p}\n" for p in names)
        + "end_header\n"
    )
    with atomic_write(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.reshape(-1).view(np.uint8))
