"""The once-per-scene work of a fingerprinting job, done once and shared by every recipient.

:func:`prepare_scene` (on the driver) checks the model, runs FGD and identifies the decoder
(:func:`gsw.mark.embed.prepare_embedding`); the result, a :class:`SharedScene` of CPU tensors, travels to
the workers (a Ray object). :func:`worker_scene` turns it, once per worker process and device, into a
:class:`WorkerScene`: the models and original renders on the device and the loss with its decoder and
LPIPS network, reused by every recipient batch that worker runs.
"""

from __future__ import annotations

import hashlib
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Sequence

import torch
from torch import Tensor

from gsw.camera import Camera
from gsw.fingerprint.batched import References, check_pool_config, pool_config
from gsw.gaussians import Gaussians
from gsw.mark.embed import EmbedConfig, ViewBank, prepare_embedding
from gsw.registry import mark_decoder_sha256

__all__ = ["SharedScene", "WorkerScene", "prepare_scene", "scene_hash", "warm_worker", "worker_scene"]


def scene_hash(gaussians: Gaussians, cameras: Sequence[Camera], num_bits: int, config: EmbedConfig,
               images: Sequence[Tensor] | None = None) -> str:
    """``"scene-sha256:<hex>"`` of what makes two jobs' copies interchangeable: the model's tensors
    (:func:`gsw.registry.hash_gaussians`), the cameras, the message length, the embedding settings and the
    training images given to FGD (or their absence: FGD prunes differently with and without them)."""
    from gsw.registry import hash_gaussians

    h = hashlib.sha256(hash_gaussians(gaussians).encode())
    for cam in cameras:
        h.update(cam.viewmat.detach().double().cpu().numpy().tobytes())
        h.update(repr((float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), int(cam.width),
                       int(cam.height))).encode())
    h.update(f"bits={int(num_bits)};config={config!r}".encode())
    if images is not None:
        h.update(b"images")
        for im in images:
            h.update(repr(tuple(im.shape)).encode())
            h.update(im.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return f"scene-sha256:{h.hexdigest()}"


@dataclass
class SharedScene:
    """The per-scene part of a job, as CPU tensors (picklable, sent to every worker).

    Attributes:
        original: the input model.
        model: the model after FGD, the starting point of every recipient's fine-tune.
        cameras: the embedding views.
        config: the embedding settings.
        num_bits: message length.
        decoder: a custom decoder, or None for the shipped one.
        scene_hash: :func:`scene_hash`.
        decoder_sha256: :func:`decoder_sha256`.
        stats: Gaussian counts and the set-up timings (recorded in each copy's ``watermark.json``).
        token: unique per :func:`prepare_scene` call: a worker reuses its prepared scene only for the same job
            (two jobs of one model may differ in what FGD made of it).
    """

    original: Gaussians
    model: Gaussians
    cameras: list[Camera]
    config: EmbedConfig
    num_bits: int
    decoder: torch.nn.Module | None
    scene_hash: str
    decoder_sha256: str
    stats: dict[str, Any] = field(default_factory=dict)
    token: str = field(default_factory=lambda: uuid.uuid4().hex)


def prepare_scene(gaussians: Gaussians, cameras: Sequence[Camera], *, num_bits: int = 32,
                  config: EmbedConfig | None = None, images: Sequence[Tensor] | None = None,
                  decoder: torch.nn.Module | None = None, device: str | torch.device | None = None,
                  token: str | None = None) -> SharedScene:
    """Runs the once-per-scene work (checks, FGD) on ``device`` and returns it as a :class:`SharedScene`.

    Args:
        gaussians: the trained model (not modified).
        cameras: its training views.
        num_bits: message length.
        config: embedding settings (:class:`~gsw.mark.embed.EmbedConfig`).
        images: optional [3, H, W] training images for FGD phase 1.
        decoder: a custom decoder (default: the shipped one).
        device: where to run FGD (default: where the model is).
        token: the scene's :attr:`SharedScene.token` (default: a new one); the token given to
            :func:`warm_worker` before, so that workers use what they prepared.

    Raises:
        ValueError: as :func:`gsw.mark.embed.prepare_embedding`.
    """
    cfg = config or pool_config()
    check_pool_config(cfg)
    g = gaussians.detach().to(device) if device is not None else gaussians.detach()
    imgs = None if images is None else [im.to(g.device) for im in images]
    setup = prepare_embedding(g, cameras, num_bits=num_bits, images=imgs, config=cfg, decoder=decoder)
    stats = dict(gaussians_in=len(g), gaussians_out=len(setup.model),
                 pruned=setup.prune.num_removed if setup.prune else 0,
                 split=setup.split.num_split if setup.split else 0, setup_timings=setup.timings)
    return SharedScene(gaussians.detach().to("cpu"), setup.model.to("cpu"), list(cameras), cfg, num_bits,
                       None if decoder is None else decoder.to("cpu"),
                       scene_hash(gaussians, cameras, num_bits, cfg, images), mark_decoder_sha256(num_bits, decoder),
                       stats, token or uuid.uuid4().hex)


@dataclass
class WorkerScene:
    """A :class:`SharedScene` ready to fine-tune on one device.

    Attributes:
        shared: the scene.
        device: where it lives.
        model: the FGD'd model on ``device``.
        originals: per camera, the [3, H, W] render of the input model.
        loss: the watermark loss (decoder + LPIPS) on ``device``.
        warm_s: seconds :func:`warm_worker` took to make ``originals`` and ``loss`` (0: made with the scene).
        bank: the input model on ``device`` and the job's bank of sampled viewpoints (``EmbedConfig.view_bank``;
            none without one); view ``len(cameras) + b`` is bank viewpoint ``b``, and after them come the probes
            (:meth:`probe_views`).
    """

    shared: SharedScene
    device: torch.device
    model: Gaussians
    originals: list[Tensor]
    loss: torch.nn.Module
    bank: ViewBank
    warm_s: float = 0.0
    _references: dict[int, References] = field(default_factory=dict, repr=False)
    _held_bytes: int = field(default=0, repr=False)
    _probes: list[tuple[Camera, Tensor]] = field(default_factory=list, repr=False)

    def camera(self, v: int) -> Camera:
        """View ``v``'s camera: an embedding view, beyond them a bank viewpoint, then a probe."""
        n, b = len(self.shared.cameras), len(self.bank)
        return self.shared.cameras[v] if v < n else self.bank.cameras[v - n] if v < n + b else \
            self._probes[v - n - b][0]

    def original(self, v: int) -> Tensor:
        """[3, H, W] the input model's render of view ``v`` (a bank viewpoint's is made on first use and kept)."""
        n, b = len(self.originals), len(self.bank)
        return self.originals[v] if v < n else self.bank.render(v - n) if v < n + b else self._probes[v - n - b][1]

    def probe_views(self, count: int) -> list[int]:
        """The view indices of ``count`` probes: viewpoints in the gaps between neighbouring embedding views
        (:func:`gsw.mark.views.gap_views`, seeded from the config's seed, drawn from the embedding cameras alone),
        drawn and rendered (input model) once per worker and job.

        Raises:
            ValueError: fewer than 2 embedding views.
        """
        from gsw.mark.views import gap_views
        from gsw.render.rasterize import rasterize

        first = len(self.shared.cameras) + len(self.bank)
        if len(self._probes) != count:
            cfg = self.shared.config
            cams = gap_views(self.bank.original, self.shared.cameras, count, seed=cfg.seed + 4,
                             max_side=cfg.max_render_side)
            with torch.no_grad():
                self._probes = [(c, rasterize(self.bank.original, c, background=cfg.background).image) for c in cams]
            for v in [v for v in self._references if v >= first]:  # older probes' go
                self._held_bytes -= _nbytes(self._references.pop(v))
        return list(range(first, first + count))

    def references(self, views: Sequence[int | Tensor]) -> References:
        """The loss's :class:`~gsw.fingerprint.batched.References` of ``views``' original renders, stacked in the
        order given: their wavelet detail subbands and LPIPS features (:meth:`gsw.metrics.lpips.LPIPS.references`;
        None without an LPIPS term). A view is an index (:meth:`original`: an embedding view or a bank viewpoint),
        or a [3, H, W] original render of a freshly sampled viewpoint, whose references are made for this call only.

        An indexed view's are made once and kept while the kept ones fit in :func:`reference_budget` (800x800
        with AlexNet: ~33 MB per view); beyond that they are made again per call.
        """
        per_view = []
        for v in views:
            if isinstance(v, Tensor):
                per_view.append(self._image_references(v))
                continue
            refs = self._references.get(v)
            if refs is None:
                refs = self._image_references(self.original(v))
                size = _nbytes(refs)
                if self._held_bytes + size <= reference_budget(self.device):
                    self._references[v] = refs
                    self._held_bytes += size
            per_view.append(refs)
        highs = [tuple(torch.cat(bands) for bands in zip(*levels)) for levels in zip(*(r.highs for r in per_view))]
        lpips = None if per_view[0].lpips is None else [torch.cat(taps) for taps in zip(*(r.lpips for r in per_view))]
        return References(highs, lpips)

    @torch.no_grad()
    def _image_references(self, image: Tensor) -> References:
        from gsw.decoder.dwt import dwt2

        lpips = self.loss.lpips
        return References(dwt2(image[None])[1], None if lpips is None else lpips.references(image[None]))


def _nbytes(refs: References) -> int:
    """Bytes held by one view's :class:`~gsw.fingerprint.batched.References`."""
    held = [t for level in refs.highs for t in level] + (refs.lpips or [])
    return sum(t.numel() * t.element_size() for t in held)


#: Most bytes of :class:`~gsw.fingerprint.batched.References` a :class:`WorkerScene` keeps for all its views (on a
#: GPU at most an eighth of its memory).
REFERENCE_BYTES = 16 << 30


def reference_budget(device: torch.device) -> int:
    """Bytes of references a :class:`WorkerScene` on ``device`` keeps: :data:`REFERENCE_BYTES`, on a GPU at most an
    eighth of its memory (an H200: ~17 GB; a 24-GB GPU: 3 GB), on the CPU at most 4 GiB."""
    if device.type == "cuda":
        return min(REFERENCE_BYTES, torch.cuda.get_device_properties(device).total_memory // 8)
    return min(REFERENCE_BYTES, 4 << 30)

_CACHE: dict[tuple[str, str], WorkerScene] = {}
#: Warmed parts (original renders, loss, seconds taken) by (job token, device), made before the job's scene exists.
_WARM: dict[tuple[str, str], tuple[list[Tensor], torch.nn.Module, float]] = {}


def _parts(original: Gaussians, cameras: Sequence[Camera], config: EmbedConfig, num_bits: int,
           decoder: torch.nn.Module | None, device: torch.device) -> tuple[list[Tensor], torch.nn.Module]:
    """The device-side parts that need only the input model: its renders and the loss (decoder + LPIPS)."""
    from gsw.decoder.hidden import fold_batchnorm
    from gsw.mark.detect import load_decoder_for
    from gsw.mark.loss import WatermarkLoss
    from gsw.render.rasterize import rasterize

    original = original.to(device)
    with torch.no_grad():
        originals = [rasterize(original, cam, background=config.background).image for cam in cameras]
    dec = fold_batchnorm(load_decoder_for(num_bits, decoder, device))  # one kernel fewer per block, per step
    loss = WatermarkLoss(dec, config.weights, config.lpips_net, config.logit_scale).to(device)
    return originals, loss


def warm_worker(token: str, original: Gaussians, cameras: Sequence[Camera], config: EmbedConfig, num_bits: int,
                decoder: torch.nn.Module | None, device: str | torch.device) -> None:
    """Prepares, in a worker process, what :func:`worker_scene` will need for job ``token`` that does not
    depend on FGD (the input model's renders, the decoder, LPIPS; CUDA started): run while the driver
    prepares the scene, so that a worker's start overlaps the set-up instead of following it.

    Args:
        token: the :attr:`SharedScene.token` the job's scene will carry.
        original: the input model (the job's :attr:`SharedScene.original`).
        cameras, config, num_bits, decoder: as the job's :func:`prepare_scene`.
        device: the worker's device.
    """
    t0 = time.perf_counter()
    device = torch.device(device)
    _WARM.clear()
    parts = _parts(original, cameras, config, num_bits, decoder, device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    _WARM[(token, str(device))] = (*parts, time.perf_counter() - t0)


def worker_scene(shared: SharedScene, device: str | torch.device) -> WorkerScene:
    """The :class:`WorkerScene` of ``shared`` on ``device``, built once per job (:attr:`SharedScene.token`) and
    device in a process (from :func:`warm_worker`'s parts when it ran), and reused by the job's later
    batches there.

    Args:
        shared: the scene.
        device: a torch device.
    """
    device = torch.device(device)
    key = (shared.token, str(device))
    if key not in _CACHE:
        _CACHE.clear()  # one scene at a time per worker
        warmed = _WARM.pop(key, None)
        _WARM.clear()
        originals, loss, warm_s = warmed if warmed is not None else (
            *_parts(shared.original, shared.cameras, shared.config, shared.num_bits, shared.decoder, device), 0.0)
        bank = ViewBank(shared.original.to(device), shared.cameras, shared.config)
        _CACHE[key] = WorkerScene(shared, device, shared.model.to(device), originals, loss, bank, warm_s)
    return _CACHE[key]
