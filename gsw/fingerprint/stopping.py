"""When a recipient's fine-tune is finished: per-recipient early stopping and message-weight control.

Every decision is taken from the fine-tune's own training steps (the renders of the embedding views it
already decodes for the loss), never from other views: a recipient is *passing* at a step when the decoder
reads every bit of that step's render right with ``|logit| >= margin``; it finishes once it has passed on
``window`` consecutive steps (each a different shuffled embedding view), after at least ``min_steps`` steps,
and, with a ``psnr_target``, once the running PSNR of its renders against the original renders is at least
that target; then its copy is scored on every embedding view (as every finished copy is) and, with
``confirm``, kept only when that score reaches ``confirm`` bit accuracy (and the PSNR target), else the
recipient goes on and needs twice as many consecutive passing steps for its next attempt. With
``accuracy_window`` a recipient may also finish (subject to the same confirmation) once the running mean bit
accuracy of its training steps (an exponential average over about ``accuracy_window`` steps) reaches
``confirm``: a copy that reads its bits right on almost every view but misses one bit on a few hard views never
strings ``window`` perfect steps together, yet passes the confirmation. A recipient that
reaches the step cap (``EmbedConfig.epochs`` passes over the views) finishes there, as without early stopping,
unless ``extend`` is set: then a copy whose score at the cap fails the same confirmation (``confirm`` bit
accuracy, the PSNR target) goes on for up to ``extend`` x the cap more steps, once, and finishes at that second
cap or earlier by the rule. With ``redraw``, a copy whose message was drawn by gsw (not given, not derived
from a key) and that finishes at its last cap below ``redraw_bits`` on the embedding views is discarded: the
recipient starts over from the input model with a new message (:func:`gsw.mark.message.redrawn_message`, derived
from the old one, so as secret and as uniform before the choice), up to ``redraw`` times. Such a message is kept
*because* it was embeddable, so it is registered as chosen and tested with the decoder's calibrated null model
(:mod:`gsw.mark.evidence`), not the exact randomization test that needs a uniform message. With ``focus``, a
recipient whose copy fails a confirmation (an early stop refused, or the step cap reached) draws that share of its
later steps from the embedding views its copy read a bit wrong on, weighted by their wrong bits, instead of its
next shuffled view: the steps go where the bits are missing (the views are known from the score, at no cost).
With ``probes``, the score also reads that many viewpoints in the gaps between neighbouring embedding views (drawn
once per job from the embedding cameras alone, :func:`gsw.mark.views.gap_views`): a copy is confirmed only when
their mean bit accuracy is >= ``probe_bits`` too, a copy below it at its last cap is redrawn as above, and
``focus`` sends steps to the probes read wrong as to the embedding views: a mark that reads every embedding view
but not the views between them (what held-out views are) is caught before the copy is written.

With ``adapt > 1`` each recipient's message weight is steered towards the PSNR target at every check: divided
by ``adapt`` while its running PSNR is below the target (down to ``w / max_factor`` of the configured weight
``w``), multiplied by ``adapt`` while the PSNR is above it and its bits do not pass yet (up to ``w``: the
control only ever lowers the configured recipe's weight).

The statistics stay on the device; the host reads them every ``check_every`` steps (one synchronisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gsw.mark.loss import steer_weight

__all__ = ["PRESETS", "EarlyStop", "SlotMonitor"]

_INTEGER_FIELDS = ("min_steps", "window", "check_every", "accuracy_window", "redraw", "probes")

#: Named settings, as measured on lego 800x800 with a pool of 16 on an H200 (BENCHMARKS.md, "Fifth GPU round" to
#: "Tenth GPU round"): ``quality``: 954-1,122 per GPU-hour in five jobs, 122 of their 128 copies >= 99 % bits and
#: >= 37 dB held-out; ``careful`` (confirmation 0.998, also on a running accuracy, no early stop before 384 steps):
#: 1,068 and 1,158 per GPU-hour in two jobs on fresh models, 122 of 128, every miss a hard message;
#: ``throughput``: 1,268-1,295 per GPU-hour, 13-14 of 16 meeting both; ``focused`` (``careful`` whose steps after a
#: failed confirmation all revisit the views read wrong, ``focus=1``): 1,374 and 1,405 per GPU-hour on two models
#: where ``careful`` ran 1,194 and 1,097, 62 of 64 copies meeting both for each ("Fourteenth GPU round");
#: ``assured`` (``focused`` with ``redraw=2``: a drawn message that ends below 0.995 on the embedding views is replaced,
#: up to twice), with the squared-error image term and no FGD (``gsw fingerprint --mse 35 --no-fgd``): 1,118 and 1,172
#: per GPU-hour on two models, 31 and 32 of 32 copies meeting both, every copy >= 37 dB ("Sixteenth GPU round"); 981
#: per GPU-hour with 64 of 64 on a third ("Seventeenth GPU round"); ``probed`` (``assured`` whose confirmation also reads
#: 16 viewpoints between the embedding views, ``probes=16``), same flags: the built-in scene 64 of 64 at 1,992 per
#: GPU-hour where ``assured`` met both in 57 of 64 (3,734) in the same run, lego 62 of 64 at 1,202 ("Eighteenth GPU
#: round"); on a built-in held-out ring 10 degrees above the embedding ring no better than ``assured`` (5 and 6 of 16).
#: Those numbers were measured with the paper's recipe (``assured`` with ``--mse 35 --no-fgd``). Under the pool's
#: default since 2026-11-29 (SH rest frozen, the squared-error term, no FGD; "Twentieth GPU round"): ``quality`` 32 of
#: 32 at 1,564 per GPU-hour, ``assured`` 63 of 64 at 1,852; the built-in scene, ``probed``: 63 of 64 at 3,915,
#: ``probed,probe_bits=0.995``: 64 of 64 at 3,419. ``gsw fingerprint``'s default is ``quality``.
_CAREFUL = "min_steps=384,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.998,extend=0.5,accuracy_window=32"
PRESETS = {
    "quality": "min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.995,extend=0.5",
    "careful": _CAREFUL,
    "throughput": "min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.99",
    "focused": _CAREFUL + ",focus=1",
    "assured": _CAREFUL + ",focus=1,redraw=2",
    "probed": _CAREFUL + ",focus=1,redraw=2,probes=16",
}


@dataclass(frozen=True)
class EarlyStop:
    """Per-recipient stopping rule (see the module docstring).

    Attributes:
        min_steps: steps before a recipient may finish.
        window: consecutive passing steps needed.
        margin: smallest ``|logit|`` of a right bit that counts (decoder logit units).
        check_every: steps between decisions (host synchronisations).
        psnr_target: running training-view PSNR (dB) also required to finish; None: no PSNR condition.
        adapt: per-check factor of the message-weight control (1: off; needs ``psnr_target``).
        max_factor: the controlled weight stays >= the configured one / ``max_factor``.
        confirm: before a recipient stops early, its copy is scored on every embedding view (as every finished
            copy is); it stops only when the mean bit accuracy there is >= ``confirm`` (and the mean PSNR >=
            ``psnr_target`` when given), else its streak starts over. 0: no condition on the bits.
        extend: a recipient whose copy fails that confirmation at the step cap goes on for up to this fraction
            of the cap more steps (once); 0: every recipient finishes at the cap.
        accuracy_window: 0, or: a recipient also passes when the running mean bit accuracy of its training steps
            (over about this many steps, counted since it started or its last refused stop, doubled per refusal)
            is >= ``confirm`` (which must then be > 0).
        redraw: new messages a recipient may get (0: none; only for messages gsw drew): see the module docstring.
        redraw_bits: a copy finished at its last cap below this mean bit accuracy on the embedding views is
            redrawn (while ``redraw`` allows).
        focus: share in [0, 1] of a recipient's steps after a failed confirmation that revisit the embedding
            views its copy read wrong (see the module docstring); 0: every step takes the next shuffled view.
        probes: viewpoints between neighbouring embedding views that every score also reads (0: none; see the
            module docstring).
        probe_bits: with ``probes``, the mean bit accuracy on them a copy needs to be confirmed (and not redrawn).
    """

    min_steps: int = 100
    window: int = 16
    margin: float = 1.0
    check_every: int = 8
    psnr_target: float | None = None
    adapt: float = 1.0
    max_factor: float = 4.0
    confirm: float = 0.0
    extend: float = 0.0
    accuracy_window: int = 0
    redraw: int = 0
    redraw_bits: float = 0.995
    focus: float = 0.0
    probes: int = 0
    probe_bits: float = 0.99

    def __post_init__(self) -> None:
        for name in ("min_steps", "window", "check_every"):  # accuracy_window may be 0
            if int(getattr(self, name)) < 1:
                raise ValueError(f"EarlyStop.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.confirm <= 1.0:
            raise ValueError(f"EarlyStop.confirm is a bit accuracy in [0, 1], got {self.confirm}")
        if not 0.0 <= self.extend <= 10.0:
            raise ValueError(f"EarlyStop.extend is a fraction of the step cap in [0, 10], got {self.extend}")
        if self.accuracy_window < 0 or self.accuracy_window > 0 and self.confirm <= 0:
            raise ValueError("EarlyStop.accuracy_window must be >= 0, and > 0 only with a confirmation (confirm > 0), "
                             f"got accuracy_window={self.accuracy_window}, confirm={self.confirm}")
        if self.redraw < 0 or not 0.0 <= self.redraw_bits <= 1.0:
            raise ValueError("EarlyStop.redraw must be >= 0 and redraw_bits a bit accuracy in [0, 1], got "
                             f"redraw={self.redraw}, redraw_bits={self.redraw_bits}")
        if self.probes < 0 or not 0.0 <= self.probe_bits <= 1.0:
            raise ValueError("EarlyStop.probes must be >= 0 and probe_bits a bit accuracy in [0, 1], got "
                             f"probes={self.probes}, probe_bits={self.probe_bits}")
        if not 0.0 <= self.focus <= 1.0:
            raise ValueError(f"EarlyStop.focus is a share of the steps in [0, 1], got {self.focus}")
        if self.margin < 0:
            raise ValueError(f"EarlyStop.margin must be >= 0, got {self.margin}")
        if self.adapt < 1 or self.max_factor < 1:
            raise ValueError(f"EarlyStop.adapt and max_factor must be >= 1, got {self.adapt}, {self.max_factor}")
        if self.adapt > 1 and self.psnr_target is None:
            raise ValueError("EarlyStop.adapt > 1 steers the message weight towards psnr_target: give one")

    def confirmed(self, bit_accuracy: float, psnr: float, probe_accuracy: float | None = None) -> bool:
        """Whether a copy scored ``bit_accuracy`` / ``psnr`` (dB) on the embedding views and ``probe_accuracy`` on
        the probes (None: none scored) may stop early (or, with ``extend``, finish at the step cap)."""
        return (bit_accuracy >= self.confirm and (self.psnr_target is None or psnr >= self.psnr_target)
                and (probe_accuracy is None or probe_accuracy >= self.probe_bits))

    def redraws(self, bit_accuracy: float, done: int, probe_accuracy: float | None = None) -> bool:
        """Whether a copy finished at its last cap with ``bit_accuracy`` on the embedding views and
        ``probe_accuracy`` on the probes (None: none scored) is discarded for a new message, its recipient having
        had ``done`` new messages so far."""
        low = bit_accuracy < self.redraw_bits or probe_accuracy is not None and probe_accuracy < self.probe_bits
        return done < self.redraw and low

    def extension(self, cap: int) -> int:
        """Extra steps a recipient that fails :meth:`confirmed` at the step ``cap`` gets (0: none)."""
        return max(1, round(self.extend * cap)) if self.extend > 0 else 0

    @classmethod
    def parse(cls, text: str) -> "EarlyStop":
        """From ``"key=value,..."`` with the attribute names (``psnr_target=none`` for no target), optionally
        starting with the name of a preset (:data:`PRESETS`) whose values the later keys override
        (``"quality,extend=1"``).

        Raises:
            ValueError: an unknown key or preset, or a malformed value.
        """
        fields = {f: t for f, t in cls.__annotations__.items()}
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if parts and "=" not in parts[0]:
            name = parts.pop(0)
            if name not in PRESETS:
                raise ValueError(f"early-stop setting {name!r}: not a preset ({', '.join(PRESETS)}) and not key=value")
            parts = PRESETS[name].split(",") + parts
        kwargs: dict = {}
        for part in parts:
            key, sep, value = part.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in fields:
                raise ValueError(f"early-stop setting {part!r}: expected key=value with key one of "
                                 f"{', '.join(fields)}")
            try:
                if key == "psnr_target":
                    kwargs[key] = None if value.strip().lower() == "none" else float(value)
                else:
                    kwargs[key] = int(value) if key in _INTEGER_FIELDS else float(value)
            except ValueError:
                raise ValueError(f"early-stop setting {part!r}: {value!r} is not a number") from None
        return cls(**kwargs)


class SlotMonitor:
    """Device-side per-slot statistics of a recipient pool and the decisions of an :class:`EarlyStop`.

    Args:
        k: number of slots.
        weight: the configured message weight.
        rule: the stopping rule, or None (every recipient runs to the step cap).
        device: where the statistics live.
    """

    def __init__(self, k: int, weight: float, rule: EarlyStop | None, device: torch.device) -> None:
        self.rule, self.weight = rule, float(weight)
        self.streak = torch.zeros(k, device=device)
        self.psnr = torch.zeros(k, device=device)
        self.weights = torch.full((k,), self.weight, device=device)
        self.count = torch.zeros(k, device=device)  # steps observed per slot
        self.accuracy = torch.zeros(k, device=device)  # running bit accuracy (rule.accuracy_window)
        self.since = torch.zeros(k, device=device)  # steps since the recipient started or its last refused stop
        self.rejections = [0] * k  # early stops refused by the confirmation, per slot
        self.alpha = 2.0 / ((rule.window if rule else 16) + 1)
        self.alpha_accuracy = 2.0 / ((rule.accuracy_window if rule else 0) + 1)

    def reset(self, j: int) -> None:
        """Slot ``j`` holds a new recipient."""
        self.streak[j] = 0.0
        self.psnr[j] = 0.0
        self.count[j] = 0.0
        self.accuracy[j] = 0.0
        self.since[j] = 0.0
        self.rejections[j] = 0
        self.weights[j] = self.weight

    @torch.no_grad()
    def observe(self, slots: Tensor, logits: Tensor, messages: Tensor, renders: Tensor, targets: Tensor) -> None:
        """Records one step of the ``slots`` (no host synchronisation).

        Args:
            slots: [B] the active slots (device indices), in the order of the batch.
            logits: [B, k] decoder logits of their renders.
            messages: [B, k] their bits.
            renders: [B, 3, H, W] their renders.
            targets: [B, 3, H, W] the original renders.
        """
        if self.rule is None:
            return
        signed = logits.detach() * (2 * messages - 1)
        ok = (signed >= max(self.rule.margin, 1e-12)).all(dim=1).float()
        self.streak[slots] = (self.streak[slots] + 1) * ok
        mse = (renders.detach().clamp(0, 1) - targets.clamp(0, 1)).square().mean(dim=(1, 2, 3))
        p = -10 * torch.log10(mse.clamp_min(1e-12))
        first = self.count[slots] == 0
        self.psnr[slots] = torch.where(first, p, (1 - self.alpha) * self.psnr[slots] + self.alpha * p)
        if self.rule.accuracy_window:
            acc = (signed > 0).float().mean(dim=1)
            a = self.alpha_accuracy
            self.accuracy[slots] = torch.where(self.since[slots] == 0, acc, (1 - a) * self.accuracy[slots] + a * acc)
        self.since[slots] += 1
        self.count[slots] += 1

    def decide(self, steps: list[int], active: list[bool], caps: list[int]) -> list[int]:
        """The active slots that finish now (one host synchronisation); adjusts the message weights.

        Args:
            steps: per slot, the steps its recipient has taken.
            active: per slot, whether it holds a recipient.
            caps: per slot, its recipient's step cap.
        """
        done = [j for j, (s, a, c) in enumerate(zip(steps, active, caps)) if a and s >= c]
        rule = self.rule
        if rule is None:
            return done
        streak, psnr, accuracy, since = (t.tolist() for t in torch.stack([self.streak, self.psnr, self.accuracy,
                                                                          self.since]).cpu())
        for j, (s, a) in enumerate(zip(steps, active)):
            if not a or j in done:
                continue
            doubling = 2 ** self.rejections[j]  # each refusal doubles the evidence needed
            bits_ok = streak[j] >= rule.window * doubling or (
                rule.accuracy_window > 0 and since[j] >= rule.accuracy_window * doubling
                and accuracy[j] >= rule.confirm)
            psnr_ok = rule.psnr_target is None or psnr[j] >= rule.psnr_target
            if s >= rule.min_steps and bits_ok and psnr_ok:
                done.append(j)
            elif rule.adapt > 1 and not psnr_ok:
                self._scale(j, 1 / rule.adapt)
            elif rule.adapt > 1 and not bits_ok:
                self._scale(j, rule.adapt)
        return sorted(done)

    def refuse(self, j: int) -> None:
        """Slot ``j``'s early stop was refused (:meth:`EarlyStop.confirmed`): its streak starts over and the
        next attempt needs twice the window (the scores stay a bounded share of the steps)."""
        self.streak[j] = 0.0
        self.since[j] = 0.0
        self.rejections[j] += 1

    def _scale(self, j: int, factor: float) -> None:
        self.weights[j] = steer_weight(float(self.weights[j]), factor, self.weight / self.rule.max_factor, self.weight)
