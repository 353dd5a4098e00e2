"""Robustness and invisibility report of a watermarked model (the core of `gsw eval`).

For a watermarked model, its original and the embedded message, over a set of (held-out) views:

* invisibility: PSNR / SSIM / LPIPS (VGG) of the watermarked renders against the original renders;
* clean detection: bit accuracy and the share of views at p <= 1e-6, for the watermarked and
  for the original (unmarked) model;
* image attacks (:data:`gsw.attacks.presets.IMAGE_ATTACKS`, and optionally the official code's variants)
  applied to the watermarked renders;
* model attacks (:data:`gsw.attacks.presets.MODEL_ATTACKS`) applied to the watermarked model before
  rendering;
* optionally the same attacks on the original model's renders (the false positives under attack).

Every :class:`Detection` keeps its per-view p-values, so rates at other false-positive rates can be
computed afterwards (:mod:`gsw.eval.grid`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from gsw.attacks.presets import IMAGE_ATTACKS, MODEL_ATTACKS, OFFICIAL_ATTACKS
from gsw.camera import Camera
from gsw.mark.detect import message_num_bits, verify
from gsw.gaussians import Gaussians
from gsw.mark.message import MessageLike, as_message
from gsw.metrics.image import psnr, ssim
from gsw.render.rasterize import rasterize
from gsw.stats import DETECTION_FPR


@dataclass
class Detection:
    """Bit accuracy (mean over views), share of views detected at :data:`DETECTION_FPR`, per-view p-values.

    Attributes:
        bit_accuracy: mean over the views of the fraction of matching bits.
        detected_views: share of the views with p-value <= :data:`DETECTION_FPR`.
        p_values: per view, the binomial p-value of its matching bits (:func:`gsw.mark.detect.verify`).
    """

    bit_accuracy: float
    detected_views: float
    p_values: list[float] = field(default_factory=list)


@dataclass
class EvaluationReport:
    """Result of :func:`evaluate_watermark` (all means over the views)."""

    psnr: float
    ssim: float
    lpips: float | None
    clean: Detection
    unmarked: Detection
    image_attacks: dict[str, Detection] = field(default_factory=dict)
    model_attacks: dict[str, Detection] = field(default_factory=dict)
    unmarked_image_attacks: dict[str, Detection] = field(default_factory=dict)
    unmarked_model_attacks: dict[str, Detection] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def to_markdown(self) -> str:
        """The report as markdown tables."""
        lines = ["| measure | value |", "|---|---|",
                 f"| PSNR vs original renders | {self.psnr:.2f} dB |",
                 f"| SSIM vs original renders | {self.ssim:.4f} |",
                 f"| LPIPS (VGG) vs original renders | "
                 f"{'off' if self.lpips is None else f'{self.lpips:.4f}'} |",
                 f"| bit accuracy, watermarked | {100 * self.clean.bit_accuracy:.2f} % |",
                 f"| views at p <= {DETECTION_FPR:g}, watermarked | {100 * self.clean.detected_views:.0f} % |",
                 f"| bit accuracy, original (unmarked) | {100 * self.unmarked.bit_accuracy:.2f} % |",
                 f"| views at p <= {DETECTION_FPR:g}, original | {100 * self.unmarked.detected_views:.0f} % |",
                 ""]
        unmarked = {"image": self.unmarked_image_attacks, "model": self.unmarked_model_attacks}
        extra = any(unmarked.values())
        lines += ["| attack | kind | bit accuracy | views at p <= 1e-6 |" + (" original: views at p <= 1e-6 |"
                                                                          if extra else ""),
                  "|---|---|---|---|" + ("---|" if extra else "")]
        for kind, table in (("image", self.image_attacks), ("model", self.model_attacks)):
            for name, d in table.items():
                row = f"| {name} | {kind} | {100 * d.bit_accuracy:.2f} % | {100 * d.detected_views:.0f} % |"
                if extra:
                    row += f" {100 * unmarked[kind][name].detected_views:.0f} % |"
                lines.append(row)
        return "\n".join(lines) + "\n"


def _detection(images: Sequence[Tensor], message: Tensor, decoder) -> Detection:
    v = verify(list(images), message, decoder=decoder)
    n = len(v.p_values)
    return Detection(sum(v.bit_accuracy) / n, sum(p <= DETECTION_FPR for p in v.p_values) / n, list(v.p_values))


@torch.no_grad()
def evaluate_watermark(watermarked: Gaussians, original: Gaussians, cameras: Sequence[Camera],
                       message: MessageLike, *, num_bits: int | None = None,
                       background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                       image_attacks: Mapping[str, Callable[[Tensor], Tensor]] | None = None,
                       model_attacks: Mapping[str, Callable[[Gaussians], Gaussians]] | None = None,
                       official: bool = False, lpips_net: str | None = "vgg",
                       decoder: torch.nn.Module | None = None,
                       attack_unmarked: bool = False) -> EvaluationReport:
    """Invisibility and robustness of a watermark over a set of views.

    Args:
        watermarked: the watermarked model.
        original: the model before embedding (the reference renders).
        cameras: the evaluation views (use views not seen during embedding).
        message: the embedded message (bits, hex or `"key:<secret>"`).
        num_bits: message length (inferred from bits/hex, :func:`gsw.mark.detect.message_num_bits`).
        background: render background.
        image_attacks: name -> attack on [3, H, W] images (default: the paper's table).
        model_attacks: name -> attack on Gaussians (default: all of :mod:`gsw.attacks`).
        official: also run the official code's image-attack variants (prefixed `official_`).
        lpips_net: LPIPS network for the invisibility metrics, or None to skip LPIPS.
        decoder: a custom decoder (default: the shipped one).
        attack_unmarked: also run every attack on the original model (its renders, or the model
            itself for model attacks) and test the result for the message: the false positives
            under attack (`unmarked_image_attacks`, `unmarked_model_attacks`).

    Returns:
        An :class:`EvaluationReport`.
    """
    if not cameras:
        raise ValueError("evaluate_watermark needs at least one camera")
    if num_bits is None:
        num_bits = message_num_bits(message)
    bits = as_message(message, num_bits)
    image_attacks = dict(IMAGE_ATTACKS if image_attacks is None else image_attacks)
    if official:
        image_attacks.update({f"official_{k}": v for k, v in OFFICIAL_ATTACKS.items()})
    model_attacks = dict(MODEL_ATTACKS if model_attacks is None else model_attacks)

    def renders(g: Gaussians) -> list[Tensor]:
        return [rasterize(g, cam, background=background).image.clamp(0, 1) for cam in cameras]

    marked, plain = renders(watermarked), renders(original)
    n = len(cameras)
    lp = None
    if lpips_net is not None:
        from gsw.metrics.lpips import lpips

        lp = sum(float(lpips(a[None], b[None], net=lpips_net)) for a, b in zip(marked, plain)) / n
    report = EvaluationReport(
        psnr=sum(float(psnr(a, b)) for a, b in zip(marked, plain)) / n,
        ssim=sum(float(ssim(a, b)) for a, b in zip(marked, plain)) / n,
        lpips=lp,
        clean=_detection(marked, bits, decoder),
        unmarked=_detection(plain, bits, decoder),
    )
    sources = [(watermarked, marked, report.image_attacks, report.model_attacks)]
    if attack_unmarked:
        sources.append((original, plain, report.unmarked_image_attacks, report.unmarked_model_attacks))
    for model, images, image_table, model_table in sources:
        for name, attack in image_attacks.items():
            image_table[name] = _detection([attack(img) for img in images], bits, decoder)
        for name, attack in model_attacks.items():
            model_table[name] = _detection(renders(attack(model)), bits, decoder)
    return report
