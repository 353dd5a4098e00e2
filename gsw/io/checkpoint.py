"""Read 3DGS models from training checkpoints: gsplat (``ckpt_*.pt``) and nerfstudio splatfacto (``*.ckpt``).

- gsplat's ``simple_trainer.py`` saves ``{"step": int, "splats": state_dict}`` with ``means [N, 3]``,
  ``quats [N, 4]`` (``w, x, y, z``, unnormalised), ``scales [N, 3]`` (log), ``opacities [N]`` (logits),
  ``sh0 [N, 1, 3]`` and ``shN [N, K - 1, 3]`` (coefficient-major), i.e. exactly the
  :class:`~gsw.gaussians.Gaussians` conventions.
- nerfstudio's splatfacto saves ``{"pipeline": state_dict, ...}`` with the same tensors under
  ``_model.gauss_params.{means, quats, scales, opacities [N, 1], features_dc [N, 3], features_rest [N, K - 1,
  3]}`` (``_model.{...}`` in older versions). Those models live in nerfstudio's normalised frame: pair them with
  cameras through :func:`gsw.data.nerfstudio.load_nerfstudio` and its ``dataparser_transforms.json``.

Checkpoints are loaded with ``torch.load(weights_only=True)`` (no code from the file runs). Checkpoints of the
appearance-model variant (``features`` / ``colors`` instead of SH) are rejected: they hold no SH colours.

Example:
    >>> from gsw.io.checkpoint import load_checkpoint
    >>> g = load_checkpoint("results/ckpts/ckpt_29999_rank0.pt")  # doctest: +SKIP
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from gsw.gaussians import Gaussians

__all__ = ["CheckpointError", "load_checkpoint"]

_GSPLAT = ("means", "quats", "scales", "opacities", "sh0", "shN")
_SPLATFACTO = ("means", "quats", "scales", "opacities", "features_dc", "features_rest")
_SPLATFACTO_PREFIXES = ("_model.gauss_params.", "_model.")


class CheckpointError(ValueError):
    """A checkpoint is unreadable or does not hold a 3DGS model in a known layout."""


def _tensor(params: Mapping[str, Any], key: str, path: Path) -> Tensor:
    value = params[key]
    if not isinstance(value, Tensor) or not value.is_floating_point():
        raise CheckpointError(f"{path}: {key} must be a floating-point tensor, got {type(value).__name__}")
    return value.detach().to(device="cpu", dtype=torch.float32)


def _from_gsplat(splats: Mapping[str, Any], path: Path) -> Gaussians:
    missing = [k for k in _GSPLAT if k not in splats]
    if missing:
        hint = " (an appearance-model checkpoint: it holds features/colors, not SH)" \
            if "features" in splats or "colors" in splats else ""
        raise CheckpointError(f"{path}: 'splats' lacks {', '.join(missing)}{hint}")
    t = {k: _tensor(splats, k, path) for k in _GSPLAT}
    opacities = t["opacities"].reshape(-1) if t["opacities"].dim() == 2 and t["opacities"].shape[1] == 1 \
        else t["opacities"]
    sh0 = t["sh0"].reshape(-1, 1, 3) if t["sh0"].dim() == 2 else t["sh0"]
    return _assemble(t["means"], t["quats"], t["scales"], opacities, sh0, t["shN"], path)


def _from_splatfacto(state: Mapping[str, Any], prefix: str, path: Path) -> Gaussians:
    t = {k: _tensor(state, prefix + k, path) for k in _SPLATFACTO}
    opacities = t["opacities"].reshape(-1) if t["opacities"].dim() == 2 else t["opacities"]
    dc = t["features_dc"].reshape(-1, 1, 3) if t["features_dc"].dim() == 2 else t["features_dc"]
    return _assemble(t["means"], t["quats"], t["scales"], opacities, dc, t["features_rest"], path)


def _assemble(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh0: Tensor,
              sh_rest: Tensor, path: Path) -> Gaussians:
    if sh_rest.dim() == 2 and sh_rest.shape[1] == 0:  # degree 0 saved as [N, 0]
        sh_rest = sh_rest.reshape(len(sh_rest), 0, 3)
    if sh0.dim() != 3 or sh_rest.dim() != 3:
        raise CheckpointError(f"{path}: SH tensors must be [N, K, 3], got {list(sh0.shape)} and "
                              f"{list(sh_rest.shape)}")
    try:
        g = Gaussians(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits,
                      sh=torch.cat([sh0, sh_rest], dim=1))
        return g.check_finite()
    except (ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{path}: {exc}") from None


def load_checkpoint(path: str | os.PathLike) -> Gaussians:
    """Load the Gaussians of a gsplat ``.pt`` or nerfstudio splatfacto ``.ckpt`` checkpoint.

    Args:
        path: the checkpoint file.

    Returns:
        :class:`~gsw.gaussians.Gaussians` on the CPU in float32 (the checkpoint's raw parameters, unchanged).

    Raises:
        CheckpointError: not a torch checkpoint, objects that need code to unpickle, an unknown layout
            (the message lists the top-level keys), missing or malformed tensors, NaN/Inf values.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({first})") from None
    if not isinstance(data, Mapping):
        raise CheckpointError(f"{path}: expected a dict checkpoint, got {type(data).__name__}")
    if isinstance(data.get("splats"), Mapping):
        return _from_gsplat(data["splats"], path)
    state = data.get("pipeline")
    if isinstance(state, Mapping):
        for prefix in _SPLATFACTO_PREFIXES:
            if prefix + "means" in state:
                missing = [k for k in _SPLATFACTO if prefix + k not in state]
                if missing:
                    raise CheckpointError(f"{path}: splatfacto pipeline lacks {', '.join(prefix + k for k in missing)}")
                return _from_splatfacto(state, prefix, path)
        raise CheckpointError(f"{path}: the nerfstudio pipeline holds no Gaussians (no _model.gauss_params.means)")
    keys = ", ".join(map(str, list(data)[:10]))
    raise CheckpointError(f"{path}: unknown checkpoint layout (top-level keys: {keys}); supported: gsplat "
                          "{'splats': {means, quats, scales, opacities, sh0, shN}} and nerfstudio splatfacto "
                          "{'pipeline': {_model.gauss_params.*}}")
