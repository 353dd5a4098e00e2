""":func:`fingerprint`: one watermarked copy per recipient of one scene, registered, resumable.

Flow: check the recipients, the output folder (:class:`~gsw.fingerprint.store.JobFolder`) and the registry
before any work; skip finished recipients; run the once-per-scene work (FGD) once
(:func:`~gsw.fingerprint.shared.prepare_scene`; on Ray the workers start and warm up meanwhile); fine-tune the
others in a pool of slots (:mod:`gsw.fingerprint.batched`) in this process or on Ray workers
(:mod:`gsw.fingerprint.run`); for every finished copy, in this process: write its folder atomically (on
writer threads while the fine-tunes go on), register it, then write its completion marker.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.fingerprint.plan import Recipient, assign_messages, check_messages, check_recipients, read_recipients
from gsw.fingerprint.stopping import EarlyStop
from gsw.gaussians import Gaussians
from gsw.fingerprint.batched import check_pool_config, pool_config
from gsw.mark.embed import EmbedConfig, check_config

__all__ = ["RecipientReport", "FingerprintReport", "fingerprint"]

#: Threads writing copies (a copy is a few hundred ms of PLY encoding, file writes and fsyncs, most of it
#: outside the GIL: with one thread the copies of the last batches wait in line at the end of a job).
WRITER_THREADS = min(8, os.cpu_count() or 1)


@dataclass
class RecipientReport:
    """What happened to one recipient (no message).

    Attributes:
        name: the recipient.
        status: "embedded" (this run), "skipped" (finished earlier) or "completed" (only its marker was missing).
        folder: its model folder.
        mark_id: its registry id.
        bit_accuracy, min_bit_accuracy, psnr, min_psnr: scores on the embedding views (embedded only).
        seconds: its share of its pool's fine-tune time (embedded only).
        steps: its optimisation steps (embedded only).
        stopped_early: whether the early-stopping rule finished it before the step cap (embedded only).
        refusals: early stops refused by the rule's confirmation (embedded only).
        redraws: new messages it got (:attr:`~gsw.fingerprint.stopping.EarlyStop.redraw`; embedded only): then
            its registered message is the last one, of origin "chosen"; the scores and steps are the last
            attempt's.
        redrawn_steps: the steps of its discarded attempts (embedded only).
        finished_s: seconds after the fine-tunes began when its copy reached the writer (embedded only; with
            Ray, a batch's copies arrive together when the batch ends).
        worker_setup_s: seconds its worker spent preparing the scene before its batch (0: cached).
        worker_warm_s: seconds its worker's warm-up took, while the driver ran the set-up (Ray; 0 without).
        probe_bit_accuracy: its mean bit accuracy on the stopping rule's probes (embedded with
            :attr:`~gsw.fingerprint.stopping.EarlyStop.probes` only).
    """

    name: str
    status: str
    folder: str
    mark_id: int | None = None
    bit_accuracy: float | None = None
    min_bit_accuracy: float | None = None
    psnr: float | None = None
    min_psnr: float | None = None
    seconds: float | None = None
    steps: int | None = None
    stopped_early: bool | None = None
    refusals: int | None = None
    redraws: int | None = None
    redrawn_steps: int | None = None
    finished_s: float | None = None
    worker_setup_s: float | None = None
    worker_warm_s: float | None = None
    probe_bit_accuracy: float | None = None


@dataclass
class FingerprintReport:
    """Result of :func:`fingerprint`.

    Attributes:
        recipients: one report per recipient, in input order.
        runner: "ray", "local" or "none" (nothing to do).
        scene_hash: the job's scene hash.
        timings: seconds of "ray_start" (Ray and its workers started; on Ray only) and "setup" (FGD and the
            original renders, on a thread at the same time), "before_finetune" (from the call to the end of both),
            "finetune" (all batches, from there) and "total".
    """

    recipients: list[RecipientReport]
    runner: str
    scene_hash: str
    timings: dict[str, float] = field(default_factory=dict)

    def names(self, status: str) -> list[str]:
        """The recipients with ``status``."""
        return [r.name for r in self.recipients if r.status == status]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no secrets)."""
        return dict(runner=self.runner, scene_hash=self.scene_hash, timings=self.timings,
                    recipients=[asdict(r) for r in self.recipients])


def _recipients(recipients: str | os.PathLike | Sequence[Recipient | str]) -> list[Recipient]:
    if isinstance(recipients, (str, os.PathLike)):
        return read_recipients(recipients)
    return check_recipients([r if isinstance(r, Recipient) else Recipient(str(r)) for r in recipients])


