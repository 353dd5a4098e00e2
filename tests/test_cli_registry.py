"""`gsw keys list|show` and `gsw identify`: secrets stay hidden, JSON only, exit statuses 0/1/2.

These tests exercise the command line; whether a truly watermarked image is identified is tested in
test_mark_identify.py. Here the recipient's message is whatever the shipped decoder reads from a given
image, so that image carries the mark exactly, without an optimisation run.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from gsw.cli.main import main
from gsw.data.images import read_image, write_image
from gsw.mark import extract
from gsw.mark.message import message_to_hex, random_message
from gsw.registry import open_registry, shipped_decoder_sha256

BITS = 48


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> tuple[Path, Path, Path, str]:
    """(registry, the image carrying 'carol', another image, carol's message hex)."""
    folder = tmp_path_factory.mktemp("cli")
    g = torch.Generator().manual_seed(3)
    write_image(folder / "leak.png", torch.rand(3, 64, 64, generator=g))
    write_image(folder / "other.png", torch.rand(3, 64, 64, generator=g))
    carol = message_to_hex(extract(read_image(folder / "leak.png"), num_bits=BITS).bits[0])
    sha = shipped_decoder_sha256(BITS)
    with open_registry(folder / "reg.sqlite") as reg:
        reg.add_many([dict(label=name, message=random_message(BITS, seed=i), decoder_sha256=sha)
                      for i, name in enumerate(["alice", "bob"])])
        reg.add("carol", carol, decoder_sha256=sha, width=64, height=64, background=(0, 0, 0))
    return folder / "reg.sqlite", folder / "leak.png", folder / "other.png", carol


def test_keys_list_hides_messages_unless_asked(setup, capsys) -> None:
    reg, _, _, carol = setup
    assert main(["keys", "list", "--registry", str(reg)]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ("alice", "bob", "carol")) and "3 marks" in out
    assert carol not in out
    assert main(["keys", "list", "--registry", str(reg), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)  # JSON only
    assert [r["label"] for r in rows] == ["alice", "bob", "carol"] and all("message_hex" not in r for r in rows)
    assert carol not in json.dumps(rows)
    assert main(["keys", "list", "--registry", str(reg), "--show-secret"]) == 0
    assert carol in capsys.readouterr().out


def test_keys_show_by_id_or_label(setup, capsys) -> None:
    reg, _, _, carol = setup
    assert main(["keys", "show", "carol", "--registry", str(reg)]) == 0
    out = capsys.readouterr().out
    assert "carol" in out and "64x64" in out and carol not in out
    assert main(["keys", "show", "3", "--registry", str(reg), "--json", "--show-secret"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["label"] == "carol" and shown["message_hex"] == carol and shown["width"] == 64
    assert main(["keys", "show", "zed", "--registry", str(reg)]) == 2
    assert "no mark with label 'zed'" in capsys.readouterr().err


def test_identify_exit_statuses_and_json(setup, capsys) -> None:
    reg, leak, other, carol = setup
    assert main(["identify", str(leak), "--registry", str(reg)]) == 0
    out = capsys.readouterr().out
    assert "IDENTIFIED  carol" in out and "identified: carol" in out and carol not in out
    assert main(["identify", str(leak), "--registry", str(reg), "--json"]) == 0
    found = json.loads(capsys.readouterr().out)  # JSON only
    assert found["recipients"] == ["carol"] and found["marks_tested"] == 3 and found["images"] == [str(leak)]
    assert carol not in json.dumps(found)
    assert main(["identify", str(other), "--registry", str(reg), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["recipients"] == []
    assert main(["identify", str(other), "--registry", str(reg)]) == 1
    assert "nobody identified" in capsys.readouterr().out


def test_identify_and_verify_read_a_folder(setup, tmp_path, capsys) -> None:
    """A folder stands for the images and videos in it (recursively), taken together as one source."""
    reg, leak, _, carol = setup
    crawl = tmp_path / "crawl"
    (crawl / "page").mkdir(parents=True)
    shutil.copy(leak, crawl / "page" / "leak.png")
    (crawl / "index.html").write_text("<html></html>")
    assert main(["identify", str(crawl), "--registry", str(reg), "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["recipients"] == ["carol"] and found["images"] == [str(crawl / "page" / "leak.png")]
    assert main(["verify", str(crawl), "--message", carol, "--bits", str(BITS), "--chosen-message"]) == 0
    out = capsys.readouterr().out
    assert "DETECTED" in out and str(crawl / "page" / "leak.png") in out and "index.html" not in out
    (tmp_path / "empty").mkdir()
    assert main(["identify", str(tmp_path / "empty"), "--registry", str(reg)]) == 2
    assert "no images or videos found in" in capsys.readouterr().err


def test_identify_reads_videos(setup, tmp_path, capsys) -> None:
    av = pytest.importorskip("av")
    reg, leak, other, _ = setup
    video = tmp_path / "clip.mkv"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("ffv1", rate=5)
        stream.width, stream.height, stream.pix_fmt = 64, 64, "bgr0"  # lossless
        for path in (other, leak, other):
            arr = np.ascontiguousarray((read_image(path) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy())
            container.mux(stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")))
        container.mux(stream.encode())
    assert main(["identify", str(video), "--frames", "3", "--registry", str(reg), "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["recipients"] == ["carol"] and found["images"] == [f"{video}#{i}" for i in range(3)]


def test_identify_errors_exit_2_and_name_the_file(setup, tmp_path, capsys) -> None:
    pytest.importorskip("av")  # the broken-video case needs the reader (gsw[video])
    reg, leak, _, _ = setup
    broken = tmp_path / "broken.mp4"
    broken.write_text("not a video\n" * 20)
    assert main(["identify", str(broken), "--registry", str(reg)]) == 2
    assert f"{broken} is not a readable video" in capsys.readouterr().err
    missing = tmp_path / "none.sqlite"
    assert main(["identify", str(leak), "--registry", str(missing)]) == 2
    assert f"no mark registry at {missing}" in capsys.readouterr().err
    assert not missing.exists()  # reading never creates a registry
    corrupt = tmp_path / "corrupt.sqlite"
    corrupt.write_bytes(b"\x00garbage" * 300)
    assert main(["keys", "list", "--registry", str(corrupt)]) == 2
    assert f"{corrupt} is not a gsw registry" in capsys.readouterr().err
    empty = tmp_path / "empty.sqlite"
    open_registry(empty).close()
    assert main(["identify", str(leak), "--registry", str(empty)]) == 2
    assert "holds no marks" in capsys.readouterr().err
    assert main(["identify", str(leak), "--registry", str(reg), "--fpr", "2"]) == 2


def test_registry_from_the_environment(setup, monkeypatch, capsys) -> None:
    reg, leak, _, _ = setup
    monkeypatch.setenv("GSW_REGISTRY", str(reg))
    assert main(["identify", str(leak), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["recipients"] == ["carol"]


def test_identify_refuses_marks_it_cannot_test(setup, tmp_path, capsys) -> None:
    _, leak, _, _ = setup
    foreign = tmp_path / "foreign.sqlite"
    with open_registry(foreign) as reg:
        reg.add("zoe", "0123abcd", decoder_sha256="12" * 32)
    assert main(["identify", str(leak), "--registry", str(foreign)]) == 2
    assert "none of the 1 registered marks can be tested" in capsys.readouterr().err
    assert main(["identify", str(leak), "--registry", str(foreign), "--device", "tpu"]) == 2
    assert "--device must be auto, cpu or cuda" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ issuing marks

# One epoch is not detectable at the default 1e-6, so embed's own output check runs at --fpr 1 (always passes).
EMBED = ["--epochs", "1", "--lpips", "none", "--device", "cpu", "--no-progress", "--fpr", "1"]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    from gsw.data import save_inria_model
    from gsw.scenes import default_scene

    scene = default_scene(width=48, height=48, n_cameras=4, detail=0.4)
    folder = tmp_path_factory.mktemp("model")
    save_inria_model(folder, scene.gaussians, scene.cameras, iteration=100)
    return folder


def _assert_no_file_holds(folder: Path, messages: list[str]) -> None:
    """No file under ``folder`` (or ``folder`` itself) holds any message, as hex text or as raw bytes."""
    files = [folder] if folder.is_file() else [p for p in folder.rglob("*") if p.is_file()]
    assert files
    for path in files:
        data = path.read_bytes()
        for text in messages:
            assert text.encode() not in data.lower() and bytes.fromhex(text) not in data, (path, text)


def test_two_embeds_without_a_message_get_different_secret_messages(model_dir, tmp_path, capsys) -> None:
    outs, messages = [tmp_path / "a", tmp_path / "b"], []
    for out in outs:  # same options, same --seed (0)
        assert main(["embed", str(model_dir), "--output", str(out), "--bits", "64", *EMBED, "--json"]) == 0
        messages.append(json.loads(capsys.readouterr().out)["message"])
    assert messages[0] != messages[1] and all(len(m) == 16 for m in messages)
    for out in outs:
        _assert_no_file_holds(out, messages)
    images = []
    for name in ("a.png", "b.png"):
        write_image(tmp_path / "src.png", torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(1)))
        assert main(["embed-image", str(tmp_path / "src.png"), "--output", str(tmp_path / name), "--bits", "64",
                     "--steps", "2", "--no-progress", "--json"]) in (0, 1)
        images.append(json.loads(capsys.readouterr().out)["message"])
    assert images[0] != images[1]
    for name in ("a.png", "b.png"):
        _assert_no_file_holds(tmp_path / name, images)


def test_embed_records_the_issued_mark(model_dir, tmp_path, capsys) -> None:
    from gsw.data import load_inria_model
    from gsw.registry import hash_gaussians

    reg, out = tmp_path / "marks.sqlite", tmp_path / "m"
    assert main(["embed", str(model_dir), "--output", str(out), "--bits", "48", "--white", *EMBED,
                 "--label", "alice", "--registry", str(reg), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert "message" not in summary and "bits" not in summary  # kept in the registry, not printed
    assert summary["mark"]["label"] == "alice" and summary["registry"] == str(reg)
    with open_registry(reg, create=False) as r:
        mark = r.get("alice")
    assert (mark.num_bits, mark.decoder_sha256) == (48, shipped_decoder_sha256(48))
    assert mark.model_hash == hash_gaussians(load_inria_model(out).gaussians)
    assert (mark.width, mark.height, mark.background) == (48, 48, (1.0, 1.0, 1.0))
    assert mark.origin == "random"  # a fresh secret message: the exact test applies
    assert mark.message_hex not in json.dumps(summary)
    _assert_no_file_holds(out, [mark.message_hex])
    # refused before any embedding: a label already registered, --registry without --label, a bad label
    for extra in (["--label", "alice", "--registry", str(reg)], ["--registry", str(reg)], ["--label", "123"]):
        assert main(["embed", str(model_dir), "--output", str(tmp_path / "m2"), *EMBED, *extra]) == 2
        assert not (tmp_path / "m2").exists()
    err = capsys.readouterr().err
    assert "already registered" in err and "--label" in err and "all digits" in err


def test_embed_image_records_the_mark_and_identify_names_the_recipient(setup, tmp_path, capsys) -> None:
    reg = tmp_path / "marks.sqlite"
    with open_registry(reg) as r:
        r.add("alice", random_message(BITS, seed=7), decoder_sha256=shipped_decoder_sha256(BITS))
    src, out = tmp_path / "poster.png", tmp_path / "poster_bob.png"
    write_image(src, 0.25 + 0.5 * torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0)))
    # bob's message: what the decoder already reads from the poster (a faint 40 dB pass keeps it exactly)
    message = message_to_hex(extract(read_image(src), num_bits=BITS).bits[0])
    args = ["--bits", str(BITS), "--message", message, "--steps", "5", "--psnr", "40", "--device", "cpu",
            "--no-progress", "--registry", str(reg)]
    assert main(["embed-image", str(src), "--output", str(out), *args, "--label", "bob"]) == 0
    text, err = capsys.readouterr()
    with open_registry(reg, create=False) as r:
        bob = r.get("bob")
    assert "recorded as mark" in text and message not in text and bob.message_hex == message
    assert bob.origin == "chosen" and "--chosen-message" in err  # a typed message: tested as chosen
    assert (bob.width, bob.height, bob.num_bits, bob.model_hash) == (64, 64, BITS, None)
    assert main(["identify", str(out), "--registry", str(reg), "--device", "cpu", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["recipients"] == ["bob"]
    # the same message for another recipient is refused before any work
    assert main(["embed-image", str(src), "--output", str(tmp_path / "x.png"), *args, "--label", "carol"]) == 2
    assert "already issued" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


def test_embed_image_readout_klein_records_the_wrapper_and_identify_names_the_recipient(tmp_path, capsys) -> None:
    from gsw.decoder.readout import shipped_klein_fingerprint

    reg, src, out = tmp_path / "marks.sqlite", tmp_path / "poster.png", tmp_path / "poster_kim.png"
    with open_registry(reg) as r:
        r.add("dan", random_message(BITS, seed=8), decoder_sha256=shipped_decoder_sha256(BITS), origin="random")
    write_image(src, 0.25 + 0.5 * torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(1)))
    args = ["--bits", str(BITS), "--key", "kim-secret", "--steps", "20", "--psnr", "32", "--readout", "klein",
            "--device", "cpu", "--no-progress", "--registry", str(reg)]
    assert main(["embed-image", str(src), "--output", str(out), *args, "--label", "kim"]) == 0
    with open_registry(reg, create=False) as r:
        kim = r.get("kim")
    assert kim.decoder_sha256 == shipped_klein_fingerprint(BITS) != shipped_decoder_sha256(BITS)
    assert kim.origin == "random"
    capsys.readouterr()
    assert main(["identify", str(out), "--registry", str(reg), "--device", "cpu", "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["recipients"] == ["kim"] and found["marks_tested"] == 2  # the klein mark is recognised, not skipped
    # the same message through the same readout for another recipient is refused before any work
    assert main(["embed-image", str(src), "--output", str(tmp_path / "x.png"), *args, "--label", "zoe"]) == 2
    assert "already issued" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
