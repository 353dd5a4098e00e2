"""Fuzz suite for the input readers (issue #28): a seeded corpus (numpy RNG, no extra dependency) of PLY,
.splat, cameras.json and image files and of watermark messages, mutated from valid inputs or drawn at random.

Every input must either load cleanly, with content equal to an independent decode written here (so nothing is
silently changed), or raise the reader's documented error class with a message naming the file or problem:
``PlyError``, ``SplatError``, ``CameraFileError``, ``ImageError`` (all ``ValueError`` subclasses) and
``ValueError`` for :func:`gsw.mark.message.as_message`. Any other exception type is a failure, as is an input
taking more than ``MAX_SECONDS`` (inputs are tiny, so a slow one means a hang-like bug).
"""

from __future__ import annotations

import io
import json
import math
import struct
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import torch

from gsw.camera_io import CameraFileError, load_inria_cameras
from gsw.data.images import ImageError, read_image
from gsw.io.ply import PlyError, load_ply, ply_property_names
from gsw.io.splat import MAX_ABS_POSITION, SCALE_RANGE, SPLAT_DTYPE, SplatError, load_splat
from gsw.mark.message import as_message, message_to_hex
from test_data_images import png_bytes

SEED = 28
COUNTS = {"ply": 700, "splat": 400, "cameras": 500, "images": 300, "messages": 500}
MAX_SECONDS = 10.0
SH_C0 = 0.5 / math.sqrt(math.pi)  # the degree-0 SH basis constant, written independently of gsw


class Outcomes:
    """Runs inputs and records every violation (reported together, the first 15 shown)."""

    def __init__(self, kind: str) -> None:
        self.kind, self.count, self.failures, self.errors = kind, 0, [], 0

    def run(self, name: str, fn: Callable[[], Any]) -> tuple[Any, BaseException | None]:
        self.count += 1
        start = time.perf_counter()
        try:
            value, exc = fn(), None
        except Exception as e:  # noqa: BLE001 - every exception type is inspected
            value, exc = None, e
        if time.perf_counter() - start > MAX_SECONDS:
            self.fail(name, f"took {time.perf_counter() - start:.1f} s")
        self.errors += exc is not None
        return value, exc

    def fail(self, name: str, problem: str) -> None:
        self.failures.append(f"{name}: {problem}")

    def expect_error(self, name: str, exc: BaseException | None, cls: type, *fragments: str) -> None:
        """``exc`` must be exactly of the documented class and its message must hold every fragment."""
        if exc is None:
            self.fail(name, f"loaded, expected {cls.__name__} ({', '.join(fragments)})")
        elif type(exc) is not cls:
            self.fail(name, f"{type(exc).__name__} instead of {cls.__name__}: {exc}")
        else:
            missing = [f for f in fragments if f not in str(exc)]
            if missing:
                self.fail(name, f"message lacks {missing}: {exc}")

    def report(self, minimum: int) -> None:
        print(f"fuzz {self.kind}: {self.count} inputs, {self.errors} rejected, {self.count - self.errors} loaded, "
              f"{len(self.failures)} failures")
        assert self.count >= minimum
        assert not self.failures, "\n".join(self.failures[:15])


# ---------------------------------------------------------------------------------------------- PLY

_PLY_TYPES = {"binary_little_endian": "<f4", "binary_big_endian": ">f4"}


def _ply_base(rng: np.random.Generator) -> dict[str, Any]:
    """A valid PLY: its bytes, the header length, the property names and the columns it holds."""
    degree, normals, n = int(rng.integers(0, 4)), bool(rng.random() < 0.5), int(rng.integers(1, 7))
    fmt = str(rng.choice(["binary_little_endian", "binary_big_endian", "ascii"], p=[0.5, 0.25, 0.25]))
    names = ply_property_names(degree, normals)
    if rng.random() < 0.3:
        names = [str(p) for p in rng.permutation(names)]
    if rng.random() < 0.3:
        names.insert(int(rng.integers(0, len(names) + 1)), "extra_field")
    cols = {p: (rng.standard_normal(n) * 3).astype(np.float32) for p in names}
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {n}\n" + "".join(f"property float {p}\n" for p in names)
              + "end_header\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(cols[p][i])) for p in names) + "\n" for i in range(n)).encode()
    else:
        body = np.stack([cols[p] for p in names], 1).astype(_PLY_TYPES[fmt]).tobytes()
    return dict(data=header + body, header=len(header), names=names, cols=cols, fmt=fmt, degree=degree, n=n)


