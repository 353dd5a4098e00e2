"""Scanning many images and videos for registered marks: :func:`scan`.

Every image file is one source, every video one source (its frames taken together). Each source gets
the result :func:`gsw.mark.identify.identify` would give it alone (every registered mark tested by its
origin's test -- random: the exact randomization test, chosen: the calibrated null model -- with the scale
search, and Holm's family-wise correction over the marks; batching changes the decoder's outputs only by
float rounding, which the tests, reading signs and ranks, see only when two logits, or one and 0, lie
within it: :mod:`gsw.mark.identify`), computed as a pipeline:

1. ``readers`` threads read sources ahead of the decoder (PIL and PyAV release the GIL), at most
   ``2 x batch_size`` sources ahead, keeping 8-bit images as uint8 (a quarter of float32's bytes to stack and
   move to the GPU, which makes them float32 bitwise as the float reader would: :func:`gsw.data.images.to_unit`);
2. consecutive sources are taken together until they hold ``batch_size`` images; the decoders (loaded once,
   :func:`gsw.mark.identify.plan_identify`) read all their images together, images of one shape in batches
   of up to ``batch_size`` (:func:`gsw.mark.identify.decode_sources`);
3. each source is tested on its own decoder outputs (:func:`gsw.mark.identify.identify_readings`), while
   the next group is decoded on a thread.

A file that cannot be read (or that the decoder cannot read) gets a row with its ``error``; the others are
scanned. On a cluster (an ``address``), when asked (``use_ray=True``), or by default with at least
:data:`RAY_DATA_MIN_SOURCES` sources on CUDA with several GPUs visible (:func:`ray_by_default`), and with Ray Data
installed (``pip install gsw[ray]``), the paths go to Ray Data workers instead (``map_batches``, one worker per GPU
on CUDA or per CPU), each running the same pipeline on blocks of sources, as many blocks for every worker
(:func:`ray_block_size`), one block in flight per worker at a time; the rows come back in input order. On one
GPU or a CPU the default is this process (:func:`ray_by_default` says why). ``times`` collects each pipeline's
:class:`StageTimes` (benchmarks).
"""

from __future__ import annotations

import json
import os
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import torch

from gsw.stats import DETECTION_FPR

if TYPE_CHECKING:
    from gsw.mark.identify import IdentifyPlan, SourceReadings

__all__ = ["DEFAULT_BATCH_SIZES", "DEFAULT_READERS", "RAY_DATA_MIN_SOURCES", "RAY_SOURCES_PER_CALL", "ScanRow",
           "StageTimes", "ray_block_size", "ray_by_default", "scan", "scan_sources"]

#: Sources from which :func:`scan` uses Ray Data by default on several GPUs (:func:`ray_by_default`).
RAY_DATA_MIN_SOURCES = 256
#: Images per decoder call (and per group of consecutive sources decoded together) by device type: on a GPU
#: large batches amortise the per-call cost; on a CPU the decoder is compute-bound and batches beyond a few
#: images run slower per image (measured on a 2-core CPU at 256x256: ~0.64 s per image in batches of 48
#: against ~0.47 s one by one, BENCHMARKS.md).
DEFAULT_BATCH_SIZES = {"cuda": 64, "cpu": 4}
#: Threads reading (decoding the files of) sources ahead of the decoder.
DEFAULT_READERS = 4
#: A Ray Data worker is handed at most this many x ``batch_size`` sources per call (:func:`ray_block_size`). Each
#: call starts its pipeline anew (the readers' first group, the last group's tests not overlapped): on 4 GPUs,
#: 10,000 lego files in calls of 4 x 64 were scanned at 932 images/s, in calls of 16 x 64 at 1,056, four processes
#: with one call each (no Ray) at 1,213; so calls are large, and a crawl of up to 64 x 64 sources per worker is
#: one call per worker (then 10,000 built-in scene files: 1,177 images/s, 0.85 of 4 x one worker; BENCHMARKS.md,
#: ninth round).
RAY_SOURCES_PER_CALL = 64
#: The extra output column of a timed Ray Data call (its :class:`StageTimes` as JSON, on its first row).
_TIMES = "_stage_times"