def _check_registered(marks: dict, names: Sequence[str], decoder_sha: str, num_bits: int, path: Any) -> None:
    for name in names:
        m = marks.get(name)
        if m is not None and (m.decoder_sha256 != decoder_sha or m.num_bits != num_bits):
            raise ValueError(f"registry {path}: recipient {name!r} is registered for another decoder "
                             f"({m.num_bits} bits, decoder {m.decoder_sha256[:12]}; this job: {num_bits} bits, "
                             f"{decoder_sha[:12]}); use the registry of this decoder's marks")


def _choose_runner(use_ray: bool | None, address: str | None, batches: int, log: Callable[[str], None]) -> str:
    from gsw.fingerprint.run import SCALE_OUT_HINT, ray_available

    if use_ray is False:
        if address:
            raise ValueError("an address was given but Ray is switched off")
        return "local"
    if not ray_available():
        if use_ray or address:
            raise ImportError(SCALE_OUT_HINT.replace("running in one process. ", ""))
        log(SCALE_OUT_HINT)
        return "local"
    return "ray" if (use_ray or address or batches > 1) else "local"


class _Writer:
    """The one writer: copies, registry records and completion markers.

    Each copy's folder is written (atomically) on background threads (:data:`WRITER_THREADS`) while the
    fine-tunes go on; once written, it is registered and marked complete in the calling thread (the
    registry's), in arrival order, at the next call or at :meth:`flush`. The order per recipient stays:
    folder, registry record, completion marker.
    """

    def __init__(self, folder, registry, shared, record: dict, reports: dict, bar) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.folder, self.registry, self.shared, self.record, self.reports, self.bar = (
            folder, registry, shared, record, reports, bar)
        self.messages: dict[str, str] = {}
        # "random" (drawn, or from a key) / "chosen" (given in the file, or redrawn: kept for being embeddable)
        self.origins: dict[str, str] = {}
        self.pool = ThreadPoolExecutor(max_workers=WRITER_THREADS, thread_name_prefix="gsw-fingerprint-writer")
        self.pending: list = []  # (result, future of its model hash)
        self.started = time.perf_counter()  # reset when the fine-tunes begin
        self.arrived: dict[str, float] = {}

    def _write(self, r) -> str:
        from gsw.cli.metadata import watermark_record

        cams, cfg = self.shared.cameras, self.shared.config
        stats = dict(self.shared.stats, mean_bit_accuracy=r.bit_accuracy, mean_psnr=r.psnr, steps=r.steps)
        rec = watermark_record(num_bits=self.shared.num_bits, background=cfg.background, cameras=cams, config=cfg,
                               stats=stats, decoder=self.record["decoder"],
                               message_origin=self.origins.get(r.name, "chosen"))
        return self.folder.write_copy(r.name, r.gaussians, cams, rec)

    def __call__(self, results: list) -> None:
        from gsw.mark.message import message_to_hex

        now = time.perf_counter() - self.started
        for r in results:
            if r.redraws:
                self.messages[r.name], self.origins[r.name] = message_to_hex(r.message), "chosen"
        self.arrived.update((r.name, now) for r in results)
        self.pending += [(r, self.pool.submit(self._write, r)) for r in results]
        self._register(wait=False)

    def flush(self) -> None:
        """Waits for every copy and registers it; stops the threads."""
        try:
            self._register(wait=True)
        finally:
            self.pool.shutdown(wait=True)

    def _register(self, wait: bool) -> None:
        n = len(self.pending) if wait else next((i for i, (_, f) in enumerate(self.pending) if not f.done()),
                                                 len(self.pending))
        ready, self.pending = self.pending[:n], self.pending[n:]  # arrival order: a written prefix
        if not ready:
            return
        cams, cfg, k = self.shared.cameras, self.shared.config, self.shared.num_bits
        sizes = {(c.width, c.height) for c in cams}
        width, height = next(iter(sizes)) if len(sizes) == 1 else (None, None)
        hashes = [f.result() for _, f in ready]  # re-raises a failed write
        results = [r for r, _ in ready]
        ids = self.registry.add_many([dict(label=r.name, message=self.messages[r.name], num_bits=k,
                                           decoder_sha256=self.shared.decoder_sha256, model_hash=h, width=width,
                                           height=height, background=cfg.background,
                                           origin=self.origins.get(r.name, "chosen"))
                                      for r, h in zip(results, hashes)])
        for r, h, mark_id in zip(results, hashes, ids):
            self.folder.mark_done(r.name, h, mark_id)
            self.reports[r.name] = RecipientReport(r.name, "embedded", str(self.folder.copy_path(r.name)), mark_id,
                                                   r.bit_accuracy, r.min_bit_accuracy, r.psnr, r.min_psnr,
                                                   r.seconds, r.steps, r.stopped_early, r.refusals, r.redraws,
                                                   r.redrawn_steps, self.arrived.get(r.name), r.worker_setup_s,
                                                   r.worker_warm_s, r.probe_bit_accuracy)
        if self.bar is not None:
            self.bar.update(0, recipients=f"{sum(x.status == 'embedded' for x in self.reports.values())}")


