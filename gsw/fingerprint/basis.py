"""A bit basis: one fit per scene that gives every recipient a watermarked starting point.

A pool (:mod:`gsw.fingerprint.batched`) starts each recipient from the same FGD'd model ``theta`` and
fine-tunes it for its message.  A bit basis moves most of that work to a once-per-scene fit: ``k + 1``
parameter offsets ``D_0, D_1 .. D_k`` (``k`` the message length) such that

    ``theta(m) = theta + D_0 + sum_i s_i D_i``,   ``s_i = 2 m_i - 1``,

carries the message ``m`` for *any* ``m``.  :func:`fit_basis` fits them with the watermark loss of
:func:`gsw.mark.embed.embed` (the same decoder, LPIPS, weights, update mask and learning rates) on batches
of uniformly random messages, each rendered from the next embedding view; a recipient then starts from
``theta(m)`` (:meth:`BitBasis.start`) instead of ``theta``, and the pool's early-stopping rule
(:mod:`gsw.fingerprint.stopping`) finishes it as soon as its copy passes the rule's confirmation on the
embedding views -- before any step when the start already does.

The offsets are stored as ``k + 1`` slots of a :class:`~gsw.fingerprint.batched.SlotParams` holding
``theta + D_j`` (so its masked Adam is the pool's), with the slot index ``j`` the component.  The fit draws
its messages from a generator seeded with :attr:`BasisConfig.seed` and its view order from the same seed:
it is deterministic on a device.  Positions stay shared (as in :class:`SlotParams` while
``EmbedConfig.lr_position`` is 0).

Example:
    >>> BasisConfig(steps=600, batch=8)
    BasisConfig(steps=600, batch=8, seed=0)
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from gsw.fingerprint.batched import SlotParams, batched_loss
from gsw.gaussians import Gaussians

__all__ = ["BasisConfig", "BitBasis", "fit_basis", "scene_basis"]

#: The trained parameter tensors of :class:`SlotParams`, by attribute.
_ATTRS = ("dc", "rest", "logits", "log_scales", "quats")


@dataclass(frozen=True)
class BasisConfig:
    """How to fit a :class:`BitBasis`.

    Attributes:
        steps: optimisation steps of the fit.
        batch: random messages per step (each renders the next embedding view).
        seed: seed of the fit's messages and view order.
    """

    steps: int = 600
    batch: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch < 1:
            raise ValueError(f"a bit basis needs steps >= 1 and batch >= 1, got {self.steps}, {self.batch}")

    @classmethod
    def parse(cls, text: str) -> "BasisConfig":
        """``"steps=600,batch=8,seed=0"`` (any subset; ``""``: the defaults) -> :class:`BasisConfig`."""
        values: dict[str, int] = {}
        for token in filter(None, text.split(",")):
            key, sep, value = token.partition("=")
            if not sep or key not in ("steps", "batch", "seed"):
                raise ValueError(f"bad bit-basis setting {token!r} (keys: steps, batch, seed)")
            try:
                values[key] = int(value)
            except ValueError:
                raise ValueError(f"bit-basis setting {key} needs an integer, got {value!r}") from None
        return cls(**values)


class BitBasis:
    """``k + 1`` offsets of a model's trained parameters (see the module docstring).

    Args:
        model: the starting model ``theta`` (the FGD'd model of the scene).
        num_bits: ``k``.
        config: the embedding settings (learning rates, mask kind).
    """

    def __init__(self, model: Gaussians, num_bits: int, config) -> None:
        self.num_bits = num_bits
        self.params = SlotParams(model, num_bits + 1, config)

    def combine(self, signs: Tensor) -> dict[str, Tensor]:
        """The parameters of ``theta(m)`` for B sign vectors, differentiable in the offsets.

        Args:
            signs: [B, k] message signs ``2 m - 1`` (float, on the model's device).

        Returns:
            per trained attribute of :class:`SlotParams` (``dc``, ``rest``, ``logits``, ``log_scales``,
            ``quats``): a [B, *shape] tensor.
        """
        p = self.params
        base = {"dc": p.model.sh[:, :1], "rest": p.model.sh[:, 1:], "logits": p.model.opacity_logits,
                "log_scales": p.model.log_scales, "quats": p.model.quats}
        total = signs.sum(dim=1)  # [B]: sum_i s_i D_i = sum_i s_i (P_i - theta) = sum_i s_i P_i - (sum_i s_i) theta
        out = {}
        for name in _ATTRS:
            comp = getattr(p, name)  # [k + 1, *shape] = theta + D_j
            flat = comp[1:].reshape(self.num_bits, -1)
            mixed = (signs @ flat).view(signs.shape[0], *comp.shape[1:])
            shape = (-1,) + (1,) * (comp.dim() - 1)
            out[name] = comp[0] + mixed - total.view(shape) * base[name]
        return out

    def models(self, signs: Tensor) -> list[Gaussians]:
        """``theta(m)`` for each of B sign vectors [B, k], differentiable in the offsets."""
        parts = self.combine(signs)
        means = self.params.model.means
        return [Gaussians(means, parts["log_scales"][b], parts["quats"][b], parts["logits"][b],
                          torch.cat([parts["dc"][b], parts["rest"][b]], dim=1)) for b in range(signs.shape[0])]

    @torch.no_grad()
    def start(self, message: Tensor) -> dict[str, Tensor]:
        """The starting parameters of the recipient with ``message`` ([k] bits): per attribute, its tensor."""
        signs = (2 * message.to(self.params.dc.device, torch.float32) - 1)[None]
        return {name: t[0] for name, t in self.combine(signs).items()}


def fit_basis(scene, config: BasisConfig, on_step: Callable[[int], None] | None = None) -> BitBasis:
    """Fits a :class:`BitBasis` for a scene (the module docstring says how).

    Args:
        scene: a :class:`gsw.fingerprint.shared.WorkerScene`.
        config: the fit's settings.
        on_step: progress: called with the step number after every step.

    Returns:
        The fitted basis (on the scene's device).

    Raises:
        ValueError: settings the fit does not support (train-time image attacks).
    """
    from gsw.render.rasterize import rasterize

    cfg = scene.shared.config
    if cfg.attacks > 0:
        raise ValueError("a bit basis is fitted without train-time image attacks (EmbedConfig.attacks must be 0)")
    k, device = scene.shared.num_bits, scene.device
    basis = BitBasis(scene.model, k, cfg)
    gen = torch.Generator().manual_seed(config.seed)
    rng, order = random.Random(config.seed), []
    cams, originals, bg = scene.shared.cameras, scene.originals, cfg.background
    components = list(range(k + 1))
    for step in range(config.steps):
        messages = torch.randint(0, 2, (config.batch, k), generator=gen).float().to(device)
        views = []
        for _ in range(config.batch):
            if not order:
                order = list(range(len(cams)))
                rng.shuffle(order)
            views.append(order.pop())
        models = basis.models(2 * messages - 1)
        renders = [rasterize(g, cams[v], background=bg, validate=False).image for g, v in zip(models, views)]
        targets = [originals[v] for v in views]
        # one batched pass when the views share a size, else one per view
        groups = [range(len(views))] if len({r.shape for r in renders}) == 1 else [[b] for b in range(len(views))]
        loss = sum(batched_loss(scene.loss, torch.stack([renders[b] for b in g]),
                                torch.stack([targets[b] for b in g]), messages[list(g)])[0] for g in groups)
        loss.backward()
        basis.params.step(components)
        if on_step is not None:
            on_step(step + 1)
    return basis


def scene_basis(scene, config: BasisConfig) -> BitBasis:
    """The :class:`BitBasis` of a :class:`~gsw.fingerprint.shared.WorkerScene` for ``config``: fitted on the
    first call, then reused by every recipient batch of the worker (kept on the scene)."""
    if config not in scene.bases:
        scene.bases[config] = fit_basis(scene, config)
    return scene.bases[config]
