"""gsw scan's batched pipeline (gsw.fingerprint.scan): the results of identify on each source alone."""

from __future__ import annotations

import os

from pathlib import Path

import pytest
import torch
from helpers import scan_crawl

import gsw.fingerprint.scan
import gsw.mark.identify
import gsw.mark.scales
from gsw.fingerprint.scan import scan, scan_sources
from gsw.io.video import expand_inputs
from gsw.io.video import load_images_or_video
from gsw.mark.identify import decode_sources, identify, identify_readings, plan_identify

pytest.importorskip("av")


@pytest.fixture(scope="module")
def crawl(tmp_path_factory) -> tuple[list[Path], list]:
    root = tmp_path_factory.mktemp("scan")
    marks = scan_crawl(root / "web")
    return expand_inputs([root / "web"]), marks


def _summary(found) -> list[tuple]:
    return [(r.mark.label, r.p_value, r.adjusted_p_value, r.matches, r.identified, r.exact) for r in found.results]


def test_decode_then_test_equals_identify_on_each_source(crawl) -> None:
    paths, marks = crawl
    sources = [load_images_or_video([p], 16) for p in paths if p.name not in ("broken.png", "empty.mp4")]
    plan = plan_identify(marks)
    decoded = decode_sources(sources, plan, batch_size=5)
    for images, readings in zip(sources, decoded):
        alone = identify(images, marks)
        together = identify_readings(readings, plan)
        assert _summary(together) == _summary(alone) and together.num_images == alone.num_images == len(images)
    with pytest.raises(ValueError, match="source 1: no images"):
        decode_sources([sources[0], []], plan)


#: The chosen marks' messages are read from unmarked renders, which the calibrated null model discounts:
#: they are identified at this level (not at the default 1e-6).
FPR = 1e-4


def test_scan_rows_equal_the_per_source_path(crawl) -> None:
    paths, marks = crawl
    rows = scan_sources(paths, marks, fpr=FPR, batch_size=4, readers=2)
    assert [Path(r.source) for r in rows] == paths
    by_name = {Path(r.source).name: r for r in rows}
    assert by_name["img1.png"].identified == "alice" and by_name["wide0.jpg"].identified == "bob"
    assert by_name["img3.png"].identified == "dave" and by_name["clip.mkv"].images == 3
    assert by_name["clip.mkv"].identified == "carol" and by_name["img0.png"].identified == ""
    for path, row in zip(paths, rows):
        if path.name in ("broken.png", "empty.mp4"):
            assert row.error and row.images == 0 and row.best_p is None
            continue
        alone = identify(load_images_or_video([path], 16), marks, fpr=FPR)
        best = alone.results[0]
        assert (row.identified, row.best_label, row.best_p, row.best_adjusted_p, row.images, row.error) == (
            ";".join(alone.recipients), best.mark.label, best.p_value, best.adjusted_p_value, alone.num_images, "")
    assert [r.to_dict() for r in scan_sources(paths, marks, fpr=FPR, batch_size=64,
                                                           readers=1)] == [r.to_dict() for r in rows]


def test_images_of_many_sources_share_decoder_calls(crawl, monkeypatch) -> None:
    paths, marks = crawl
    batches = []
    real = gsw.mark.scales._decode

    def counting(decoder, images):
        batches.append(images.shape[0])
        return real(decoder, images)

    monkeypatch.setattr(gsw.mark.scales, "_decode", counting)
    scan_sources(paths, marks, batch_size=64)
    # one chunk: per reading, the six 96x96 PNGs and the video's 3 frames together, the two JPEGs together
    assert max(batches) == 9 and len(batches) < sum(r for r in batches)


