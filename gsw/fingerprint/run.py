"""Running recipient batches: in this process, or on Ray workers of a local or remote Ray cluster.

Both runners call ``on_result`` in the calling process (the driver) for every finished batch: the one
writer of output folders and registry records. :class:`RayWorkers` is the generic part: a pool of Ray
actors (``num_gpus`` / ``num_cpus`` each) started before the work exists, so that their start overlaps the
driver's set-up, then fed one payload per free worker; a payload whose worker dies runs again (up to
``max_retries`` times). Ray is optional (``pip install gsw[ray]``); :func:`ray_available` says whether it is
installed.
"""

from __future__ import annotations

import contextlib
import importlib.util
import time
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import torch

if TYPE_CHECKING:
    from gsw.fingerprint.stopping import EarlyStop

__all__ = ["SCALE_OUT_HINT", "BatchFailure", "RayWorkers", "connect_ray", "ray_available", "ray_workers", "run_batch",
           "run_local", "run_ray"]

#: What to tell a user who runs without Ray.
SCALE_OUT_HINT = ("Ray is not installed: running in one process. To spread recipients over several GPUs or "
                  "machines, install the Ray extra (pip install gsw[ray]) and pass --address to join a cluster")


class BatchFailure(RuntimeError):
    """Some batches failed (after their retries); the others were written."""


def ray_available() -> bool:
    """Whether Ray can be imported."""
    return importlib.util.find_spec("ray") is not None