def fingerprint(model: Gaussians, cameras: Sequence[Camera], recipients: str | os.PathLike | Sequence[Recipient | str],
                output_dir: str | os.PathLike, registry: Any, *, num_bits: int = 32,
                config: EmbedConfig | None = None, images: Sequence[Tensor] | None = None,
                decoder: torch.nn.Module | None = None, batch_size: int = 4, early_stop: EarlyStop | None = None,
                task_size: int | None = None, device: str | torch.device | None = None,
                use_ray: bool | None = None, address: str | None = None, gpus_per_task: float = 1.0,
                max_retries: int = 3, progress: bool = True,
                log: Callable[[str], None] | None = None) -> FingerprintReport:
    """Writes one watermarked copy of ``model`` per recipient into ``output_dir/<recipient>/`` and registers it.

    Args:
        model: the trained model (not modified).
        cameras: its training views (the embedding views).
        recipients: a recipients CSV file (:mod:`gsw.fingerprint.plan`), or recipients / names.
        output_dir: the job's folder (new, empty, or this scene's earlier job: finished recipients are skipped).
        registry: an open :class:`~gsw.registry.Registry` or a registry file path (created if missing).
        num_bits: message length.
        config: embedding settings (default :func:`~gsw.fingerprint.batched.pool_config`, the paper's recipe; the
            pool refuses what it does not implement, :func:`~gsw.fingerprint.batched.check_pool_config`).
        images: optional training images for FGD phase 1.
        decoder: a custom decoder (default: the shipped one).
        batch_size: recipients fine-tuned together on one device (the slots of a pool: a finished
            recipient's slot is refilled with the next one, :mod:`gsw.fingerprint.batched`).
        early_stop: per-recipient early stopping (:class:`~gsw.fingerprint.stopping.EarlyStop`); None: every
            recipient runs ``config.epochs`` passes over the views. ``gsw fingerprint``'s default is
            ``EarlyStop.parse("quality")``, the measured setting (README).
        task_size: recipients handed to a Ray worker at a time (default: ``batch_size``); in one process all
            recipients go through one pool.
        device: where to compute (default: :func:`gsw.device.resolve_device` "auto").
        use_ray: True: Ray workers; False: this process; None: Ray when installed and there are several
            batches (or an ``address``).
        address: a Ray cluster to join (default: a local Ray cluster).
        gpus_per_task: GPUs per Ray worker on CUDA (default one worker per GPU; 0.5 runs two per GPU).
        max_retries: reruns of a batch whose Ray worker dies (and restarts of a worker).
        progress: show one progress bar for the job (and messages) on stderr.
        log: where messages go (default: stderr when ``progress``).

    Returns:
        A :class:`FingerprintReport`.

    Raises:
        ValueError: malformed recipients, settings the pool or :func:`gsw.mark.embed.check_config` refuses, an
            output folder of another scene, a recipient registered for another decoder or model; nothing is written
            then.
        gsw.fingerprint.run.BatchFailure: batches that failed on Ray after their retries (the rest is written).
    """
    from gsw.device import resolve_device
    from gsw.fingerprint.shared import scene_hash
    from gsw.fingerprint.store import JobFolder
    from gsw.registry import Registry, mark_decoder_sha256, open_registry

    start = time.perf_counter()
    if batch_size < 1 or (task_size is not None and task_size < 1):
        raise ValueError(f"batch_size and task_size must be >= 1, got {batch_size}, {task_size}")
    log = log or ((lambda text: print(f"gsw fingerprint: {text}", file=sys.stderr)) if progress else (lambda _t: None))
    cfg = config or pool_config()
    check_pool_config(cfg)
    check_config(cfg, cameras)
    if early_stop is not None and early_stop.probes and len(cameras) < 2:
        raise ValueError(f"early_stop.probes lie between neighbouring embedding views: give at least 2 cameras, "
                         f"got {len(cameras)}")
    people = _recipients(recipients)
    check_messages(people, num_bits)  # before anything is written
    dev = resolve_device(device if device is not None else "auto")
    dec_sha = mark_decoder_sha256(num_bits, decoder)
    folder = JobFolder(output_dir, scene_hash=scene_hash(model, cameras, num_bits, cfg, images),
                       decoder_sha256=dec_sha, num_bits=num_bits)
    reg = registry if isinstance(registry, Registry) else open_registry(registry)
    try:
        pool = dict(slots=batch_size, stop=early_stop, task_size=task_size or batch_size)
        return _run(model, cameras, people, folder, reg, cfg, num_bits, images, decoder, pool, dev, use_ray,
                    address, gpus_per_task, max_retries, progress, log, start)
    finally:
        if reg is not registry:
            reg.close()