def test_a_source_the_decoder_rejects_gets_an_error_and_the_others_are_scanned(crawl, monkeypatch) -> None:
    paths, marks = crawl
    real = gsw.mark.identify.read_images

    def picky(images, decoder, **kwargs):
        if any(img.shape[-1] == 112 for img in images):
            raise RuntimeError("cannot read\n this size")
        return real(images, decoder, **kwargs)

    monkeypatch.setattr(gsw.mark.identify, "read_images", picky)
    rows = {Path(r.source).name: r for r in scan_sources(paths, marks, batch_size=64)}
    assert rows["wide0.jpg"].error == rows["wide1.jpg"].error == "cannot read this size"
    assert rows["wide0.jpg"].images == 1 and rows["wide0.jpg"].best_p is None
    assert rows["img1.png"].identified == "alice" and not rows["img1.png"].error


def test_progress_and_bad_arguments(crawl, monkeypatch) -> None:
    paths, marks = crawl
    seen, times = [], []
    rows = scan(paths[:3], marks, use_ray=False, batch_size=2, readers=3, on_row=seen.append, times=times)
    assert seen == rows
    (st,) = times  # the pipeline's stages: the testing thread's waits and work fit in its wall time
    assert (st.sources, st.images) == (3, sum(r.images for r in rows)) and st.pid == os.getpid()
    assert min(st.read_wait, st.decode_wait, st.test) >= 0 and st.decode > 0
    assert st.read_wait + st.decode_wait + st.test <= st.wall
    assert st.started <= st.ended and st.ended - st.started == pytest.approx(st.wall, abs=0.05)
    assert st.worker_ready == 0 and st.worker_init == 0  # in this process: no Ray worker
    for bad in (dict(batch_size=0), dict(readers=0), dict(batch_size=2.5)):
        with pytest.raises(ValueError, match="must be a positive int"):
            scan(paths[:1], marks, use_ray=False, **bad)
    with pytest.raises(ValueError, match="no marks"):
        scan(paths[:1], [], use_ray=False)
    monkeypatch.setattr(gsw.fingerprint.scan, "_ray_data_available", lambda: False)
    with pytest.raises(ImportError, match=r"pip install gsw\[ray\]"):
        scan(paths[:1], marks, use_ray=True)
    assert [r.source for r in scan(paths[:1], marks)] == [str(paths[0])]  # default: this process, quietly


def test_ray_only_by_default_where_it_adds_gpus(monkeypatch) -> None:
    """Ray Data by default only for many sources on several visible GPUs (one GPU, a CPU: this process)."""
    from gsw.fingerprint.scan import RAY_DATA_MIN_SOURCES, ray_by_default

    n = RAY_DATA_MIN_SOURCES
    for gpus, device, sources, want in [(2, "cuda", n, True), (4, "cuda:1", 10 * n, True), (1, "cuda", 10 * n, False),
                                        (2, "cuda", n - 1, False), (2, "cpu", 10 * n, False), (2, None, 10 * n, False)]:
        monkeypatch.setattr(torch.cuda, "device_count", lambda g=gpus: g)
        assert ray_by_default(sources, device) is want, (gpus, device, sources)


@pytest.mark.parametrize("sources, workers, batch", [(10_000, 4, 64), (10_000, 2, 64), (10_000, 1, 64), (7, 3, 4),
                                                     (1, 4, 64), (5_000, 3, 4)])
def test_ray_blocks_are_shared_evenly(sources, workers, batch) -> None:
    """Every worker gets the same number of calls of at most RAY_SOURCES_PER_CALL x batch sources, covering all."""
    from gsw.fingerprint.scan import RAY_SOURCES_PER_CALL, ray_block_size

    size = ray_block_size(sources, workers, batch)
    calls = -(-sources // size)
    assert 1 <= size <= RAY_SOURCES_PER_CALL * batch and calls * size >= sources
    if sources >= workers:  # calls dealt in turn: no worker gets a whole call more than another
        per_worker = [sum(min(size, sources - c * size) for c in range(w, calls, workers)) for w in range(workers)]
        assert max(per_worker) - min(per_worker) < size
    assert ray_block_size(10_000, 4, 64) == 2_500  # one call per worker (was 10 calls of 1,024, then 12 of 834)
    assert ray_block_size(100_000, 4, 64) == 3_572  # 28 calls of at most 64 x 64 sources, 7 per worker