def ray_block_size(sources: int, workers: int, batch_size: int) -> int:
    """Sources per Ray Data call: at most :data:`RAY_SOURCES_PER_CALL` x ``batch_size``, and the same number of
    calls for every worker (10,000 sources in calls of 1,024 on 4 workers left one worker a third call of
    1,024 while the others had done 2,048 each; 4 calls of 2,500 give every worker one)."""
    cap = RAY_SOURCES_PER_CALL * batch_size
    calls = workers * -(-sources // (workers * cap))  # a multiple of the workers
    return max(1, -(-sources // max(1, calls)))


@dataclass
class ScanRow:
    """One source's result (no messages).

    Attributes:
        source: the file.
        images: images (frames) read.
        identified: labels of the identified recipients, most significant first.
        best_label: the most significant mark tested (identified or not).
        best_adjusted_p: its family-wise adjusted p-value.
        best_p: its p-value.
        best_bit_accuracy: its share of message bits read right in the best image.
        error: why the source could not be read ("" when it was).
    """

    source: str
    images: int = 0
    identified: str = ""
    best_label: str = ""
    best_adjusted_p: float | None = None
    best_p: float | None = None
    best_bit_accuracy: float | None = None
    error: str = ""

    def to_dict(self) -> dict[str, Any]:
        """A flat dict (CSV / JSON row)."""
        return asdict(self)


@dataclass
class StageTimes:
    """Where one scanning pipeline's time went, in seconds (benchmarks: :func:`scan`'s ``times``).

    Attributes:
        wall: the pipeline from start to end.
        read_wait: the testing thread waiting for the readers (the next group of sources).
        decode_wait: the testing thread waiting for the decoding thread.
        test: the testing thread testing sources (:func:`gsw.mark.identify.identify_readings`, rows).
        decode: the decoding thread in :func:`gsw.mark.identify.decode_sources` (moving the images, resizing,
            the decoders, the logits back).
        sources: sources scanned.
        images: images read.
        pid: the process (one per Ray worker).
        started: when the pipeline started (seconds since the epoch: a timeline across processes).
        ended: when it ended (seconds since the epoch).
        worker_ready: on Ray, when this worker had loaded its decoders (seconds since the epoch; 0 here).
        worker_init: on Ray, the seconds this worker spent loading them (0 here).
    """

    wall: float = 0.0
    read_wait: float = 0.0
    decode_wait: float = 0.0
    test: float = 0.0
    decode: float = 0.0
    sources: int = 0
    images: int = 0
    pid: int = 0
    started: float = 0.0
    ended: float = 0.0
    worker_ready: float = 0.0
    worker_init: float = 0.0


def _batching(batch_size: int | None, readers: int, device: torch.device | str | None) -> int:
    """``batch_size``, or the default of ``device`` (:data:`DEFAULT_BATCH_SIZES`) when None.

    Raises:
        ValueError: ``batch_size`` or ``readers`` not a positive int.
    """
    if batch_size is None:
        batch_size = DEFAULT_BATCH_SIZES.get(torch.device(device or "cpu").type, DEFAULT_BATCH_SIZES["cpu"])
    for name, value in (("batch_size", batch_size), ("readers", readers)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    return batch_size


def _load(path: Path, frames: int) -> tuple[list[torch.Tensor], str]:
    """A source's images, or ``([], why)`` when it cannot be read."""
    from gsw.io.video import load_images_or_video

    try:
        return load_images_or_video([path], frames, keep_uint8=True), ""
    except (OSError, ValueError, ImportError, RuntimeError) as err:
        return [], _why(err)


def _why(err: BaseException) -> str:
    """An error's message on one line (a report cell)."""
    return " ".join(str(err).split()) or type(err).__name__


def _read_ahead(paths: Sequence[Path], frames: int, readers: int,
                ahead: int) -> Iterator[tuple[Path, list[torch.Tensor], str]]:
    """``(path, images, error)`` per source, in order, read by ``readers`` threads at most ``ahead`` sources
    ahead of the consumer (bounded memory)."""
    with ThreadPoolExecutor(max_workers=readers) as pool:
        todo = iter(paths)
        pending: deque = deque((p, pool.submit(_load, p, frames)) for p in islice(todo, ahead))
        while pending:
            path, future = pending.popleft()
            for p in islice(todo, 1):
                pending.append((p, pool.submit(_load, p, frames)))
            yield (path, *future.result())


def _chunks(loaded: Iterator[tuple[Path, list[torch.Tensor], str]],
            images: int) -> Iterator[list[tuple[Path, list[torch.Tensor], str]]]:
    """Consecutive sources grouped until a group holds at least ``images`` images (or the sources end)."""
    chunk: list[tuple[Path, list[torch.Tensor], str]] = []
    count = 0
    for item in loaded:
        chunk.append(item)
        count += len(item[1])
        if count >= images:
            yield chunk
            chunk, count = [], 0
    if chunk:
        yield chunk


def _decode(sources: list[list[torch.Tensor]], plan: IdentifyPlan, batch_size: int) -> list[SourceReadings | str]:
    """:func:`decode_sources` of the sources together; when that fails, each source alone, so that a source
    the decoder cannot read gets its own error (a string) and the others their readings."""
    from gsw.mark.identify import decode_sources

    if not sources:
        return []
    try:
        return decode_sources(sources, plan, batch_size=batch_size)
    except (RuntimeError, ValueError) as err:
        if len(sources) == 1:
            return [_why(err)]
        return [out for images in sources for out in _decode([images], plan, batch_size)]


def _row(path: Path, images: int, error: str, readings: SourceReadings | str | None, plan: IdentifyPlan,
         fpr: float) -> ScanRow:
    """A source's row: its identification from ``readings`` (:func:`_decode`'s output, an error string, or
    None for a source that could not be read)."""
    from gsw.mark.identify import identify_readings

    row = ScanRow(str(path), images, error=error)
    if isinstance(readings, str):
        row.error = readings
    elif readings is not None:
        res = identify_readings(readings, plan, fpr=fpr, keep=1)  # the row reports the best mark only
        row.identified = ";".join(res.recipients)
        if res.results:
            best = res.results[0]
            row.best_label, row.best_adjusted_p, row.best_p = best.mark.label, best.adjusted_p_value, best.p_value
            row.best_bit_accuracy = best.best_bit_accuracy
    return row


def _scan_planned(paths: Sequence[Path], plan: IdentifyPlan, *, fpr: float, frames: int, batch_size: int,
                  readers: int, on_row: Callable[[ScanRow], None] | None = None,
                  times: StageTimes | None = None) -> list[ScanRow]:
    """:func:`scan_sources` with the decoders already loaded (``plan``): what every Ray worker runs.

    A chunk of sources is decoded on a thread while the previous chunk is tested here (the decoder's
    kernels release the GIL), so that a GPU does not wait for the tests. ``times`` (if given) gets the
    stages' seconds added."""
    rows: list[ScanRow] = []
    st = times if times is not None else StageTimes()
    start, st.started = time.perf_counter(), st.started or time.time()

    def decode(sources: list[list[torch.Tensor]]) -> list[SourceReadings | str]:
        t0 = time.perf_counter()
        try:
            return _decode(sources, plan, batch_size)
        finally:
            st.decode += time.perf_counter() - t0

    def finish(chunk: list[tuple[Path, list[torch.Tensor], str]], decoding: Future) -> None:
        t0 = time.perf_counter()
        decoded = iter(decoding.result())
        t1 = time.perf_counter()
        for path, images, error in chunk:
            rows.append(_row(path, len(images), error, next(decoded) if images else None, plan, fpr))
            st.sources, st.images = st.sources + 1, st.images + len(images)
            if on_row is not None:
                on_row(rows[-1])
        st.decode_wait, st.test = st.decode_wait + t1 - t0, st.test + time.perf_counter() - t1

    previous = None
    with ThreadPoolExecutor(max_workers=1) as decoder:
        chunks = _chunks(_read_ahead(paths, frames, readers, ahead=max(2 * batch_size, readers)), batch_size)
        while True:
            t0 = time.perf_counter()
            chunk = next(chunks, None)
            st.read_wait += time.perf_counter() - t0
            if chunk is None:
                break
            decoding = decoder.submit(decode, [images for _, images, _ in chunk if images])
            if previous is not None:
                finish(*previous)
            previous = (chunk, decoding)
        if previous is not None:
            finish(*previous)
    st.wall, st.pid, st.ended = st.wall + time.perf_counter() - start, os.getpid(), time.time()
    return rows


def scan_sources(paths: Sequence[Path], marks: Sequence, *, fpr: float = DETECTION_FPR,
                 device: torch.device | None = None, frames: int = 16, batch_size: int | None = None,
                 readers: int = DEFAULT_READERS, on_row: Callable[[ScanRow], None] | None = None,
                 times: StageTimes | None = None) -> list[ScanRow]:
    """Identifies each source in this process, the images of consecutive sources decoded in batches.

    Sources are read by ``readers`` threads ahead of the decoding (image and video decoding release the
    GIL). Consecutive sources are taken together until they hold ``batch_size`` images; their images go
    through each decoder together (:func:`gsw.mark.identify.decode_sources`: images of one shape in batches
    of up to ``batch_size``), then each source is tested on its own decoder outputs
    (:func:`gsw.mark.identify.identify_readings`): the p-values and identified recipients of
    :func:`gsw.mark.identify.identify` on that source alone.

    Args:
        paths: image / video files.
        marks: the registered marks (:meth:`gsw.registry.Registry.list`).
        fpr: family-wise false-positive rate per source.
        device: where to decode (None: the CPU).
        frames: frames read per video.
        batch_size: images per decoder call (and per group of sources); None: :data:`DEFAULT_BATCH_SIZES`
            of ``device``.
        readers: threads reading sources.
        on_row: called after each source (progress).
        times: gets the pipeline's stage times added (:class:`StageTimes`).

    Returns:
        One :class:`ScanRow` per path, in order; an unreadable source (or one the decoder cannot read) has
        its ``error`` set and the others are scanned.

    Raises:
        ValueError: ``batch_size`` or ``readers`` < 1.
    """
    from gsw.mark.identify import plan_identify

    batch_size = _batching(batch_size, readers, device)
    plan = plan_identify(marks, device=device or "cpu")
    return _scan_planned(paths, plan, fpr=fpr, frames=frames, batch_size=batch_size, readers=readers,
                         on_row=on_row, times=times)


class _RayScanner:  # pragma: no cover - runs in Ray Data workers
    """One Ray Data worker: the decoders loaded once, each batch of paths scanned by :func:`_scan_planned`."""

    def __init__(self, marks: Sequence, fpr: float, frames: int, batch_size: int, readers: int, gpu: bool,
                 threads: int = 1, timed: bool = False) -> None:
        from gsw.mark.identify import plan_identify

        t0 = time.perf_counter()
        torch.set_num_threads(threads)  # Ray caps a worker's threads at its num_cpus (OMP_NUM_THREADS)
        self.plan = plan_identify(marks, device="cuda" if gpu else "cpu")
        self.fpr, self.frames, self.batch_size, self.readers, self.timed = fpr, frames, batch_size, readers, timed
        self.init_s, self.ready = time.perf_counter() - t0, time.time()

    def __call__(self, batch: dict) -> dict:
        times = StageTimes(worker_ready=self.ready, worker_init=self.init_s)
        rows = _scan_planned([Path(p) for p in batch["path"]], self.plan, fpr=self.fpr, frames=self.frames,
                             batch_size=self.batch_size, readers=self.readers, times=times)
        out = {k: [getattr(r, k) for r in rows] for k in ScanRow.__dataclass_fields__}
        if self.timed and rows:  # this call's stage times ride on its first row
            out[_TIMES] = [json.dumps(asdict(times))] + [""] * (len(rows) - 1)
        return out


def _ray_data_available() -> bool:
    """Whether Ray Data imports (Ray with its ``data`` extra)."""
    try:
        import ray.data  # noqa: F401
    except ImportError:
        return False
    return True


def _scan_ray(paths: Sequence[Path], marks: Sequence, *, fpr: float, frames: int, gpu: bool, address: str | None,
              workers: int | None, batch_size: int, readers: int, on_row: Callable[[ScanRow], None] | None = None,
              times: list[StageTimes] | None = None) -> list[ScanRow]:
    """Ray Data: one worker per GPU (or CPU), each scanning blocks of sources (:func:`ray_block_size`); rows put
    back in input order (``on_row`` sees them here as they arrive, a worker call's rows at a time). A GPU worker gets
    its share of the cluster's CPUs (reading, decoding files and the CPU side of the tests), as ``num_cpus`` and
    torch threads."""
    import ray

    from gsw.fingerprint.run import connect_ray

    started = connect_ray(address)
    try:
        resources = ray.cluster_resources()
        n = workers or max(1, int(resources.get("GPU" if gpu else "CPU", 1)))
        cpus = max(1, int((resources.get("CPU", 1) - 1) // n)) if gpu else 1  # one CPU left to Ray Data
        ds = ray.data.from_items([{"path": str(p)} for p in paths])
        ds = ds.map_batches(_RayScanner, fn_constructor_args=(list(marks), fpr, frames, batch_size, readers, gpu, cpus,
                                                              times is not None),
                            batch_size=ray_block_size(len(paths), n, batch_size),
                            # one call in flight per worker, so that a worker that started first does not queue
                            # the others' blocks: Ray Data 2.60 starts the pool without waiting for every actor,
                            # and one worker of two took all 48 sources of a CPU scan (BENCHMARKS.md)
                            compute=ray.data.ActorPoolStrategy(size=n, max_tasks_in_flight_per_actor=1),
                            num_gpus=1 if gpu else 0, num_cpus=cpus)
        by_path = {}
        for row in ds.iter_rows():
            r = dict(row)
            timing = r.pop(_TIMES, "")
            if timing and times is not None:
                times.append(StageTimes(**json.loads(timing)))
            by_path[r["source"]] = row = ScanRow(**r)
            if on_row is not None:
                on_row(row)
    finally:
        if started:
            ray.shutdown()
    return [by_path.get(str(p)) or ScanRow(str(p), error="no result came back from Ray") for p in paths]


def ray_by_default(sources: int, device: torch.device | str | None) -> bool:
    """Whether :func:`scan` uses Ray Data when not told: at least :data:`RAY_DATA_MIN_SOURCES` sources on CUDA
    with more than one GPU visible, the one case where Ray Data adds hardware this process cannot use. On one
    GPU it was slower (lego 800x800: 203-226 against 254-287 images/s in one process); on a 2-core CPU two workers
    beat one process only once their ~7-s start is paid (6.8 against 5.1 images/s after it; BENCHMARKS.md)."""
    gpu = device is not None and torch.device(device).type == "cuda"
    return sources >= RAY_DATA_MIN_SOURCES and gpu and torch.cuda.device_count() > 1


def scan(inputs: Sequence[str | os.PathLike], marks: Sequence, *, fpr: float = DETECTION_FPR,
         device: torch.device | None = None, frames: int = 16, use_ray: bool | None = None,
         address: str | None = None, workers: int | None = None, batch_size: int | None = None,
         readers: int = DEFAULT_READERS, on_row: Callable[[ScanRow], None] | None = None,
         progress: bool = False, times: list[StageTimes] | None = None) -> list[ScanRow]:
    """Tests every image and video found in ``inputs`` against the registered marks.

    Args:
        inputs: files, folders (searched recursively) and glob patterns.
        marks: the registered marks.
        fpr: family-wise false-positive rate per source.
        device: where to decode (None: the CPU).
        frames: frames read per video.
        use_ray: True: Ray Data; False: this process; None: Ray Data when installed and either an ``address``
            is given or :func:`ray_by_default` holds.
        address: a Ray cluster to join.
        workers: Ray Data workers (default: one per CPU, or per GPU on CUDA).
        batch_size: images per decoder call (in this process and in every Ray worker); None:
            :data:`DEFAULT_BATCH_SIZES` of ``device``.
        readers: threads reading sources (in this process and in every Ray worker).
        on_row: called with each source's row as it is finished (in input order in this process; with Ray, in the
            order the workers' calls return, a call's rows at a time).
        progress: a progress bar over the sources on stderr (:class:`gsw.progress.Progress`).
        times: gets one :class:`StageTimes` per pipeline run (this process: one; Ray: one per worker call), for
            benchmarks.

    Returns:
        One :class:`ScanRow` per source, in input order.

    Raises:
        ValueError: no marks; nothing to scan; ``batch_size`` or ``readers`` < 1.
        ImportError: Ray asked for (``use_ray`` or ``address``) but not installed.
    """
    if not marks:
        raise ValueError("the registry holds no marks")
    from gsw.io.video import expand_inputs

    batch_size = _batching(batch_size, readers, device)
    paths = expand_inputs(inputs)
    want_ray = use_ray if use_ray is not None else bool(address) or ray_by_default(len(paths), device)
    if want_ray and not _ray_data_available():
        if use_ray or address:
            raise ImportError("scanning on Ray needs Ray Data (ray[data], with pandas and pyarrow): install the Ray "
                              "extra (pip install gsw[ray])")
        want_ray = False
    from gsw.progress import Progress

    with Progress(len(paths), "scan", enabled=progress) as bar:
        def done(row: ScanRow) -> None:
            bar.update(1)
            if on_row is not None:
                on_row(row)

        if want_ray:
            gpu = device is not None and torch.device(device).type == "cuda"
            return _scan_ray(paths, marks, fpr=fpr, frames=frames, gpu=gpu, address=address, workers=workers,
                             batch_size=batch_size, readers=readers, on_row=done, times=times)
        st = None if times is None else StageTimes()
        rows = scan_sources(paths, marks, fpr=fpr, device=device, frames=frames, batch_size=batch_size,
                            readers=readers, on_row=done, times=st)
    if st is not None:
        times.append(st)
    return rows