def _ply_expected(cols: dict[str, np.ndarray], degree: int) -> dict[str, np.ndarray]:
    """The Gaussians fields the INRIA layout means, decoded here (channel-major f_rest)."""
    n, k = len(cols["x"]), (degree + 1) ** 2
    sh = np.zeros((n, k, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = cols[f"f_dc_{c}"]
        for j in range(k - 1):
            sh[:, 1 + j, c] = cols[f"f_rest_{c * (k - 1) + j}"]
    stack = lambda *ps: np.stack([cols[p] for p in ps], 1)  # noqa: E731
    return dict(means=stack("x", "y", "z"), log_scales=stack("scale_0", "scale_1", "scale_2"),
                quats=stack("rot_0", "rot_1", "rot_2", "rot_3"), opacity_logits=cols["opacity"], sh=sh)


def _same_bits(g, expected: dict[str, np.ndarray]) -> str | None:
    for name, want in expected.items():
        got = g.parameters()[name].numpy()
        if got.shape != want.shape or not np.array_equal(got.view(np.uint32), want.astype(np.float32).view(np.uint32)):
            return f"{name} differs from the independent decode"
    return None


def _ply_mutation(rng: np.random.Generator, base: dict[str, Any]) -> tuple[str, bytes, Any]:
    """(kind, bytes, expectation): "error" + message fragments, or the expected fields (or "same")."""
    data, h, n, fmt = base["data"], base["header"], base["n"], base["fmt"]
    kind = str(rng.choice(["valid", "count", "truncate", "append", "header_flip", "body_flip", "nonfinite",
                           "garbage", "empty"]))
    if kind == "count":
        m = int(rng.choice([x for x in range(0, n + 4) if x != n]))
        return kind, data.replace(f"element vertex {n}\n".encode(), f"element vertex {m}\n".encode()), \
            ("error", "trailing data" if m < n else "truncated")
    if kind == "truncate":
        return kind, data[: int(rng.integers(0, len(data)))], ("error",)
    if kind == "append":
        extra = rng.bytes(int(rng.integers(1, 40)))
        benign = fmt == "ascii" and not extra.strip()
        return kind, data + extra, "same" if benign else ("error", "trailing data")
    if kind == "header_flip":
        buf = bytearray(data)
        buf[int(rng.integers(0, h))] = int(rng.integers(0, 256))
        return kind, bytes(buf), "same_or_error"
    if kind == "body_flip" and fmt != "ascii":
        buf = bytearray(data)
        for _ in range(int(rng.integers(1, 5))):
            buf[int(rng.integers(h, len(buf)))] = int(rng.integers(0, 256))
        rows = np.frombuffer(bytes(buf[h:]), _PLY_TYPES[fmt]).reshape(n, -1).astype(np.float32)
        return kind, bytes(buf), {p: rows[:, i] for i, p in enumerate(base["names"])}
    if kind == "nonfinite" and fmt != "ascii":
        used = [p for p in base["names"] if p not in ("nx", "ny", "nz", "extra_field")]
        prop = str(rng.choice(used))
        rows = np.frombuffer(data[h:], _PLY_TYPES[fmt]).reshape(n, -1).copy()
        rows[int(rng.integers(0, n)), base["names"].index(prop)] = rng.choice([np.nan, np.inf, -np.inf])
        return kind, data[:h] + rows.tobytes(), ("error", "non-finite", f"{prop} (1)")
    if kind == "garbage":
        prefix = [b"", b"ply\n", b"ply\nformat binary_little_endian 1.0\nelement vertex 2\n"][int(rng.integers(0, 3))]
        return kind, prefix + rng.bytes(int(rng.integers(0, 200))), ("error",)
    if kind == "empty":
        names = "".join(f"property float {p}\n" for p in base["names"])
        return kind, f"ply\nformat {fmt} 1.0\nelement vertex 0\n{names}end_header\n".encode(), \
            ("error", "0 Gaussians")
    return "valid", data, "same"


def test_fuzz_ply(tmp_path):
    rng, out = np.random.default_rng(SEED), Outcomes("ply")
    path = tmp_path / "m.ply"
    for i in range(COUNTS["ply"]):
        base = _ply_base(rng)
        kind, data, expect = _ply_mutation(rng, base)
        name = f"ply #{i} ({kind}, {base['fmt']}, degree {base['degree']}, n {base['n']})"
        path.write_bytes(data)
        g, exc = out.run(name, lambda: load_ply(path))
        if isinstance(expect, tuple):
            out.expect_error(name, exc, PlyError, str(path), *expect[1:])
            continue
        if exc is not None:  # an error is acceptable only for damage the reader may not survive
            if expect == "same" or (isinstance(expect, dict) and all(
                    np.isfinite(v).all() for p, v in expect.items() if p not in ("nx", "ny", "nz", "extra_field"))):
                out.fail(name, f"valid input rejected: {type(exc).__name__}: {exc}")
            else:
                out.expect_error(name, exc, PlyError, str(path))
            continue
        cols = base["cols"] if expect in ("same", "same_or_error") else expect
        problem = _same_bits(g, _ply_expected(cols, base["degree"]))
        if problem:
            out.fail(name, f"loaded silently changed content: {problem}")
    out.report(COUNTS["ply"])


# ---------------------------------------------------------------------------------------------- .splat


def _splat_decode(data: bytes) -> np.ndarray | None:
    """The records if the bytes are a plausible .splat file (the module's documented rule), else None."""
    if not data or len(data) % 32:
        return None
    rec = np.frombuffer(data, SPLAT_DTYPE)
    with np.errstate(invalid="ignore"):
        pos, scale = rec["position"].astype(np.float64), rec["scale"].astype(np.float64)
        ok = (np.isfinite(pos).all() and np.isfinite(scale).all() and (np.abs(pos) <= MAX_ABS_POSITION).all()
              and ((scale >= SCALE_RANGE[0]) & (scale <= SCALE_RANGE[1])).all() and not (rec["rot"] == 128).all(1).any())
    return rec if ok else None


def _splat_check(g, rec: np.ndarray) -> str | None:
    if len(g) != len(rec) or g.sh_degree != 0:
        return f"{len(g)} splats of degree {g.sh_degree}, expected {len(rec)} of degree 0"
    rgb = (0.5 + SH_C0 * g.sh[:, 0].double()).numpy() * 255
    checks = {
        "means": np.array_equal(g.means.numpy(), rec["position"]),
        "scales": np.allclose(g.log_scales.double().exp().numpy(), rec["scale"], rtol=4e-6, atol=0),
        "colours": np.allclose(rgb, rec["rgba"][:, :3], rtol=0, atol=1e-3),
        "alpha": np.allclose(g.opacities.double().numpy() * 255, rec["rgba"][:, 3], rtol=0, atol=1e-3),
        "quats": np.array_equal(g.quats.numpy(), (rec["rot"].astype(np.float32) - 128) / 128),
    }
    bad = [k for k, ok in checks.items() if not ok]
    return f"{', '.join(bad)} differ from the independent decode" if bad else None


def _splat_valid(rng: np.random.Generator) -> bytes:
    n = int(rng.integers(1, 6))
    rec = np.zeros(n, SPLAT_DTYPE)
    rec["position"] = rng.uniform(-50, 50, (n, 3))
    rec["scale"] = np.exp(rng.uniform(-8, 2, (n, 3)))
    rec["rgba"] = rng.integers(0, 256, (n, 4))
    rec["rot"] = rng.integers(0, 256, (n, 4))
    rec["rot"][:, 0] = rng.choice([0, 255], n)  # never all 128
    return rec.tobytes()


def _splat_input(rng: np.random.Generator) -> tuple[str, bytes]:
    kind = str(rng.choice(["valid", "random", "random64", "bad_size", "flip", "truncate", "edge"]))
    if kind == "random":
        return kind, rng.bytes(32 * int(rng.integers(1, 5)))
    if kind == "random64":
        return kind, rng.bytes(64)
    if kind == "bad_size":
        return kind, rng.bytes(int(rng.choice([0, 1, 31, 33, 63, 65, 100])))
    data = _splat_valid(rng)
    if kind == "flip":
        buf = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            buf[int(rng.integers(0, len(buf)))] = int(rng.integers(0, 256))
        return kind, bytes(buf)
    if kind == "truncate":
        return kind, data[: int(rng.integers(0, len(data)))]
    if kind == "edge":
        rec = np.frombuffer(data, SPLAT_DTYPE).copy()
        field, value = [("position", np.nan), ("position", 2e7), ("position", -1e7), ("scale", 0.0),
                        ("scale", -1.0), ("scale", 1e-10), ("scale", 1e7), ("scale", 1.1e7), ("scale", np.inf),
                        ("rot", 128)][int(rng.integers(0, 10))]
        rec[field][int(rng.integers(0, len(rec)))] = value
        return f"edge {field}={value}", rec.tobytes()
    return kind, data


def test_fuzz_splat(tmp_path):
    rng, out = np.random.default_rng(SEED + 1), Outcomes("splat")
    path = tmp_path / "m.splat"
    random_loaded = 0
    for i in range(COUNTS["splat"]):
        kind, data = _splat_input(rng)
        name = f"splat #{i} ({kind}, {len(data)} bytes)"
        path.write_bytes(data)
        g, exc = out.run(name, lambda: load_splat(path))
        rec = _splat_decode(data)
        if rec is None:
            out.expect_error(name, exc, SplatError, str(path))
        elif exc is not None:
            out.fail(name, f"plausible input rejected: {type(exc).__name__}: {exc}")
        else:
            random_loaded += kind.startswith("random")
            problem = _splat_check(g, rec)
            if problem:
                out.fail(name, f"loaded silently changed content: {problem}")
    assert random_loaded == 0, "random bytes loaded as a model"
    out.report(COUNTS["splat"])


# ---------------------------------------------------------------------------------------------- cameras.json

_REQUIRED_CAMERA = ("width", "height", "position", "rotation", "fx", "fy")


def _finite(v: Any) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _matrix(v: Any, shape: tuple[int, ...]) -> bool:
    if not shape:
        return _finite(v)
    return isinstance(v, list) and len(v) == shape[0] and all(_matrix(x, shape[1:]) for x in v)


def _field_ok(field: str, v: Any) -> bool:
    """The documented rule for each INRIA field, written independently of gsw.camera_io."""
    if field in ("width", "height"):
        return _finite(v) and v == int(v) and 1 <= v <= 16384
    if field == "id":
        return _finite(v) and v == int(v) and abs(v) < 2**63
    if field in ("fx", "fy"):
        return _finite(v) and v > 0
    if field in ("cx", "cy"):
        return _finite(v)
    if field == "img_name":
        return isinstance(v, str)
    if field == "position":
        return _matrix(v, (3,))
    if field == "rotation":
        if not _matrix(v, (3, 3)):
            return False
        r = np.array(v, dtype=np.float64)
        return np.abs(r @ r.T - np.eye(3)).max() <= 1e-4 and np.linalg.det(r) > 0
    return True  # unknown keys are ignored


def _camera_oracle(parsed: Any) -> tuple[bool, list[str], int | None, list[str]]:
    """(valid, message fragments, first bad entry, its bad fields) for a parsed cameras.json."""
    if not isinstance(parsed, list) or not parsed:
        return False, ["non-empty JSON list"], None, []
    for k, e in enumerate(parsed):
        if not isinstance(e, dict):
            return False, [f"camera {k}", "expected a JSON object"], k, []
        missing = [f for f in _REQUIRED_CAMERA if f not in e]
        if missing:
            return False, [f"camera {k}", "lacks"], k, missing
        bad = [f for f, v in e.items() if not _field_ok(f, v)]
        if bad:
            return False, [f"camera {k}"], k, bad
    return True, [], None, []


def _rotation(rng: np.random.Generator) -> list[list[float]]:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return (q if np.linalg.det(q) > 0 else -q).tolist()


def _random_json_value(rng: np.random.Generator) -> Any:
    choices = [
        lambda: int(rng.integers(-5, 20000)), lambda: float(rng.integers(1, 5000)), lambda: float(rng.uniform(-10, 5000)),
        lambda: bool(rng.random() < 0.5), lambda: None, lambda: str(rng.integers(0, 100)), lambda: "",
        lambda: [float(x) for x in rng.standard_normal(int(rng.integers(0, 5)))], lambda: {"a": 1},
        lambda: float("nan"), lambda: float("inf"), lambda: 10**400, lambda: 1e300, lambda: -0.0,
        lambda: _rotation(rng), lambda: [1, 2, True], lambda: [[1, 0, 0], [0, 1, 0]], lambda: "caf\u00e9",
    ]
    return choices[int(rng.integers(0, len(choices)))]()


def _camera_entries(rng: np.random.Generator) -> list[dict[str, Any]]:
    entries = []
    for k in range(int(rng.integers(1, 4))):
        e = {"id": k, "img_name": str(rng.choice(["a", "b_01", "caf\u00e9", "\u5199\u771f"])), "width": int(rng.integers(1, 2000)),
             "height": int(rng.integers(1, 2000)), "position": rng.standard_normal(3).tolist(),
             "rotation": _rotation(rng), "fy": float(rng.uniform(1, 2000)), "fx": float(rng.uniform(1, 2000))}
        if rng.random() < 0.3:
            e.update(cx=float(rng.uniform(0, 100)), cy=float(rng.uniform(0, 100)))
        entries.append(e)
    return entries


def _camera_input(rng: np.random.Generator) -> tuple[str, bytes]:
    entries = _camera_entries(rng)
    kind = str(rng.choice(["valid", "field", "field", "delete", "toplevel", "truncate", "flip", "insert",
                           "latin1", "utf16", "bom"]))
    if kind == "field":
        e = entries[int(rng.integers(0, len(entries)))]
        field = str(rng.choice(list(_REQUIRED_CAMERA) + ["id", "img_name", "cx", "cy"]))
        e[field] = _random_json_value(rng)
        kind = f"field {field}={e[field]!r}"[:60]
    elif kind == "delete":
        del entries[int(rng.integers(0, len(entries)))][str(rng.choice(_REQUIRED_CAMERA))]
    elif kind == "toplevel":
        return kind, json.dumps(_random_json_value(rng)).encode()
    text = json.dumps(entries, ensure_ascii=bool(rng.random() < 0.5))
    data = text.encode("utf-8")
    if kind == "truncate":
        data = data[: int(rng.integers(0, len(data)))]
    elif kind in ("flip", "insert"):
        buf = bytearray(data)
        pos = int(rng.integers(0, len(buf)))
        char = int(rng.choice(list(b'{}[],:"0.e-\\ ') + [int(rng.integers(0, 256))]))
        if kind == "flip":
            buf[pos] = char
        else:
            buf.insert(pos, char)
        data = bytes(buf)
    elif kind == "latin1":
        data = text.encode("latin-1", errors="replace")
    elif kind == "utf16":
        data = text.encode("utf-16")
    elif kind == "bom":
        data = b"\xef\xbb\xbf" + data
    return kind, data


def _camera_check(cams: list, parsed: list[dict]) -> str | None:
    for k, (cam, e) in enumerate(zip(cams, parsed)):
        want = dict(width=int(e["width"]), height=int(e["height"]), fx=float(e["fx"]), fy=float(e["fy"]),
                    cx=float(e.get("cx", e["width"] / 2)), cy=float(e.get("cy", e["height"] / 2)),
                    name=e.get("img_name", ""))
        got = {key: getattr(cam, key) for key in want}
        if got != want or type(cam.width) is not int:
            return f"camera {k}: {got} != {want}"
        c2w = cam.c2w.numpy()
        if not (np.array_equal(c2w[:3, 3], np.array(e["position"], np.float64))
                and np.allclose(c2w[:3, :3], np.array(e["rotation"], np.float64), atol=1e-12)):
            return f"camera {k}: pose differs from the file"
    return None if len(cams) == len(parsed) else f"{len(cams)} cameras for {len(parsed)} entries"


def test_fuzz_cameras_json(tmp_path):
    rng, out = np.random.default_rng(SEED + 2), Outcomes("cameras")
    path = tmp_path / "cameras.json"
    for i in range(COUNTS["cameras"] - 1):
        kind, data = _camera_input(rng)
        name = f"cameras #{i} ({kind})"
        path.write_bytes(data)
        cams, exc = out.run(name, lambda: load_inria_cameras(path))
        try:
            parsed = json.loads(data.decode("utf-8-sig"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            out.expect_error(name, exc, CameraFileError, str(path))
            continue
        valid, fragments, k, bad = _camera_oracle(parsed)
        if valid:
            if exc is not None:
                out.fail(name, f"valid input rejected: {type(exc).__name__}: {exc}")
            elif problem := _camera_check(cams, parsed):
                out.fail(name, f"loaded silently changed content: {problem}")
            continue
        out.expect_error(name, exc, CameraFileError, str(path), *fragments)
        if exc is not None and bad and not any(f"'{f}'" in str(exc) or f in str(exc) for f in bad):
            out.fail(name, f"message names none of the bad fields {bad}: {exc}")
    path.unlink()
    path.mkdir()
    _, exc = out.run("cameras: a directory", lambda: load_inria_cameras(path))
    out.expect_error("cameras: a directory", exc, CameraFileError, str(path), "is a directory")
    out.report(COUNTS["cameras"])


# ---------------------------------------------------------------------------------------------- images

_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def _png_case(rng: np.random.Generator) -> tuple[bytes, np.ndarray | None, float]:
    """A random PNG, the [H, W, 3|4] float image it holds (None: must be rejected) and the tolerance."""
    ct = int(rng.choice(list(_PNG_DEPTHS)))
    bd = int(rng.choice(_PNG_DEPTHS[ct]))
    h, w, top = int(rng.integers(1, 9)), int(rng.integers(1, 9)), 2**bd - 1
    shape = (h, w) if _PNG_CHANNELS[ct] == 1 else (h, w, _PNG_CHANNELS[ct])
    a = rng.integers(0, top + 1, shape)
    palette = trns = None
    tol = 1e-6 if bd <= 8 or ct == 0 else 1 / 255 + 1e-6  # Pillow keeps the top 8 bits of 16-bit colour
    if ct == 3:
        palette = rng.integers(0, 256, (top + 1, 3))
        rgb = palette[a] / 255
    elif ct in (0, 4):
        gray = (a if ct == 0 else a[..., 0]) / top
        rgb = np.stack([gray] * 3, -1)
    else:
        rgb = a[..., :3] / top
    alpha = a[..., -1] / top if ct in (4, 6) else None
    if ct in (0, 2, 3) and rng.random() < 0.4:  # tRNS transparency
        if ct == 3:
            table = rng.integers(0, 256, int(rng.integers(1, top + 2)))
            trns = table.astype(np.uint8).tobytes()
            alpha = np.concatenate([table, np.full(top + 1 - len(table), 255)])[a] / 255
        else:
            key = a.reshape(-1, _PNG_CHANNELS[ct])[int(rng.integers(0, h * w))]
            trns = struct.pack(f">{len(key)}H", *key.tolist())
            alpha = (a.reshape(h, w, -1) != key).any(-1).astype(np.float64)
            if ct == 2 and bd == 16:
                return png_bytes(a, bd, ct, palette=palette, trns=trns), None, tol  # rejected by name
    expected = rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)
    return png_bytes(a, bd, ct, palette=palette, trns=trns), expected, tol


def _jpeg_case(rng: np.random.Generator) -> tuple[bytes, np.ndarray, float]:
    from PIL import Image

    h, w = int(rng.integers(8, 25)), int(rng.integers(8, 25))
    y, x = np.mgrid[0:h, 0:w] / 24.0
    c = rng.uniform(0.2, 0.8, 3)
    rgb = np.clip(np.stack([c[0] + 0.2 * x, c[1] + 0.2 * y, c[2] - 0.1 * x], -1), 0, 1)
    im = Image.fromarray((rgb * 255).round().astype(np.uint8), "RGB")
    mode = str(rng.choice(["RGB", "L", "CMYK"]))
    buf = io.BytesIO()
    im.convert(mode).save(buf, format="JPEG", quality=95)
    if mode == "L":
        rgb = np.asarray(im.convert("L"), np.float64)[..., None].repeat(3, -1) / 255
    return buf.getvalue(), rgb, 0.03


def test_fuzz_images(tmp_path):
    rng, out = np.random.default_rng(SEED + 3), Outcomes("images")
    for i in range(COUNTS["images"]):
        kind = str(rng.choice(["png", "png", "png", "jpeg", "truncate", "jpeg_truncate", "garbage", "huge"]))
        suffix = ".jpg" if kind.startswith("jpeg") else ".png"
        data, expected, tol = _jpeg_case(rng) if kind.startswith("jpeg") else _png_case(rng)
        full = expected
        if kind in ("truncate", "jpeg_truncate"):
            data, expected = data[: int(rng.integers(0, len(data)))], "full_or_error"
        elif kind == "garbage":
            data, expected = [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff"][int(rng.integers(0, 3))] + rng.bytes(
                int(rng.integers(0, 100))), None
        elif kind == "huge":
            side = int(rng.integers(16385, 10**6))
            data, expected = png_bytes(np.zeros((1, 1), np.uint8), 8, 0, size=(side, 1)), None
        path = tmp_path / f"img_{i}{suffix}"
        path.write_bytes(data)
        name = f"image #{i} ({kind}, {len(data)} bytes)"
        img, exc = out.run(name, lambda: read_image(path))
        if expected is None:
            out.expect_error(name, exc, ImageError, str(path))
        elif isinstance(expected, str):  # a truncated file: an error, or the full content (a cut trailer)
            if exc is not None:
                out.expect_error(name, exc, ImageError, str(path))
            elif full is None or tuple(img.shape) != (full.shape[2], *full.shape[:2]) or \
                    np.abs(img.permute(1, 2, 0).numpy() - full).mean() > tol:
                out.fail(name, "a truncated file loaded with content other than the full file's")
        elif exc is not None:
            out.fail(name, f"valid image rejected: {type(exc).__name__}: {exc}")
        else:
            got = img.permute(1, 2, 0).numpy()
            if got.shape != expected.shape or not np.isfinite(got).all():
                out.fail(name, f"shape {got.shape}, expected {expected.shape}")
            elif (np.abs(got - expected).mean() if kind == "jpeg" else np.abs(got - expected).max()) > tol:
                out.fail(name, f"pixels differ from the independent decode by {np.abs(got - expected).max():.4f}")
            elif got.min() < 0 or got.max() > 1:
                out.fail(name, "values outside [0, 1]")
    out.report(COUNTS["images"])


# ---------------------------------------------------------------------------------------------- messages


def _message_input(rng: np.random.Generator, bits: int) -> tuple[str, Any, Any]:
    """(kind, message, expectation): the expected [bits] 0/1 array, or ("error", fragment)."""
    digits = "".join(rng.choice(list("0123456789abcdef"), bits // 4))
    truth = np.array([(int(c, 16) >> (3 - i)) & 1 for c in digits for i in range(4)], np.float32)
    kind = str(rng.choice(["hex", "hex_len", "hex_char", "bits", "bits_len", "bits_value", "bits_type", "key",
                           "num_bits"]))
    if kind == "hex":
        text = "".join(c.upper() if rng.random() < 0.5 else c for c in digits)
        return kind, ("0x" if rng.random() < 0.3 else "") + text, truth
    if kind == "hex_len":
        cut = int(rng.integers(0, len(digits) + 5))
        return kind, (digits * 2)[:cut] if cut != len(digits) else digits + "0", ("error", "hex digits")
    if kind == "hex_char":
        pos = int(rng.integers(0, len(digits)))
        bad = str(rng.choice(list("gxz -_\u0661\uff11\n")))
        return kind, digits[:pos] + bad + digits[pos + 1:], ("error", "hex digits")
    if kind == "bits":
        form = int(rng.integers(0, 4))
        value = [truth.astype(int).tolist(), truth.tolist(), torch.from_numpy(truth), truth.astype(bool).tolist()][form]
        return f"bits form {form}", value, truth
    if kind == "bits_len":
        n = int(rng.choice([x for x in range(0, bits + 9) if x != bits]))
        return kind, rng.integers(0, 2, n).tolist(), ("error", f"has {n} bits, expected {bits}")
    if kind == "bits_value":
        b = truth.tolist()
        b[int(rng.integers(0, bits))] = float(rng.choice([2, -1, 0.5, np.nan, np.inf, 1e-9]))
        return kind, b, ("error", "0 or 1")
    if kind == "bits_type":
        b: list[Any] = truth.astype(int).tolist()
        b[int(rng.integers(0, bits))] = [None, "1", {"a": 1}, [0, 1], b"1"][int(rng.integers(0, 5))]
        return kind, b, ("error", "message")
    if kind == "key":
        return kind, "key:" + "".join(chr(int(c)) for c in rng.integers(32, 0x3000, int(rng.integers(0, 12)))), "key"
    return kind, digits, ("error_bits", "num_bits")


def test_fuzz_messages():
    rng, out = np.random.default_rng(SEED + 4), Outcomes("messages")
    for i in range(COUNTS["messages"]):
        bits = int(rng.choice([4, 8, 32, 48, 64]))
        kind, message, expect = _message_input(rng, bits)
        name = f"message #{i} ({kind}, {bits} bits, {message!r:.40})"
        num_bits = int(rng.choice([0, -4])) if kind == "num_bits" else bits
        got, exc = out.run(name, lambda: as_message(message, num_bits))
        if isinstance(expect, tuple):
            out.expect_error(name, exc, ValueError, expect[1])
        elif exc is not None:
            out.fail(name, f"valid message rejected: {type(exc).__name__}: {exc}")
        elif tuple(got.shape) != (bits,) or not bool(((got == 0) | (got == 1)).all()):
            out.fail(name, f"not {bits} bits of 0/1: {got}")
        elif isinstance(expect, np.ndarray) and not np.array_equal(got.numpy(), expect):
            out.fail(name, "bits differ from the input")
        elif kind == "hex" and message_to_hex(got) != message.lower().removeprefix("0x"):
            out.fail(name, "hex does not round-trip")
        elif kind == "key" and not torch.equal(got, as_message(message, num_bits)):
            out.fail(name, "a key does not give the same message twice")
    out.report(COUNTS["messages"])


def test_corpus_size():
    """The corpus holds at least 2,000 generated inputs in all (each format's test asserts its own count)."""
    total = sum(COUNTS.values())
    print(f"fuzz corpus: {total} inputs ({COUNTS})")
    assert total >= 2000


@pytest.mark.parametrize("reader, error", [(load_ply, PlyError), (load_splat, SplatError),
                                           (load_inria_cameras, CameraFileError), (read_image, ImageError)])
def test_documented_error_classes_are_value_errors(reader, error, tmp_path: Path):
    assert issubclass(error, ValueError)
    (tmp_path / "dir").mkdir()
    with pytest.raises(error, match="is a directory"):
        reader(tmp_path / "dir")
