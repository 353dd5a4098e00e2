"""Tests for gsw.camera_io: INRIA cameras.json reading with type-checked fields, and the JSON file checks."""

from __future__ import annotations

import json

import pytest
import torch

from gsw.camera import MAX_IMAGE_SIZE, Camera, load_inria_cameras, save_inria_cameras
from gsw.camera_io import CameraFileError, camera_from_inria, read_json


def entry(**change) -> dict:
    e = {"id": 0, "img_name": "a", "width": 64, "height": 48, "position": [0.0, 0.0, -3.0],
         "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "fy": 50.0, "fx": 50.0}
    e.update(change)
    return e


def write(tmp_path, entries) -> object:
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(entries))
    return path


def test_valid_file_loads_and_round_trips(tmp_path):
    cams = load_inria_cameras(write(tmp_path, [entry(), entry(id=1, img_name="b", width=64.0)]))
    assert [c.name for c in cams] == ["a", "b"] and cams[1].width == 64 and isinstance(cams[1].width, int)
    save_inria_cameras(cams, tmp_path / "out.json")
    assert json.loads((tmp_path / "out.json").read_text())[0] == entry()
    assert load_inria_cameras(tmp_path / "out.json")[1].fx == 50.0


@pytest.mark.parametrize("field, value, match", [
    ("width", 128.9, r"field 'width' must be an integer, got 128.9 \(float\)"),
    ("height", True, r"field 'height' must be an integer, got True \(bool\)"),
    ("width", 200000, r"field 'width' = 200000 is outside 1..16384"),
    ("height", 0, r"field 'height' = 0 is outside 1..16384"),
    ("fx", True, r"field 'fx' must be a positive finite number, got True \(bool\)"),
    ("fx", None, r"field 'fx' must be a positive finite number, got None"),
    ("fy", "50", r"field 'fy' must be a positive finite number, got '50' \(str\)"),
    ("fy", [50.0], r"field 'fy' must be a positive finite number, got \[50.0\] \(list\)"),
    ("fx", 0.0, r"field 'fx' must be a positive finite number"),
    ("cx", "1", r"field 'cx' must be a finite number, got '1'"),
    ("id", 1.5, r"field 'id' must be an integer"),
    ("img_name", 7, r"field 'img_name' must be a string, got 7"),
    ("position", [0, 0], r"field 'position' must be a 3 list of finite numbers"),
    ("position", [0, True, 0], r"field 'position' must be a 3 list"),
    ("position", None, r"field 'position' must be a 3 list"),
    ("rotation", [[1, 0, 0], [0, 1, 0], [0, 0, "1"]], r"field 'rotation' must be a 3x3 list"),
    ("rotation", [[1, 0, 0], [0, 1, 0], [0, 0, 2]], r"field 'rotation' is not a rotation: .*not orthonormal"),
    ("rotation", [[1, 0, 0], [0, 1, 0], [0, 0, -1]], r"field 'rotation' is not a rotation: .*reflection"),
])
def test_fields_are_type_checked_and_named_with_the_camera_index(tmp_path, field, value, match):
    path = write(tmp_path, [entry(), entry(**{field: value})])
    with pytest.raises(CameraFileError, match=rf"cameras.json: camera 1: {match}"):
        load_inria_cameras(path)


def test_file_level_errors_name_the_file(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text("[{")
    with pytest.raises(CameraFileError, match=r"malformed JSON in .*cameras.json"):
        load_inria_cameras(path)
    path.write_bytes(json.dumps([entry(img_name="caf\u00e9")], ensure_ascii=False).encode("latin-1"))
    with pytest.raises(CameraFileError, match=r"cameras.json: not UTF-8 text \(byte \d+: b'\\xe9'\)"):
        load_inria_cameras(path)
    path.write_text(json.dumps({"cameras": []}))
    with pytest.raises(CameraFileError, match="expected a non-empty JSON list of camera entries, got dict"):
        load_inria_cameras(path)
    path.write_text("[]")
    with pytest.raises(CameraFileError, match="non-empty JSON list"):
        load_inria_cameras(path)
    path.write_text("[3]")
    with pytest.raises(CameraFileError, match="camera 0: expected a JSON object, got int"):
        load_inria_cameras(path)
    path.write_text("[" * 100_000)
    with pytest.raises(CameraFileError, match="malformed JSON"):
        load_inria_cameras(path)
    path.write_text('[{"width": ' + "9" * 10_000 + "}]")
    with pytest.raises(CameraFileError, match="malformed JSON"):
        load_inria_cameras(path)
    path.unlink()
    path.mkdir()
    with pytest.raises(CameraFileError, match="cameras.json: is a directory, expected a JSON file"):
        load_inria_cameras(path)
    with pytest.raises(CameraFileError, match="missing file"):
        load_inria_cameras(tmp_path / "absent.json")
    assert issubclass(CameraFileError, ValueError)


def test_nonfinite_json_numbers_are_rejected(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([entry()]).replace("50.0", "NaN", 1))
    with pytest.raises(CameraFileError, match="camera 0: field 'fy' must be a positive finite number, got nan"):
        load_inria_cameras(path)
    assert read_json(write(tmp_path, [1e999])) == [float("inf")]  # parsed; the field checks reject it


def test_camera_rejects_absurd_sizes_and_booleans():
    """width 200000 used to reach the renderer (a 480 GB allocation); booleans are not numbers."""
    kwargs = dict(viewmat=torch.eye(4), fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=8, height=8)
    for change in (dict(width=200_000), dict(height=MAX_IMAGE_SIZE + 1)):
        with pytest.raises(ValueError, match=rf"must be an int in 1..{MAX_IMAGE_SIZE}"):
            Camera(**{**kwargs, **change})
    with pytest.raises(ValueError, match="Camera.fx must be a positive finite number, got True"):
        Camera(**{**kwargs, "fx": True})
    assert Camera(**{**kwargs, "width": MAX_IMAGE_SIZE}).width == MAX_IMAGE_SIZE
    with pytest.raises(CameraFileError, match="INRIA camera entry: field 'width' = 200000"):
        Camera.from_inria(entry(width=200000))
    assert camera_from_inria(entry(), "ctx").to_inria(0) == entry()