def _run(model, cameras, people, folder, reg, cfg, num_bits, images, decoder, pool, dev, use_ray, address,
         gpus_per_task, max_retries, progress, log, start) -> FingerprintReport:
    """The body of :func:`fingerprint` once the inputs are checked."""
    from gsw.fingerprint.run import ray_workers, run_local, run_ray
    from gsw.fingerprint.shared import prepare_scene
    from gsw.progress import Progress

    marks = {m.label: m for m in reg.list()}
    _check_registered(marks, [p.name for p in people], folder.decoder_sha256, num_bits, reg.path)
    status = {p.name: folder.status(p.name, getattr(marks.get(p.name), "model_hash", None), p.name in marks)
              for p in people}
    folder.claim()
    reports: dict[str, RecipientReport] = {}
    for p in people:
        if status[p.name] != "todo":
            mark = marks[p.name]
            if status[p.name] == "finish":
                folder.mark_done(p.name, mark.model_hash, mark.id)
            reports[p.name] = RecipientReport(p.name, "skipped" if status[p.name] == "done" else "completed",
                                              str(folder.copy_path(p.name)), mark.id)
    todo = assign_messages([p for p in people if status[p.name] == "todo"], num_bits,
                           taken=[m.message_hex for m in marks.values() if m.decoder_sha256 == folder.decoder_sha256])
    timings: dict[str, float] = {}
    runner = "none"
    if todo:
        size = pool["task_size"]
        drawn = {p.name for p in people if p.message is None and p.key is None}  # the stopping rule may redraw these
        batches = [[(r.name, r.message, r.name in drawn) for r in todo[i:i + size]] for i in range(0, len(todo), size)]
        runner = _choose_runner(use_ray, address, len(batches), log)
        with contextlib.ExitStack() as stack:
            token = uuid.uuid4().hex
            workers = None

            def setup() -> Any:
                t0 = time.perf_counter()
                out = prepare_scene(model, cameras, num_bits=num_bits, config=cfg, images=images, decoder=decoder,
                                    device=dev, token=token)
                timings["setup"] = time.perf_counter() - t0
                return out

            # the set-up runs on a thread while Ray starts here and its workers warm up
            with ThreadPoolExecutor(max_workers=1) as background:
                preparing = background.submit(setup)
                if runner == "ray":
                    t0 = time.perf_counter()
                    workers = stack.enter_context(ray_workers(
                        address, dev.type, len(batches), gpus_per_task=gpus_per_task, max_retries=max_retries,
                        warm_args=(token, model.detach().to("cpu"), list(cameras), cfg, num_bits,
                                   None if decoder is None else decoder.to("cpu"))))
                    timings["ray_start"] = time.perf_counter() - t0
                shared = preparing.result()
            timings["before_finetune"] = time.perf_counter() - start
            steps = cfg.epochs * len(cameras)
            with Progress(len(todo) * steps, "fingerprint", enabled=progress) as bar:
                writer = _Writer(folder, reg, shared, {"decoder": _decoder_fingerprint(num_bits, decoder)}, reports,
                                 bar)
                writer.messages = {r.name: r.message for r in todo}
                writer.origins = {p.name: "chosen" if p.message is not None else "random" for p in people}
                t0 = writer.started = time.perf_counter()
                try:
                    if workers is not None:
                        def on_result(results: list) -> None:
                            writer(results)
                            bar.update(len(results) * steps)

                        run_ray(workers, shared, batches, dev.type, on_result, slots=pool["slots"],
                                stop=pool["stop"])
                    else:
                        run_local(shared, batches, str(dev), writer, on_step=bar.update, slots=pool["slots"],
                                  stop=pool["stop"])
                finally:
                    writer.flush()  # the copies finished so far are registered even when a batch failed
                timings["finetune"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    return FingerprintReport([reports[p.name] for p in people], runner, folder.scene_hash, timings)


def _decoder_fingerprint(num_bits: int, decoder: torch.nn.Module | None) -> str:
    """The decoder fingerprint ``watermark.json`` records (:func:`gsw.eval.grid.decoder_fingerprint`)."""
    from gsw.decoder.zoo import load_decoder
    from gsw.eval.grid import decoder_fingerprint

    return decoder_fingerprint(load_decoder(num_bits) if decoder is None else decoder)