def run_batch(shared, batch: Sequence[tuple[str, str, bool]], device: str, on_step: Callable[[int], None] | None = None,
              *, slots: int | None = None, stop: EarlyStop | None = None,
              on_copy: Callable[[Any], None] | None = None) -> list:
    """Fine-tunes recipients in a pool of ``slots`` slots on ``device`` (the body of a task).

    Args:
        shared: the :class:`~gsw.fingerprint.shared.SharedScene`.
        batch: (recipient, hex message, whether ``stop`` may redraw the message) triples.
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
            copy.worker_setup_s, copy.worker_warm_s = setup_s, scene.warm_s
            if on_copy is not None:
                on_copy(copy)

        messages = torch.stack([message_from_hex(m, shared.num_bits) for _, m, _ in batch])
        return finetune_batch(scene, [n for n, _, _ in batch], messages, on_step, slots=slots, stop=stop,
                              on_copy=with_setup, redrawable=[r for _, _, r in batch])


def run_local(shared, batches: Sequence[Sequence[tuple[str, str, bool]]], device: str,
              on_result: Callable[[list], None], on_step: Callable[[int], None] | None = None, *,
              slots: int | None = None, stop: EarlyStop | None = None) -> None:
    """Runs every recipient of ``batches`` through one pool of ``slots`` slots in this process; each copy
    is handed to ``on_result`` (as a one-element list) as soon as it is finished."""
    recipients = [r for batch in batches for r in batch]
    run_batch(shared, recipients, device, on_step, slots=slots or max(len(b) for b in batches), stop=stop,
              on_copy=lambda copy: on_result([copy]))


def _ray_task(shared, batch, device, slots=None, stop=None):  # pragma: no cover - runs in a Ray worker
    return run_batch(shared, batch, _worker_device(device), slots=slots, stop=stop)


def _worker_device(device: str) -> str:
    return "cuda" if device.startswith("cuda") else device  # Ray sets CUDA_VISIBLE_DEVICES to the worker's GPU


def _warm(token, original, cameras, config, num_bits, decoder, device):  # pragma: no cover - in a Ray worker
    from gsw.device import deterministic
    from gsw.fingerprint.shared import warm_worker

    with deterministic():
        warm_worker(token, original, cameras, config, num_bits, decoder, _worker_device(device))


class _Worker:  # pragma: no cover - a Ray actor
    """One process holding its resources (a GPU) for the whole job: warms up (its first call, and again after a
    restart), then runs payloads. Its constructor takes no arguments: Ray cannot restart an actor whose
    constructor arguments left the object store (ray-project/ray#53727)."""

    def warm(self, fn: Callable[..., Any], *args: Any) -> None:
        fn(*args)

    def run(self, fn: Callable[..., Any], shared: Any, payload: Any, args: Sequence[Any]) -> Any:
        return fn(shared, payload, *args)


def _actor_died(err: BaseException) -> bool:
    import ray.exceptions

    return isinstance(err, ray.exceptions.RayActorError)


class RayWorkers:
    """A pool of Ray actors (``num_gpus`` / ``num_cpus`` each) on the connected cluster, started at once so that
    their start (process, imports, CUDA, then ``warm(*warm_args)``, each worker's first call) overlaps what the
    caller does next; then :meth:`map` hands out payloads to whichever worker is free.

    A worker whose process dies is restarted by Ray (up to ``max_retries`` times; ``warm`` runs again first) and
    the payload it held is run again (up to ``max_retries`` times per payload); a payload that raises is not
    run again. ``shutdown`` ends the workers.
    """

    def __init__(self, count: int, *, num_gpus: float = 0.0, num_cpus: float = 1.0, max_retries: int = 3,
                 warm: Callable[..., Any] | None = None, warm_args: Sequence[Any] = ()) -> None:
        import ray

        if count < 1:
            raise ValueError(f"a pool needs at least one worker, got {count}")
        self.max_retries = max_retries
        actor = ray.remote(_Worker).options(num_gpus=num_gpus, num_cpus=num_cpus, max_restarts=max_retries,
                                            max_task_retries=0)
        self._warm = warm
        self._refs = [ray.put(a) for a in warm_args]  # stored once, read by every worker (and its restarts)
        self.actors = [actor.remote() for _ in range(count)]
        for a in self.actors:
            self._warm_up(a)

    def _warm_up(self, actor: Any) -> None:
        """Queues ``warm(*warm_args)`` on ``actor``, ahead of any payload sent to it later (an actor runs its
        calls in order). Its result is not awaited: ``warm`` only prepares what the payloads would otherwise
        build themselves, so one that raises (Ray logs it) costs time, not results; one whose worker dies fails
        that worker's next payload, which :meth:`map` runs again."""
        if self._warm is not None:
            actor.warm.remote(self._warm, *self._refs)

    @staticmethod
    def capacity(num_gpus: float, num_cpus: float) -> int:
        """How many workers of this size the connected cluster holds now (0: none fits)."""
        import ray

        res = ray.cluster_resources()
        return int(res.get("GPU", 0.0) // num_gpus) if num_gpus > 0 else int(res.get("CPU", 0.0) // num_cpus)

    def map(self, fn: Callable[..., Any], shared: Any, payloads: Sequence[Any],
            on_result: Callable[[int, Any], None], args: Sequence[Any] = ()) -> list[tuple[int, BaseException]]:
        """Runs ``fn(shared, payload, *args)`` on the workers, one payload per free worker; ``shared`` goes
        into the object store once; ``on_result(index, result)`` runs here as results arrive.

        Returns:
            (index, error) of the payloads that failed.
        """
        import ray

        shared_ref = ray.put(shared)
        queue = list(range(len(payloads)))
        runs: dict[int, int] = {}  # payload -> times started
        deaths = {id(a): 0 for a in self.actors}
        idle, running, failed = list(self.actors), {}, []
        while queue or running:
            while idle and queue:
                a, i = idle.pop(0), queue.pop(0)
                runs[i] = runs.get(i, 0) + 1
                running[a.run.remote(fn, shared_ref, payloads[i], tuple(args))] = (a, i)
            if not running:  # every worker is gone
                failed += [(i, RuntimeError("no Ray worker left: each died more than max_retries times"))
                           for i in queue]
                break
            done, _ = ray.wait(list(running), num_returns=1)
            a, i = running.pop(done[0])
            try:
                result = ray.get(done[0])
            except Exception as err:  # noqa: BLE001 - the payload raised, or its worker died
                if _actor_died(err):
                    deaths[id(a)] += 1
                    if runs[i] <= self.max_retries:
                        queue.insert(0, i)
                    else:
                        failed.append((i, err))
                    if deaths[id(a)] <= self.max_retries:
                        self._warm_up(a)  # runs once Ray has restarted it
                        idle.append(a)
                else:
                    failed.append((i, err))
                    idle.append(a)
                continue
            idle.append(a)
            on_result(i, result)
        return sorted(failed, key=lambda f: f[0])

    def shutdown(self) -> None:
        import ray

        for a in self.actors:
            ray.kill(a)
        self.actors = []


def _pool_size(payloads: int, num_gpus: float, num_cpus: float) -> int:
    """Workers for ``payloads``: as many as the connected cluster holds, at most one per payload."""
    import ray

    fits = RayWorkers.capacity(num_gpus, num_cpus)
    if fits < 1:
        what = f"{num_gpus} GPU (use --device cpu, or a cluster with GPUs)" if num_gpus > 0 else f"{num_cpus} CPU"
        raise RuntimeError(f"the Ray cluster has no room for a worker of {what}; its resources: "
                           f"{ray.cluster_resources()}")
    return max(1, min(payloads, fits))


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


@contextlib.contextmanager
def ray_workers(address: str | None, device: str, batches: int, *, gpus_per_task: float = 1.0,
                max_retries: int = 3, warm_args: Sequence[Any] | None = None) -> Iterator[RayWorkers]:
    """Connects to Ray (``address``, or a new local cluster) and starts the job's workers: one per GPU share
    (``gpus_per_task``) on CUDA, one per CPU otherwise, at most ``batches``; each runs
    :func:`~gsw.fingerprint.shared.warm_worker` with ``warm_args`` (token, original model, cameras, config,
    bits, decoder) as it starts. Ends the workers (and a cluster it started) on exit.

    Raises:
        RuntimeError: the cluster has no room for one worker.
    """
    import ray

    started = connect_ray(address)
    try:
        num_gpus = gpus_per_task if device.startswith("cuda") else 0.0
        workers = RayWorkers(_pool_size(batches, num_gpus, 1.0), num_gpus=num_gpus, num_cpus=1.0,
                             max_retries=max_retries, warm=None if warm_args is None else _warm,
                             warm_args=() if warm_args is None else (*warm_args, device))
        try:
            yield workers
        finally:
            workers.shutdown()
    finally:
        if started:
            ray.shutdown()


def run_ray(workers: RayWorkers, shared, batches: Sequence[Sequence[tuple[str, str, bool]]], device: str,
            on_result: Callable[[list], None], *, slots: int | None = None, stop: EarlyStop | None = None) -> None:
    """Runs the batches on ``workers`` (:func:`ray_workers`), each a pool of ``slots`` slots (default: the
    batch's size) with the early-stopping rule ``stop``.

    Raises:
        BatchFailure: batches that failed after their retries (the others were handed to ``on_result``).
    """
    failed = workers.map(_ray_task, shared, batches, lambda _i, res: on_result(res), args=(device, slots, stop))
    if failed:
        names = [n for i, _ in failed for n, _m, _r in batches[i]]
        raise BatchFailure(f"{len(failed)} batch(es) failed ({', '.join(names)}): {failed[0][1]}; rerun the same "
                           "command to finish them (finished recipients are skipped)")
