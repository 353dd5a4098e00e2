"""Tests for gsw.io.ply (INRIA-layout PLY reading and writing)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import SHARED_DATA, require
import torch

from gsw.gaussians import Gaussians
from gsw.io import PlyError, load_gaussians, load_ply, ply_property_names, save_ply

DATA = SHARED_DATA
FIXTURE = DATA / "ply" / "sh3_fixture" / "point_cloud.ply"


def make(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    out = Gaussians(
        means=torch.randn(n, 3, generator=g) * 10,
        log_scales=torch.randn(n, 3, generator=g) - 4,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, k, 3, generator=g),
    )
    if n > 2:  # values that a text detour would lose
        out.means[0, 0] = -0.0
        out.sh[1, 0, 1] = 1e-42  # subnormal
        out.opacity_logits[2] = 3.4e38
    return out


def assert_bit_identical(a: Gaussians, b: Gaussians) -> None:
    for name, t in a.parameters().items():
        u = b.parameters()[name]
        assert t.shape == u.shape and t.dtype == u.dtype == torch.float32, name
        assert torch.equal(t.view(torch.int32), u.view(torch.int32)), name


def write_ply(
    path: Path,
    columns: dict[str, np.ndarray],
    fmt: str = "binary_little_endian",
    types: dict[str, str] | None = None,
    extra_header: str = "",
) -> Path:
    """A hand-made PLY with the given vertex columns (in dict order)."""
    types = types or {}
    n = len(next(iter(columns.values())))
    ply_to_np = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4", "short": "i2"}
    header = f"ply\nformat {fmt} 1.0\n{extra_header}element vertex {n}\n"
    header += "".join(f"property {types.get(k, 'float')} {k}\n" for k in columns) + "end_header\n"
    if fmt == "ascii":
        rows = zip(*(columns[k].tolist() for k in columns))
        body = "".join(" ".join(repr(v) for v in row) + "\n" for row in rows).encode()
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(k, endian + ply_to_np[types.get(k, "float")]) for k in columns])
        rec = np.empty(n, dtype=dtype)
        for k, v in columns.items():
            rec[k] = v
        body = rec.tobytes()
    path.write_bytes(header.encode() + body)
    return path


def inria_columns(g: Gaussians, normals: bool = True) -> dict[str, np.ndarray]:
    """INRIA property name -> column, built independently of save_ply (channel-major f_rest)."""
    n, k = len(g), g.sh.shape[1]
    cols = {"x": g.means[:, 0], "y": g.means[:, 1], "z": g.means[:, 2]}
    if normals:
        cols.update(nx=torch.zeros(n), ny=torch.zeros(n), nz=torch.zeros(n))
    for c in range(3):
        cols[f"f_dc_{c}"] = g.sh[:, 0, c]
    for c in range(3):
        for j in range(k - 1):
            cols[f"f_rest_{c * (k - 1) + j}"] = g.sh[:, 1 + j, c]
    cols["opacity"] = g.opacity_logits
    for i in range(3):
        cols[f"scale_{i}"] = g.log_scales[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = g.quats[:, i]
    return {name: v.numpy().astype(np.float32) for name, v in cols.items()}


# ------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("normals", [True, False])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_bit_exact(tmp_path, degree, normals):
    g = make(50, degree)
    path = tmp_path / "m.ply"
    save_ply(g, path, normals=normals, allow_nonfinite=False)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 50" in header
    names = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert names == ply_property_names(degree, normals)
    assert ("property float nx" in header) == normals
    h = load_ply(path)
    assert h.sh_degree == degree
    assert_bit_identical(g, h)
    save_ply(h, tmp_path / "again.ply", normals=normals)
    assert (tmp_path / "again.ply").read_bytes() == path.read_bytes()


def test_f_rest_is_channel_major(tmp_path):
    g = make(4, 3)
    save_ply(g, tmp_path / "m.ply")
    data = (tmp_path / "m.ply").read_bytes().split(b"end_header\n")[1]
    rows = np.frombuffer(data, "<f4").reshape(4, 62)
    # f_rest_0..14 are red coefficients 1..15, f_rest_15..29 green, f_rest_30..44 blue
    np.testing.assert_array_equal(rows[:, 9:24], g.sh[:, 1:, 0].numpy())
    np.testing.assert_array_equal(rows[:, 24:39], g.sh[:, 1:, 1].numpy())
    np.testing.assert_array_equal(rows[:, 39:54], g.sh[:, 1:, 2].numpy())
    np.testing.assert_array_equal(rows[:, 6:9], g.sh[:, 0].numpy())


def test_any_property_order_and_extra_properties(tmp_path):
    g = make(20, 2)
    cols = inria_columns(g)
    names = list(cols)
    rng = np.random.default_rng(0)
    shuffled = {k: cols[k] for k in rng.permutation(names)}
    shuffled["filter_3D"] = np.ones(20, np.float32)  # e.g. Mip-Splatting
    h = load_ply(write_ply(tmp_path / "shuffled.ply", shuffled))
    assert_bit_identical(g, h)
    with pytest.raises(PlyError, match="filter_3D"):
        load_ply(tmp_path / "shuffled.ply", strict=True)


def test_ascii_and_big_endian(tmp_path):
    g = make(10, 1)
    cols = inria_columns(g, normals=False)
    assert_bit_identical(g, load_ply(write_ply(tmp_path / "a.ply", cols, fmt="ascii")))
    assert_bit_identical(g, load_ply(write_ply(tmp_path / "b.ply", cols, fmt="binary_big_endian")))


def test_non_float32_properties_are_converted(tmp_path):
    g = make(10, 0)
    cols = inria_columns(g)
    types = {"x": "double", "opacity": "double", "nx": "uchar", "ny": "int", "nz": "short"}
    cols["x"] = cols["x"].astype(np.float64)
    h = load_ply(write_ply(tmp_path / "d.ply", cols, types=types, extra_header="comment mixed types\n"))
    assert_bit_identical(g, h)
    cols["opacity"] = np.full(10, 1e300)  # beyond float32: becomes inf, reported
    with pytest.raises(PlyError, match=r"opacity \(10\)"):
        load_ply(write_ply(tmp_path / "big.ply", cols, types=types))


def test_other_elements_before_vertex(tmp_path):
    g = make(6, 0)
    cols = inria_columns(g)
    path = write_ply(tmp_path / "m.ply", cols, extra_header="element camera 2\nproperty float f\n")
    # The header declares "camera" (2 x 4 bytes) before "vertex": insert its data before the vertices.
    head, body = path.read_bytes().split(b"end_header\n")
    path.write_bytes(head + b"end_header\n" + np.arange(2, dtype="<f4").tobytes() + body)
    assert_bit_identical(g, load_ply(path))


def test_fixture_loads():
    g = load_ply(require(FIXTURE))
    assert len(g) == 9080 and g.sh_degree == 3 and g.dtype == torch.float32
    g.check_finite()
    assert torch.all(g.opacities > 0) and torch.all(g.opacities < 1)
    assert load_gaussians(FIXTURE).means.shape == (9080, 3)


def test_fixture_rewrites_byte_identical(tmp_path):
    original = require(FIXTURE).read_bytes()
    save_ply(load_ply(FIXTURE), tmp_path / "copy.ply")
    assert (tmp_path / "copy.ply").read_bytes() == original


def test_large_model_round_trip(tmp_path):
    # Load speed is measured in benchmarks/, not here.
    g = make(200_000, 3)
    save_ply(g, tmp_path / "big.ply")
    assert_bit_identical(g, load_ply(tmp_path / "big.ply"))


# ------------------------------------------------------------------------------------------ atomic writes


def test_save_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "m.ply"
    save_ply(make(5, 0, seed=1), path)
    save_ply(make(7, 1, seed=2), path)  # overwrite an explicit path
    assert len(load_ply(path)) == 7
    before = path.read_bytes()
    bad = make(5, 0)
    bad.means[0, 0] = float("nan")
    with pytest.raises(PlyError, match="means"):
        save_ply(bad, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]  # no temporary left over
    save_ply(bad, tmp_path / "nan.ply", allow_nonfinite=True)
    assert torch.isnan(load_ply(tmp_path / "nan.ply", allow_nonfinite=True).means[0, 0])


# ------------------------------------------------------------------------------------------ bad input


@pytest.fixture
def good(tmp_path) -> Path:
    path = tmp_path / "good.ply"
    save_ply(make(8, 1), path)
    return path


def test_not_a_ply(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"PK\x03\x04 this is a zip")
    with pytest.raises(PlyError, match="not a PLY"):
        load_ply(tmp_path / "x.ply")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(PlyError, match="not a PLY"):
        load_ply(tmp_path / "empty.ply")


def test_bad_header(tmp_path, good):
    head, body = good.read_bytes().split(b"end_header\n")
    (tmp_path / "no_end.ply").write_bytes(head)
    with pytest.raises(PlyError, match="end_header"):
        load_ply(tmp_path / "no_end.ply")
    (tmp_path / "kw.ply").write_bytes(head.replace(b"element vertex", b"elemnt vertex") + b"end_header\n" + body)
    with pytest.raises(PlyError, match="bad PLY header.*elemnt"):
        load_ply(tmp_path / "kw.ply")
    (tmp_path / "type.ply").write_bytes(
        head.replace(b"property float x", b"property float128 x") + b"end_header\n" + body
    )
    with pytest.raises(PlyError, match="bad PLY header.*float128"):
        load_ply(tmp_path / "type.ply")
    (tmp_path / "dup.ply").write_bytes(head.replace(b"property float y", b"property float x") + b"end_header\n" + body)
    with pytest.raises(PlyError, match="duplicate property 'x'"):
        load_ply(tmp_path / "dup.ply")
    (tmp_path / "nofmt.ply").write_bytes(
        head.replace(b"format binary_little_endian 1.0\n", b"") + b"end_header\n" + body
    )
    with pytest.raises(PlyError, match="missing 'format'"):
        load_ply(tmp_path / "nofmt.ply")
    (tmp_path / "novertex.ply").write_bytes(head.replace(b"element vertex", b"element points") + b"end_header\n" + body)
    with pytest.raises(PlyError, match="no 'vertex' element"):
        load_ply(tmp_path / "novertex.ply")


def test_unsupported_format(tmp_path, good):
    data = good.read_bytes().replace(b"binary_little_endian", b"binary_middle_endian")
    (tmp_path / "f.ply").write_bytes(data)
    with pytest.raises(PlyError, match="unsupported PLY format 'binary_middle_endian"):
        load_ply(tmp_path / "f.ply")


def test_missing_properties_are_named(tmp_path):
    cols = inria_columns(make(4, 0))
    del cols["opacity"], cols["rot_3"]
    with pytest.raises(PlyError, match="missing required vertex properties: opacity, rot_3"):
        load_ply(write_ply(tmp_path / "m.ply", cols))


def test_wrong_f_rest_count(tmp_path):
    cols = inria_columns(make(4, 1))  # 9 f_rest
    cols["f_rest_9"] = cols["f_rest_0"]
    with pytest.raises(PlyError, match="found 10 f_rest_\\* properties; expected 0, 9, 24 or 45"):
        load_ply(write_ply(tmp_path / "m.ply", cols))
    cols = inria_columns(make(4, 1))
    cols["f_rest_12"] = cols.pop("f_rest_4")  # 9 properties but not numbered 0..8
    with pytest.raises(PlyError, match="missing: f_rest_4; unexpected: f_rest_12"):
        load_ply(write_ply(tmp_path / "m2.ply", cols))


def test_truncated(tmp_path, good):
    data = good.read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-10])
    row = 4 * len(ply_property_names(1))
    with pytest.raises(PlyError, match=rf"truncated.*{8 * row} bytes expected.*only {8 * row - 10} bytes"):
        load_ply(tmp_path / "t.ply")
    (tmp_path / "ascii.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\n"
        + "".join(f"property float {p}\n" for p in ply_property_names(0, normals=False))
        + "end_header\n"
        + " ".join(["0"] * 14)
        + "\n"
    )
    with pytest.raises(PlyError, match="declares 2 record lines .*found 1"):
        load_ply(tmp_path / "ascii.ply")


def test_header_vertex_count_must_match_the_data(tmp_path, good):
    """A count lower than the data used to load silently and drop Gaussians; higher is truncation."""
    head, body = good.read_bytes().split(b"end_header\n")
    row = 4 * len(ply_property_names(1))
    (tmp_path / "low.ply").write_bytes(head.replace(b"element vertex 8", b"element vertex 6") + b"end_header\n" + body)
    with pytest.raises(PlyError, match=rf"{2 * row} bytes of trailing data.*element vertex 6.*2 more vertices.*count"):
        load_ply(tmp_path / "low.ply")
    with pytest.raises(PlyError, match="trailing data"):
        load_ply(tmp_path / "low.ply", strict=False)  # not a strict-only check any more
    (tmp_path / "high.ply").write_bytes(head.replace(b"element vertex 8", b"element vertex 9") + b"end_header\n" + body)
    with pytest.raises(PlyError, match="truncated"):
        load_ply(tmp_path / "high.ply")
    # even one stray byte (a trailing newline) is reported, so that nothing after the data goes unread
    (tmp_path / "tail.ply").write_bytes(good.read_bytes() + b"\n")
    with pytest.raises(PlyError, match="1 bytes of trailing data"):
        load_ply(tmp_path / "tail.ply")
    assert len(load_ply(good)) == 8


def test_ascii_counts_and_rows_must_match(tmp_path):
    g = make(3, 0)
    path = write_ply(tmp_path / "a.ply", inria_columns(g, normals=False), fmt="ascii")
    text = path.read_text()
    assert_bit_identical(g, load_ply(path))
    (tmp_path / "blank.ply").write_text(text + "\n  \n")  # blank lines at the end are fine
    assert_bit_identical(g, load_ply(tmp_path / "blank.ply"))
    (tmp_path / "low.ply").write_text(text.replace("element vertex 3", "element vertex 2"))
    with pytest.raises(PlyError, match="1 lines of trailing data.*element vertex 2"):
        load_ply(tmp_path / "low.ply")
    lines = text.splitlines()
    lines[-1] += " 7"  # one row with an extra value, another with one fewer: same total
    lines[-2] = " ".join(lines[-2].split()[:-1])
    (tmp_path / "rows.ply").write_text("\n".join(lines) + "\n")
    with pytest.raises(PlyError, match="vertex 1 has 13 values, expected 14"):
        load_ply(tmp_path / "rows.ply")


def test_element_order(tmp_path):
    g = make(5, 0)
    cols = inria_columns(g)
    path = write_ply(tmp_path / "m.ply", cols)
    head, body = path.read_bytes().split(b"end_header\n")
    after = b"element extra 3\nproperty double t\n"
    # a list-free element after the vertices: its data must be there, and is skipped
    (tmp_path / "after.ply").write_bytes(head + b"\n" + after + b"end_header\n" + body + np.zeros(3).tobytes())
    assert_bit_identical(g, load_ply(tmp_path / "after.ply"))
    (tmp_path / "after_missing.ply").write_bytes(head + b"\n" + after + b"end_header\n" + body)
    with pytest.raises(PlyError, match="truncated"):
        load_ply(tmp_path / "after_missing.ply")
    # list elements: fine without records, an error with records (their size is unknown)
    faces = b"element face %d\nproperty list uchar int vertex_indices\n"
    (tmp_path / "faces0.ply").write_bytes(head + b"\n" + faces % 0 + b"end_header\n" + body)
    assert_bit_identical(g, load_ply(tmp_path / "faces0.ply"))
    (tmp_path / "faces.ply").write_bytes(head + b"\n" + faces % 2 + b"end_header\n" + body + b"\x01" * 10)
    with pytest.raises(PlyError, match="element 'face' \\(after 'vertex'\\) has list properties and 2 records"):
        load_ply(tmp_path / "faces.ply")
    bad_list = head.replace(b"property float x", b"property list float128 int x")
    (tmp_path / "bad_list.ply").write_bytes(bad_list + b"end_header\n" + body)
    with pytest.raises(PlyError, match="cannot parse"):
        load_ply(tmp_path / "bad_list.ply")
    (tmp_path / "two.ply").write_bytes(head + b"\nelement vertex 0\nproperty float x\nend_header\n" + body)
    with pytest.raises(PlyError, match="duplicate element 'vertex'"):
        load_ply(tmp_path / "two.ply")


def test_nonfinite_values_are_named_and_counted(tmp_path):
    cols = inria_columns(make(6, 1))
    cols["opacity"][[1, 4]] = np.nan
    cols["f_rest_3"][0] = np.inf
    cols["nx"][:] = np.nan  # normals are not used: ignored
    path = write_ply(tmp_path / "nan.ply", cols)
    with pytest.raises(PlyError, match=r"non-finite.*f_rest_3 \(1\), opacity \(2\)$"):
        load_ply(path)
    g = load_ply(path, allow_nonfinite=True)
    assert torch.isnan(g.opacity_logits).sum() == 2


def test_errors_are_value_errors(tmp_path):
    assert issubclass(PlyError, ValueError)
    with pytest.raises(FileNotFoundError):
        load_ply(tmp_path / "absent.ply")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(PlyError, match="dir.ply: is a directory"):
        load_gaussians(tmp_path / "dir.ply")
    with pytest.raises(FileNotFoundError, match="model.obj: no such model file"):
        load_gaussians(tmp_path / "model.obj")
    (tmp_path / "model.obj").write_text("o cube")
    with pytest.raises(ValueError, match="extension"):
        load_gaussians(tmp_path / "model.obj")


def test_empty_model_is_an_error_unless_allowed(tmp_path):
    save_ply(Gaussians.empty(2), tmp_path / "e.ply")
    with pytest.raises(PlyError, match="e.ply: the model has 0 Gaussians"):
        load_ply(tmp_path / "e.ply")
    with pytest.raises(PlyError, match="0 Gaussians"):
        load_gaussians(tmp_path / "e.ply")
    g = load_ply(tmp_path / "e.ply", allow_empty=True)
    assert len(g) == 0 and g.sh_degree == 2


def test_ascii_last_line_must_end(tmp_path):
    """A cut in the last number of an ASCII file still parses as a number: the missing line break reveals it."""
    g = make(2, 0)
    path = write_ply(tmp_path / "a.ply", inria_columns(g, normals=False), fmt="ascii")
    text = path.read_text()
    (tmp_path / "cut.ply").write_text(text[:-3])
    with pytest.raises(PlyError, match="cut.ply: truncated ASCII PLY data: the last record line has no line break"):
        load_ply(tmp_path / "cut.ply")
