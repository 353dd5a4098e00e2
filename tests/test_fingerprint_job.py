"""gsw.fingerprint in one process: copies, registry records, markers, resume, bad input, the no-Ray path."""

from __future__ import annotations

import shutil

import pytest
import torch

import gsw
from gsw.fingerprint.store import DONE_FILE, JOB_FILE
from gsw.fingerprint.batched import pool_config
from gsw.fingerprint.plan import parse_recipients
from gsw.mark.embed import EmbedConfig
from gsw.registry import hash_model_file, open_registry, shipped_decoder_sha256
from gsw.scenes import default_scene
from helpers import ReadsOnes


def _scene(seed: int = 0):
    return default_scene(width=32, height=32, n_cameras=2, detail=0.2, seed=seed)


def _config(scene) -> EmbedConfig:
    return pool_config(epochs=1, lpips_net=None, weights={"lpips": 0.0},
                       background=tuple(float(v) for v in scene.background))


def _run(scene, names, out, reg, **kw):
    kw.setdefault("use_ray", False)
    kw.setdefault("device", "cpu")
    return gsw.fingerprint(scene.gaussians, scene.cameras, names, out, reg, config=_config(scene), batch_size=2,
                           progress=False, **kw)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A finished job of three recipients: (scene, output folder, registry path, report)."""
    root = tmp_path_factory.mktemp("fp")
    scene = _scene()
    report = _run(scene, ["alice", "bob", "carol"], root / "out", root / "marks.sqlite")
    return scene, root / "out", root / "marks.sqlite", report


def _copy_job(job, tmp_path):
    scene, out, reg, _ = job
    shutil.copytree(out, tmp_path / "out")
    shutil.copy(reg, tmp_path / "marks.sqlite")
    return scene, tmp_path / "out", tmp_path / "marks.sqlite"


def test_copies_registered_and_marked(job) -> None:
    scene, out, reg, report = job
    assert report.runner == "local" and report.names("embedded") == ["alice", "bob", "carol"]
    assert (out / JOB_FILE).is_file()
    with open_registry(reg) as r:
        marks = {m.label: m for m in r.list()}
    assert set(marks) == {"alice", "bob", "carol"}
    assert len({m.message_hex for m in marks.values()}) == 3
    for name, mark in marks.items():
        ply = out / name / "point_cloud" / "iteration_0" / "point_cloud.ply"
        assert mark.model_hash == hash_model_file(ply)
        assert mark.decoder_sha256 == shipped_decoder_sha256(32) and (mark.width, mark.height) == (32, 32)
        assert mark.origin == "random"  # drawn with `secrets`: tested with the exact randomization test
        assert (out / name / DONE_FILE).is_file() and (out / name / "watermark.json").is_file()
        for f in out.rglob("*"):  # the secret message is in the registry only
            if f.is_file():
                data = f.read_bytes().lower()
                assert mark.message_hex.encode() not in data, f
    rep = {r.name: r for r in report.recipients}
    assert rep["bob"].mark_id == marks["bob"].id and 0 <= rep["bob"].bit_accuracy <= 1 and rep["bob"].psnr > 20
    # when each copy reached the writer, and the one pool's scene preparation (paid once, before the first batch)
    assert 0 < rep["alice"].finished_s <= report.timings["finetune"]
    t = report.timings
    assert 0 < t["setup"] <= t["before_finetune"] and t["before_finetune"] + t["finetune"] <= t["total"]
    assert all(r.worker_setup_s == rep["alice"].worker_setup_s > 0 for r in report.recipients)


def test_a_slow_write_does_not_reorder_the_registry(tmp_path, monkeypatch) -> None:
    """Copies are written on several threads; the first copy's write is slowest here, yet every recipient is
    registered (and marked done) in the order its copy arrived, each after its own folder."""
    import time

    from gsw.fingerprint import job as job_module
    from gsw.fingerprint.store import JobFolder

    monkeypatch.setattr(job_module, "WRITER_THREADS", 3)
    write = JobFolder.write_copy

    def slow_first(self, name, *args, **kwargs):
        time.sleep(1.0 if name == "alice" else 0.0)
        return write(self, name, *args, **kwargs)

    monkeypatch.setattr(JobFolder, "write_copy", slow_first)
    scene = _scene()
    report = _run(scene, ["alice", "bob", "carol"], tmp_path / "out", tmp_path / "marks.sqlite")
    by_arrival = sorted(report.recipients, key=lambda r: r.finished_s)
    assert [r.mark_id for r in by_arrival] == sorted(r.mark_id for r in report.recipients)
    with open_registry(tmp_path / "marks.sqlite") as reg:
        assert {m.label: m.model_hash for m in reg.list()} == {
            n: hash_model_file(tmp_path / "out" / n / "point_cloud" / "iteration_0" / "point_cloud.ply")
            for n in ("alice", "bob", "carol")}


def test_rerun_skips_finished_and_adds_new(job, tmp_path) -> None:
    scene, out, reg = _copy_job(job, tmp_path)
    ply = out / "alice" / "point_cloud" / "iteration_0" / "point_cloud.ply"
    before = ply.stat().st_mtime_ns
    report = _run(scene, ["alice", "bob", "carol", "dave"], out, reg)
    assert [r.status for r in report.recipients] == ["skipped", "skipped", "skipped", "embedded"]
    assert ply.stat().st_mtime_ns == before
    again = _run(scene, ["alice", "dave"], out, reg)
    assert again.runner == "none" and again.names("skipped") == ["alice", "dave"]
    from gsw.fingerprint.plan import Recipient

    _run(scene, [Recipient("erin", message="0123abcd"), Recipient("fay", key="k")], out, reg)
    with open_registry(reg) as r:  # a message given in the recipients file is a chosen one
        assert (r.get("erin").origin, r.get("fay").origin, r.get("dave").origin) == ("chosen", "random", "random")


def test_half_written_recipients(job, tmp_path) -> None:
    scene, out, reg = _copy_job(job, tmp_path)
    (out / "bob" / DONE_FILE).unlink()  # stopped between registration and marker
    (out / "erin" / "point_cloud").mkdir(parents=True)  # stopped while writing, before registration
    (out / "erin" / "junk.tmp").write_text("partial")
    report = _run(scene, ["alice", "bob", "erin"], out, reg)
    assert [r.status for r in report.recipients] == ["skipped", "completed", "embedded"]
    assert (out / "bob" / DONE_FILE).is_file() and not (out / "erin" / "junk.tmp").exists()
    with open_registry(reg) as r:
        assert r.get("erin").model_hash == hash_model_file(out / "erin" / "point_cloud" / "iteration_0" /
                                                           "point_cloud.ply")


def _snapshot(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_mtime_ns) for p in folder.rglob("*"))


def test_output_folder_of_another_scene(job, tmp_path) -> None:
    _, out, reg = _copy_job(job, tmp_path)
    before = _snapshot(out)
    with pytest.raises(ValueError, match="another scene"):
        _run(_scene(seed=1), ["alice", "zed"], out, reg)
    assert _snapshot(out) == before


def test_folder_that_is_not_a_job(tmp_path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a fingerprint job"):
        _run(_scene(), ["alice"], tmp_path / "out", tmp_path / "r.sqlite")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


@pytest.mark.parametrize("rows, error", [
    (["alice,xyz"], "message of 'alice': a 32-bit message needs exactly 8 hex digits"),
    (["alice,0123abcd", "bob,0123ABCD"], "the message of 'bob' is already issued"),
])
def test_bad_messages_are_refused_before_any_write(tmp_path, rows, error) -> None:
    """A malformed or repeated message in the recipients file leaves no output folder and no registry."""
    people = parse_recipients("recipient,message\n" + "\n".join(rows) + "\n", "r.csv")
    with pytest.raises(ValueError, match=error):
        _run(_scene(), people, tmp_path / "out", tmp_path / "r.sqlite")
    assert not (tmp_path / "out").exists() and not (tmp_path / "r.sqlite").exists()


def test_registry_of_another_decoder(tmp_path) -> None:
    with open_registry(tmp_path / "r.sqlite") as r:
        r.add("alice", "0123abcd", decoder_sha256="f" * 64)
    with pytest.raises(ValueError, match="registered for another decoder"):
        _run(_scene(), ["alice", "bob"], tmp_path / "out", tmp_path / "r.sqlite")
    assert not (tmp_path / "out").exists()


def test_name_registered_with_another_model(tmp_path) -> None:
    with open_registry(tmp_path / "r.sqlite") as r:
        r.add("alice", "0123abcd", decoder_sha256=shipped_decoder_sha256(32), model_hash="sha256:" + "0" * 64)
    with pytest.raises(ValueError, match="already registered with another model"):
        _run(_scene(), ["bob", "alice"], tmp_path / "out", tmp_path / "r.sqlite")
    assert not (tmp_path / "out" / "bob").exists()


def test_without_ray(tmp_path, monkeypatch) -> None:
    import gsw.fingerprint.run as run

    monkeypatch.setattr(run, "ray_available", lambda: False)
    messages = []
    report = _run(_scene(), ["a1", "b1", "c1"], tmp_path / "out", tmp_path / "r.sqlite", use_ray=None,
                  log=messages.append)
    assert report.runner == "local" and report.names("embedded") == ["a1", "b1", "c1"]
    assert any("pip install gsw[ray]" in m for m in messages)
    with pytest.raises(ImportError, match=r"pip install gsw\[ray\]"):
        _run(_scene(), ["d1"], tmp_path / "out", tmp_path / "r.sqlite", use_ray=True)


def test_redrawn_messages_are_registered_as_chosen(tmp_path) -> None:
    import json

    from gsw.fingerprint.plan import Recipient
    from gsw.fingerprint.stopping import EarlyStop
    from gsw.mark.message import message_from_key, message_to_hex

    people = [Recipient("drawn"), Recipient("given", "0123abcd"), Recipient("keyed", key="k-secret")]
    rule = EarlyStop(min_steps=100, window=1, check_every=1, confirm=1.0, redraw=1, redraw_bits=1.0)
    report = _run(_scene(), people, tmp_path / "out", tmp_path / "r.sqlite", decoder=ReadsOnes(), early_stop=rule)
    rep = {r.name: r for r in report.recipients}
    assert (rep["drawn"].redraws, rep["given"].redraws, rep["keyed"].redraws) == (1, 0, 0)
    with open_registry(tmp_path / "r.sqlite") as r:
        marks = {m.label: m for m in r.list()}
    assert (marks["drawn"].origin, marks["given"].origin, marks["keyed"].origin) == ("chosen", "chosen", "random")
    assert marks["given"].message_hex == "0123abcd"
    assert marks["keyed"].message_hex == message_to_hex(message_from_key("k-secret", 32))
    record = json.loads((tmp_path / "out" / "drawn" / "watermark.json").read_text())
    assert record["message_origin"] == "chosen"
    for f in (tmp_path / "out").rglob("*"):  # the new message is in the registry only
        if f.is_file():
            assert marks["drawn"].message_hex.encode() not in f.read_bytes().lower(), f


def test_probes_reach_the_report_and_need_two_cameras(tmp_path) -> None:
    from gsw.fingerprint.stopping import EarlyStop

    rule = EarlyStop(min_steps=1, window=1, check_every=1, probes=2)
    report = _run(_scene(), ["alice"], tmp_path / "out", tmp_path / "r.sqlite", decoder=ReadsOnes(), early_stop=rule)
    acc = report.recipients[0].probe_bit_accuracy
    assert acc is not None and 0 <= acc <= 1 and (acc * 64) == pytest.approx(round(acc * 64))  # 2 views of 32 bits
    one = _scene()
    with pytest.raises(ValueError, match="at least 2 cameras"):
        gsw.fingerprint(one.gaussians, one.cameras[:1], ["bob"], tmp_path / "out2", tmp_path / "r2.sqlite",
                        config=_config(one), early_stop=rule, use_ray=False, device="cpu", progress=False)
    assert not (tmp_path / "out2").exists() and not (tmp_path / "r2.sqlite").exists()  # refused before any write


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_same_job_same_bits(device, tmp_path) -> None:
    """Two runs of one job (same scene, messages and settings) write bitwise-identical copies: the rasterizer's
    backward sums in a fixed order and the decoder's convolutions run deterministically (gsw.device.deterministic),
    so a copy does not depend on the run, the worker or the GPU count that made it (#27)."""

    from gsw.data import load_inria_model

    if device == "cuda" and not (torch.cuda.is_available() and gsw.build_info()["cuda"]):
        pytest.skip("needs a CUDA device and a CUDA build of gsw")
    scene = default_scene(width=48, height=48, n_cameras=3, detail=0.3, seed=1, device=device)
    from gsw.fingerprint.plan import Recipient

    names = [Recipient("r0", "0f1e2d3c"), Recipient("r1", "a5a5a5a5")]
    copies = []
    for run in ("a", "b"):
        _run(scene, names, tmp_path / run, tmp_path / f"{run}.sqlite", device=device)
        copies.append([load_inria_model(tmp_path / run / r.name).gaussians for r in names])
    for x, y in zip(*copies):
        for key, value in x.parameters().items():
            assert torch.equal(value, y.parameters()[key]), key
