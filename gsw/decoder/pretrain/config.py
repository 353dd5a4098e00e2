"""Configurations of the two pre-training loops and the constants they share.

* :class:`TrainConfig` - the host-side trainer :func:`gsw.decoder.pretrain.loop.train` (one bit length,
  crops cut in Python, real JPEG with kornia's gradient).
* :class:`MultiConfig` - the device-resident trainer :func:`gsw.decoder.pretrain.multi.train_multi` that made
  the shipped decoders (several bit lengths at once, device-only attacks, a curriculum).
"""

from __future__ import annotations

import dataclasses

from gsw.attacks.layers import TRAINING_LAYER_NAMES

__all__ = ["MultiConfig", "TrainConfig", "UNMARKED_CROP_SIZES", "WHITEN_EIG_FLOOR"]

#: Sides of the unmarked crops seen by the balance loss and by the whitening fit.
UNMARKED_CROP_SIZES: tuple[int, ...] = (128, 192, 256, 320)
#: Whitening eigenvalue floor, relative to the largest eigenvalue (see
#: :func:`gsw.decoder.pretrain.whiten.fit_whitening_multi`).
WHITEN_EIG_FLOOR = 1e-3


@dataclasses.dataclass
class TrainConfig:
    """Host-side pre-training of one encoder/decoder pair (:func:`gsw.decoder.pretrain.loop.train`)."""

    num_bits: int = 32
    channels: int = 64  # network width (64 for the shipped decoders; smaller only for tests)
    enc_blocks: int = 4
    dec_blocks: int = 8
    dec_norm: str = "standardize"  # HiddenDecoder input_norm
    crop: int = 128  # training crop side (LL2 is crop/4)
    batch_size: int = 128  # split evenly over the noise layers
    lr: float = 1e-3
    weight_decay: float = 0.0
    psnr_start: float = 24.0  # PSNR of the watermarked crops at the start ...
    psnr_target: float = 30.0  # ... and after psnr_ramp of the run
    psnr_ramp: float = 0.4
    noise_ramp: float = 0.3  # attack strength ramps 0 -> 1 over this fraction of the run
    steps: int = 1000  # used when time_budget_s is None
    time_budget_s: float | None = None
    warmup: float = 0.02
    jpeg_mode: str = "real_diffgrad"
    noise_layers: tuple[str, ...] | None = None  # subset of training_noise_layers() names; None = all
    amp: bool = False  # bf16 autocast for the networks (DWT and attacks stay float32)
    seed: int = 0
    log_every: int = 50
    ckpt_every_s: float = 60.0


@dataclasses.dataclass
class MultiConfig:
    """Device-resident pre-training of one pair per bit length (:func:`gsw.decoder.pretrain.multi.train_multi`)."""

    bits: tuple[int, ...] = (32, 48, 64)
    channels: int = 64
    enc_blocks: int = 4
    dec_blocks: int = 8
    dec_norm: str = "standardize"  # HiddenDecoder input_norm
    crop: int = 128
    batch_size: int = 64  # per bit length; split into ``noise_chunks`` chunks, one random attack each
    noise_chunks: int = 2
    lr: float = 1e-3
    weight_decay: float = 0.0
    warmup: float = 0.03
    psnr_start: float = 22.0  # strong watermark while learning the code ...
    psnr_target: float = 30.0  # ... tightened to this
    clean_frac: float = 0.3  # no attacks before this fraction of the run
    noise_ramp_end: float = 0.6  # attack strength 0 -> 1 between clean_frac and this
    psnr_ramp_end: float = 0.8  # PSNR psnr_start -> psnr_target between clean_frac and this
    noise_layers: tuple[str, ...] = TRAINING_LAYER_NAMES
    steps: int = 1000  # used when time_budget_s is None
    time_budget_s: float | None = None
    amp: bool = True  # bf16 autocast for the networks (DWT, attacks and loss in float32)
    channels_last: bool = True
    seed: int = 0
    log_every: int = 100
    enc_down: int = 1  # the encoder works on the crop downsampled by this factor (see embed_scaled)
    templates: int = 0  # > 0: the encoder also adds learned periodic per-bit templates of this side (LL2 px)
    template_mlp: int = 0  # > 0: plus a nonlinear message -> tile branch of this width (TemplateEncoder mlp)
    template_refine: int = 0  # > 0: plus an image-adaptive conv refiner of this width (TemplateEncoder refine)
    view_warp: bool = False  # every sample also goes through GpuAttacks.view (ramped with the attack strength)
    balance: float = 0.0  # weight of the unmarked-balance loss (0 = off), see balance_loss
    balance_batch: int = 16  # unmarked crops per step and bit length for that loss
    balance_sizes: tuple[int, ...] = UNMARKED_CROP_SIZES  # their side, one drawn per step
    freeze_bn: bool = False  # decoder BatchNorm in eval mode (running statistics, frozen): for fine-tuning
    clean_chunk: bool = False  # the first of the noise_chunks is never attacked (the clean task weighs more)
