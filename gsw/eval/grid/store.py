"""The grid folder: ``grid.json`` (the settings a folder belongs to), cell files and their validity checks."""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from typing import Any, Mapping

import torch

from gsw._atomic import atomic_write
from gsw.decoder.null import decoder_fingerprint as decoder_sha256
from gsw.eval.grid.scene import GridScene
from gsw.eval.grid.spec import FORMAT, Cell, GridMismatchError, GridSpec

__all__ = ["decoder_fingerprint", "legacy_decoder_fingerprint"]


def _grid_record(spec: GridSpec, scene: GridScene) -> dict[str, Any]:
    return {"format": FORMAT, "settings": spec.settings(), "scene": json.loads(json.dumps(scene.key))}


def _digest(record: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]


def _write_json(path: Path, data: Any) -> None:
    with atomic_write(path, "w") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def _claim(out: Path, record: dict[str, Any], force: bool) -> None:
    """Creates the grid folder with its ``grid.json``, or checks that its grid has the same settings and scene."""
    path = out / "grid.json"
    if path.exists() and not force:
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise GridMismatchError(f"{path} is unreadable ({err}); pass --force to start the grid over") from None
        if old != record:
            diff = sorted(k for part in ("settings", "scene") for k in set(old.get(part, {})) | set(record[part])
                          if old.get(part, {}).get(k) != record[part].get(k))
            raise GridMismatchError(f"{out} holds a grid with other settings or scene (differs in {diff}); use "
                                    "another output folder, or --force to replace its settings")
        return
    if out.is_dir() and any(out.iterdir()) and not force:
        raise GridMismatchError(f"{out} is not empty and holds no grid.json; use a new folder, or --force to use it")
    out.mkdir(parents=True, exist_ok=True)
    _write_json(path, record)


_CELL_KEYS = ("format", "grid", "method", "bits", "seed", "config", "message", "report", "sweeps", "detection",
              "embedding", "timings", "fps", "storage")


def decoder_fingerprint(decoder: torch.nn.Module) -> str:
    """Short fingerprint of a decoder's weights, as grid cells and ``watermark.json`` record it: the first 16 hex
    digits of :func:`gsw.decoder.null.decoder_fingerprint` (the sha256 that null models and registries record)."""
    return decoder_sha256(decoder)[:16]


def legacy_decoder_fingerprint(decoder: torch.nn.Module) -> str:
    """The short fingerprint gsw recorded before 2026-11-28 (a hash of its own over the state dict, not a prefix of
    the sha256). Only read: to recognise the decoder of an older ``watermark.json`` or grid cell."""
    h = hashlib.sha256()
    for name, t in sorted(decoder.state_dict().items()):
        t = t.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def _load_cell(path: Path, cell: Cell, digest: str, config: dict[str, Any],
               decoder: tuple[str, ...]) -> dict[str, Any] | None:
    """A finished cell of this grid, or None (missing, corrupt, or from other settings, another resolved
    EmbedConfig (e.g. changed library defaults) or another decoder: recompute). ``decoder``: the fingerprints the
    cell's decoder may be recorded under (:func:`decoder_fingerprint`, :func:`legacy_decoder_fingerprint`)."""
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        complete = isinstance(data, dict) and all(k in data for k in _CELL_KEYS)
    except (OSError, ValueError):
        complete = False
    if not complete or (data["method"], data["bits"], data["seed"]) != tuple(cell) or data["format"] != FORMAT:
        warnings.warn(f"{path} is corrupt or incomplete; recomputing the cell", RuntimeWarning, stacklevel=3)
        return None
    if data["grid"] != digest or json.loads(json.dumps(data["config"])) != json.loads(json.dumps(config)):
        warnings.warn(f"{path} was computed with other settings; recomputing the cell", RuntimeWarning,
                      stacklevel=3)
        return None
    if data.get("decoder") not in decoder:
        warnings.warn(f"{path} was computed with another decoder; recomputing the cell", RuntimeWarning,
                      stacklevel=3)
        return None
    return data


def _default_decoder(bits: int) -> torch.nn.Module:
    from gsw.decoder.zoo import load_decoder

    return load_decoder(bits)
