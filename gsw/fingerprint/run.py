"""Running recipient batches: in this process, or as Ray tasks on a local or remote Ray cluster.

Both runners call ``on_result`` in the calling process (the driver) for every finished batch: the one
writer of output folders and registry records. :func:`map_ray` is the generic part: one Ray task per
payload (``num_gpus`` / ``num_cpus`` each, retried up to ``max_retries`` times when its worker dies), results
handled as they arrive. Ray is optional (``pip install gsw[ray]``); :func:`ray_available` says whether it
is installed.
"""

from __future__ import annotations

import importlib.util
import time
from typing import TYPE_CHECKING, Any, Callable, Sequence

import torch

if TYPE_CHECKING:
    from gsw.fingerprint.stopping import EarlyStop

__all__ = ["SCALE_OUT_HINT", "BatchFailure", "connect_ray", "ray_available", "map_ray", "run_batch", "run_local", "run_ray"]

#: What to tell a user who runs without Ray.
SCALE_OUT_HINT = ("Ray is not installed: running in one process. To spread recipients over several GPUs or "
                  "machines, install the Ray extra (pip install gsw[ray]) and pass --address to join a cluster")


class BatchFailure(RuntimeError):
    """Some batches failed (after their retries); the others were written."""


def ray_available() -> bool:
    """Whether Ray can be imported."""
    return importlib.util.find_spec("ray") is not None


def run_batch(shared, batch: Sequence[tuple[str, str]], device: str, on_step: Callable[[int], None] | None = None,
              *, slots: int | None = None, stop: EarlyStop | None = None,
              on_copy: Callable[[Any], None] | None = None) -> list:
    """Fine-tunes recipients in a pool of ``slots`` slots on ``device`` (the body of a task).

    Args:
        shared: the :class:`~gsw.fingerprint.shared.SharedScene`.
        batch: (recipient, hex message) pairs.
        device: torch device.
        on_step: progress callback (local runs).
        slots: recipients fine-tuned together (default: all of ``batch``).
        stop: a :class:`~gsw.fingerprint.stopping.EarlyStop`, or None.
        on_copy: called with each finished copy.

    Returns:
        Their :class:`~gsw.fingerprint.batched.CopyResult`, in order (models on the CPU).
    """
    from gsw.device import deterministic
    from gsw.fingerprint.batched import finetune_batch
    from gsw.fingerprint.shared import worker_scene
    from gsw.mark.message import message_from_hex

    with deterministic():  # a copy is the same bits whichever worker and GPU makes it
        t0 = time.perf_counter()
        scene = worker_scene(shared, device)
        setup_s = time.perf_counter() - t0

        def with_setup(copy):
            copy.worker_setup_s = setup_s
            if on_copy is not None:
                on_copy(copy)

        messages = torch.stack([message_from_hex(m, shared.num_bits) for _, m in batch])
        return finetune_batch(scene, [n for n, _ in batch], messages, on_step, slots=slots, stop=stop,
                              on_copy=with_setup)


def run_local(shared, batches: Sequence[Sequence[tuple[str, str]]], device: str,
              on_result: Callable[[list], None], on_step: Callable[[int], None] | None = None, *,
              slots: int | None = None, stop: EarlyStop | None = None) -> None:
    """Runs every recipient of ``batches`` through one pool of ``slots`` slots in this process; each copy
    is handed to ``on_result`` (as a one-element list) as soon as it is finished."""
    recipients = [r for batch in batches for r in batch]
    run_batch(shared, recipients, device, on_step, slots=slots or max(len(b) for b in batches), stop=stop,
              on_copy=lambda copy: on_result([copy]))


def _ray_task(shared, batch, device, slots=None, stop=None):  # pragma: no cover - runs in a Ray worker
    if device.startswith("cuda"):
        device = "cuda"  # Ray sets CUDA_VISIBLE_DEVICES to the task's GPU
    return run_batch(shared, batch, device, slots=slots, stop=stop)


def map_ray(fn: Callable[..., Any], shared: Any, payloads: Sequence[Any], on_result: Callable[[int, Any], None], *,
            num_gpus: float = 0.0, num_cpus: float = 1.0, max_retries: int = 3,
            args: Sequence[Any] = ()) -> list[tuple[int, BaseException]]:
    """Runs ``fn(shared, payload, *args)`` as one Ray task per payload on the connected Ray cluster.

    ``shared`` is put into the object store once. ``on_result(index, result)`` runs in this process as
    results arrive (in completion order). A task whose worker process dies is retried up to ``max_retries``
    times by Ray; a task that raises is not retried.

    Args:
        fn: a picklable function.
        shared: the common argument.
        payloads: one per task.
        on_result: the single writer.
        num_gpus, num_cpus: resources of each task.
        max_retries: retries after a worker failure.
        args: further arguments of every call.

    Returns:
        (index, error) of the tasks that failed.
    """
    import ray

    task = ray.remote(fn).options(num_gpus=num_gpus, num_cpus=num_cpus, max_retries=max_retries,
                                  retry_exceptions=False)
    shared_ref = ray.put(shared)
    pending = {task.remote(shared_ref, p, *args): i for i, p in enumerate(payloads)}
    failed = []
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        index = pending.pop(done[0])
        try:
            result = ray.get(done[0])
        except Exception as err:  # a task that raised, or died more than max_retries times
            failed.append((index, err))
            continue
        on_result(index, result)
    return failed


def connect_ray(address: str | None, **init_kwargs: Any) -> bool:
    """Connects to Ray unless already connected: ``address`` (a cluster) or a new local cluster.

    Returns:
        Whether this call started the connection (then the caller shuts it down).
    """
    import ray

    if ray.is_initialized():
        return False
    ray.init(address=address, include_dashboard=False, log_to_driver=False, **init_kwargs)
    return True


def run_ray(shared, batches: Sequence[Sequence[tuple[str, str]]], device: str, on_result: Callable[[list], None], *,
            address: str | None = None, gpus_per_task: float = 1.0, max_retries: int = 3, slots: int | None = None,
            stop: EarlyStop | None = None) -> None:
    """Runs the batches as Ray tasks (``num_gpus=gpus_per_task`` each on a CUDA device), each a pool of
    ``slots`` slots (default: the batch's size) with the early-stopping rule ``stop``.

    Raises:
        BatchFailure: batches that failed after their retries (the others were handed to ``on_result``).
    """
    import ray

    started = connect_ray(address)
    try:
        gpu = device.startswith("cuda")
        failed = map_ray(_ray_task, shared, batches, lambda _i, res: on_result(res),
                         num_gpus=gpus_per_task if gpu else 0.0, num_cpus=1.0, max_retries=max_retries,
                         args=(device, slots, stop))
    finally:
        if started:
            ray.shutdown()
    if failed:
        names = [n for i, _ in failed for n, _m in batches[i]]
        raise BatchFailure(f"{len(failed)} batch(es) failed ({', '.join(names)}): {failed[0][1]}; rerun the same "
                           "command to finish them (finished recipients are skipped)")
