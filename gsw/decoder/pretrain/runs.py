"""The run folder of a pre-training (``gsw decoder train``): one pair of files per bit length.

* ``k{bits}.pt`` - ``{"stage", "num_bits", "decoder", "whitening", "config", "step"}`` state dicts, plus
  ``"encoder"`` (the jointly trained encoder) and/or ``"encoder_ft"`` (the encoder fine-tuned against the
  frozen decoder); with ``half`` the encoders are float16 and only the last one is kept.
* ``k{bits}.json`` - the run's metadata: ``config`` (a :class:`MultiConfig` as a dict, plus ``num_bits`` and
  the fine-tune settings), ``args`` (the :class:`~gsw.decoder.pretrain.pipeline.PretrainOptions`), step counts
  and times, device and versions, the training / validation / fine-tune logs and ``results`` (evaluations).

Both are rewritten (atomically) at the end of every stage, so an interrupted run keeps its last stage.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import torch

from gsw._atomic import atomic_write
from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.pretrain.config import MultiConfig
from gsw.decoder.pretrain.encoders import TemplateEncoder, encoder_state, make_encoder
from gsw.decoder.whitening import WhiteningLayer
from gsw.decoder.zoo import atomic_torch_save

__all__ = ["ENCODER_KEYS", "load_init", "load_run_decoder", "read_meta", "write_stage"]

#: The encoders a run file may hold.
ENCODER_KEYS = ("encoder", "encoder_ft")


def read_meta(run: str | Path, num_bits: int) -> dict[str, Any]:
    """``k{num_bits}.json`` of a run folder.

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: it is not valid JSON.
    """
    path = Path(run) / f"k{num_bits}.json"
    if not path.is_file():
        raise FileNotFoundError(f"run file not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON: {e}") from e


def _read_blob(run: Path, num_bits: int) -> dict[str, Any]:
    path = run / f"k{num_bits}.pt"
    if not path.is_file():
        raise FileNotFoundError(f"run file not found: {path}")
    return torch.load(path, map_location="cpu", weights_only=False)


def load_init(run: str | Path, cfg: MultiConfig, encoder_key: str = "encoder") -> tuple[list[torch.nn.Module],
                                                                                        list[HiddenDecoder]]:
    """Encoders and decoders of an earlier run (``k{k}.pt`` per bit length of ``cfg.bits``), built for ``cfg``.

    ``encoder_key="encoder_ft"`` takes the run's fine-tuned encoder; a template encoder may grow on the way
    (:meth:`TemplateEncoder.load_grown_state_dict`: larger templates, a new or wider ``mlp`` branch).

    Raises:
        FileNotFoundError: a run file is missing.
        ValueError: a file lacks the encoder, or its networks do not fit ``cfg``.
    """
    run = Path(run)
    encs: list[torch.nn.Module] = []
    decs: list[HiddenDecoder] = []
    for k in cfg.bits:
        blob = _read_blob(run, k)
        if encoder_key not in blob:
            raise ValueError(f"{run / f'k{k}.pt'} has no {encoder_key!r} (a half checkpoint keeps only its last "
                             f"encoder: {[n for n in ENCODER_KEYS if n in blob]})")
        enc = make_encoder(k, cfg)
        dec = HiddenDecoder(k, cfg.dec_blocks, cfg.channels, cfg.dec_norm)
        try:
            if isinstance(enc, TemplateEncoder):
                enc.load_grown_state_dict(blob[encoder_key])
            else:
                enc.load_state_dict(blob[encoder_key])
            dec.load_state_dict(blob["decoder"])
        except (RuntimeError, ValueError) as e:
            raise ValueError(f"{run}: the {k}-bit networks do not fit this configuration: {e}") from e
        encs.append(enc)
        decs.append(dec)
    return encs, decs


def load_run_decoder(run: str | Path, num_bits: int) -> tuple[HiddenDecoder, WhiteningLayer, dict[str, Any]]:
    """The decoder (eval mode, CPU) and whitening of a run, with the run's metadata.

    The architecture comes from the metadata's ``config`` (input normalisation included; runs without it
    fed LL2 raw).

    Raises:
        FileNotFoundError: a run file is missing.
        ValueError: the weights do not fit the recorded architecture.
    """
    run = Path(run)
    meta = read_meta(run, num_bits)
    blob = _read_blob(run, num_bits)
    cfg = meta.get("config", {})
    dec = HiddenDecoder(num_bits, cfg.get("dec_blocks", 8), cfg.get("channels", 64), cfg.get("dec_norm", "none"))
    wl = WhiteningLayer(num_bits)
    try:
        dec.load_state_dict(blob["decoder"])
        wl.load_state_dict(blob["whitening"])
    except (KeyError, RuntimeError) as e:
        raise ValueError(f"{run / f'k{num_bits}.pt'}: decoder or whitening missing or mismatched: {e}") from e
    return dec.eval(), wl, meta


def write_stage(out: Path, stage: str, num_bits: int, meta: dict[str, Any], decoder: HiddenDecoder,
                whitening: WhiteningLayer, step: int, encoders: dict[str, torch.nn.Module], half: bool) -> None:
    """Write ``k{num_bits}.pt`` and ``k{num_bits}.json`` of ``out`` (atomically) at the end of ``stage``.

    Args:
        meta: the metadata (``config`` is also stored in the ``.pt``); its ``stage`` is set here.
        encoders: ``{"encoder": ..., "encoder_ft": ...}`` (either may be absent), stored in float16 when ``half``.
    """
    meta["stage"] = stage
    blob: dict[str, Any] = {"stage": stage, "num_bits": num_bits, "decoder": decoder.state_dict(),
                            "whitening": whitening.state_dict(), "config": meta["config"], "step": step}
    blob.update({key: encoder_state(enc, half) for key, enc in encoders.items()})
    atomic_torch_save(blob, out / f"k{num_bits}.pt")
    with atomic_write(out / f"k{num_bits}.json", "w") as f:
        f.write(json.dumps(meta, indent=1))


def config_dict(cfg: MultiConfig, num_bits: int, ft_s: float) -> dict[str, Any]:
    """The ``config`` entry of a run's metadata for one bit length."""
    return {**dataclasses.asdict(cfg), "num_bits": num_bits, "ft_s": ft_s}
