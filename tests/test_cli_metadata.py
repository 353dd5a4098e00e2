"""gsw.cli.metadata: watermark.json is written without secrets and read back with named errors."""

from __future__ import annotations

import json

import pytest

from gsw.cli.metadata import at_resolution, read_watermark_json, watermark_record, write_watermark_json
from gsw.mark.embed import EmbedConfig
from gsw.scenes import default_cameras


def _record(cameras, **config) -> dict:
    return watermark_record(num_bits=48, background=(1.0, 1.0, 1.0), cameras=cameras, decoder="f00d",
                            config=EmbedConfig(seed=1234, **config), stats={"gaussians_in": 10})


def test_round_trip_without_seed(tmp_path) -> None:
    cams = default_cameras(3, 40, 30)
    record = _record(cams, epochs=3)
    assert "seed" not in record["embedding"] and record["embedding"]["epochs"] == 3  # the seed draws random messages
    assert "1234" not in json.dumps(record)
    write_watermark_json(tmp_path, record)
    info = read_watermark_json(tmp_path)
    assert (info.num_bits, info.background, info.resolution, info.decoder) == (48, (1.0, 1.0, 1.0), (40, 30), "f00d")
    assert info.path == tmp_path / "watermark.json"
    assert read_watermark_json(tmp_path / "nothing") is None
    mixed = _record([*cams, *default_cameras(1, 20, 20)])
    assert mixed["resolution"] is None


def test_message_origin_is_recorded_and_optional(tmp_path) -> None:
    cams = default_cameras(2, 40, 30)
    assert read_watermark_json(_write(tmp_path / "r", _record(cams))).message_origin == "random"
    chosen = watermark_record(num_bits=48, background=(1.0, 1.0, 1.0), cameras=cams, decoder="f00d",
                              config=EmbedConfig(), stats={}, message_origin="chosen")
    assert read_watermark_json(_write(tmp_path / "c", chosen)).message_origin == "chosen"
    old = _record(cams)
    old.pop("message_origin")  # a file written before the field: the command line decides
    assert read_watermark_json(_write(tmp_path / "o", old)).message_origin is None
    with pytest.raises(ValueError, match="message origin must be one of"):
        watermark_record(num_bits=48, background=(0, 0, 0), cameras=cams, decoder="f", config=EmbedConfig(),
                         stats={}, message_origin="typed")


def _write(folder, record):
    folder.mkdir()
    write_watermark_json(folder, record)
    return folder


@pytest.mark.parametrize("change, match", [
    (lambda d: d.pop("num_bits"), "missing field 'num_bits'"),
    (lambda d: d.update(num_bits=40), "num_bits must be one of"),
    (lambda d: d.update(background=[1, 1]), "background must be 3 numbers"),
    (lambda d: d.update(resolution={"width": 0, "height": 3}), "resolution must be"),
    (lambda d: d.update(decoder="x"), "decoder must be"),
    (lambda d: d.update(format=99), "format 99"),
    (lambda d: d.update(message_origin="typed"), "message_origin must be one of"),
])
def test_malformed_fields_are_named(tmp_path, change, match) -> None:
    record = _record(default_cameras(2, 32, 32))
    change(record)
    (tmp_path / "watermark.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match=match) as err:
        read_watermark_json(tmp_path)
    assert "watermark.json" in str(err.value)


def test_invalid_json_names_the_file(tmp_path) -> None:
    (tmp_path / "watermark.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"watermark.json: invalid JSON"):
        read_watermark_json(tmp_path)


def test_cameras_are_brought_to_the_embedding_resolution(tmp_path) -> None:
    cams = default_cameras(2, 40, 30)
    write_watermark_json(tmp_path, _record(cams))
    info = read_watermark_json(tmp_path)
    bigger = [c.scaled(2.0) for c in cams]
    back = at_resolution(bigger, info)
    assert [(c.width, c.height) for c in back] == [(40, 30), (40, 30)]
    assert all(abs(a.fx - b.fx) < 1e-9 and abs(a.cy - b.cy) < 1e-9 for a, b in zip(back, cams))
    with pytest.raises(ValueError, match="does not scale to the embedding resolution 40x30"):
        at_resolution(default_cameras(1, 40, 40), info)
