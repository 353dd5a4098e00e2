"""The shipped, frozen watermark decoders (32, 48 and 64 bits) and their loader.

Each decoder is a pre-trained :class:`~gsw.decoder.hidden.HiddenDecoder` followed by its fitted
:class:`~gsw.decoder.whitening.WhiteningLayer`, stored as a float32 state dict in
``gsw/decoder/weights/hidden_k{bits}.pt``; ``weights/manifest.json`` records each file's sha256, size
and how it was made.  :func:`load_decoder` verifies the sha256 before loading and raises
:class:`WeightsError` (missing file, wrong checksum, unreadable or mismatched contents).

Example:
    >>> import torch
    >>> dec = load_decoder(32)                   # verified, eval mode, on the CPU
    >>> logits = dec.decode_image(torch.rand(1, 3, 64, 64))
    >>> logits.shape
    torch.Size([1, 32])
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

from gsw._atomic import atomic_write
from gsw.decoder.dwt import LEVELS, ll_subband
from gsw.decoder.hidden import HiddenDecoder
from gsw.decoder.whitening import WhiteningLayer

__all__ = [
    "WEIGHTS_DIR",
    "AVAILABLE_BITS",
    "WeightsError",
    "WatermarkDecoder",
    "load_decoder",
    "save_decoder",
    "read_provenance",
    "record_in_manifest",
    "sha256_file",
    "weights_path",
]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
MANIFEST = "manifest.json"
AVAILABLE_BITS = (32, 48, 64)


class WeightsError(RuntimeError):
    """Decoder weights are missing, corrupt (checksum mismatch) or do not match the architecture."""


class WatermarkDecoder(nn.Module):
    """Frozen decoder: LL2 subband -> HiDDeN decoder -> whitening -> logits (bit = logit > 0).

    ``forward`` takes the level-2 LL subband (what the embedding loss feeds it); ``decode_image`` takes
    images [B,3,H,W] in [0,1] and computes the subband with the project's DWT.
    """

    def __init__(self, num_bits: int, num_blocks: int = 8, channels: int = 64, input_norm: str = "none") -> None:
        super().__init__()
        self.num_bits = num_bits
        self.decoder = HiddenDecoder(num_bits, num_blocks, channels, input_norm)
        self.whitening = WhiteningLayer(num_bits)

    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        """ll [B,3,h,w] (LL2 of images in [0,1]) -> whitened logits [B,k]."""
        return self.whitening(self.decoder(ll).float())

    def decode_image(self, images: torch.Tensor) -> torch.Tensor:
        """images [B,3,H,W] in [0,1] -> whitened logits [B,k]."""
        return self(ll_subband(images, LEVELS))

    @torch.no_grad()
    def bits(self, images: torch.Tensor) -> torch.Tensor:
        """images [B,3,H,W] in [0,1] -> decoded bits [B,k] in {0,1} (float)."""
        return (self.decode_image(images) > 0).float()


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _manifest(weights_dir: Path) -> dict[str, Any]:
    path = weights_dir / MANIFEST
    if not path.exists():
        raise WeightsError(f"decoder weight manifest not found: {path} (is the package installed completely?)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise WeightsError(f"decoder weight manifest {path} is not valid JSON: {e}") from e


def weights_path(num_bits: int, weights_dir: str | Path | None = None) -> Path:
    """Path of the shipped weight file for ``num_bits``."""
    return Path(weights_dir or WEIGHTS_DIR) / f"hidden_k{num_bits}.pt"


def load_decoder(
    num_bits: int = 32,
    path: str | Path | None = None,
    *,
    sha256: str | None = None,
    device: torch.device | str = "cpu",
    weights_dir: str | Path | None = None,
) -> WatermarkDecoder:
    """Load a frozen watermark decoder (decoder + whitening), eval mode, ``requires_grad=False``.

    Args:
        num_bits: message length; the shipped ones are 32, 48 and 64.
        path: your own weight file (as written by :func:`save_decoder`); default: the shipped one.
        sha256: expected checksum of ``path``; shipped files are always checked against the manifest.
        device: where to put the module.
        weights_dir: directory holding the shipped files and ``manifest.json`` (tests use this).

    Raises:
        WeightsError: missing file, checksum mismatch, unreadable file, or contents that do not match
            a ``num_bits`` decoder.
    """
    if path is None:
        wdir = Path(weights_dir or WEIGHTS_DIR)
        if num_bits not in AVAILABLE_BITS and weights_dir is None:
            raise WeightsError(f"no shipped decoder for {num_bits} bits (available: {AVAILABLE_BITS}); pass path=")
        path = weights_path(num_bits, wdir)
        entry = _manifest(wdir).get("files", {}).get(path.name)
        if entry is None:
            raise WeightsError(f"{path.name} is not listed in {wdir / MANIFEST}")
        sha256 = entry["sha256"]
    path = Path(path)
    if not path.exists():
        raise WeightsError(f"decoder weights not found: {path}")
    if sha256 is not None:
        actual = sha256_file(path)
        if actual != sha256:
            raise WeightsError(
                f"decoder weights {path} are corrupt: sha256 {actual} does not match the expected {sha256}"
            )
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means a bad file
        raise WeightsError(f"cannot read decoder weights {path}: {e}") from e
    if not isinstance(blob, dict) or "state_dict" not in blob or "num_bits" not in blob:
        raise WeightsError(f"{path} is not a gsw decoder file (expected keys 'num_bits', 'state_dict')")
    if int(blob["num_bits"]) != num_bits:
        raise WeightsError(f"{path} holds a {blob['num_bits']}-bit decoder, {num_bits} bits were asked for")
    arch = blob.get("arch", {})
    try:
        model = WatermarkDecoder(num_bits, int(arch.get("num_blocks", 8)), int(arch.get("channels", 64)),
                                 str(arch.get("input_norm", "none")))  # files before input_norm fed LL2 raw
    except ValueError as e:
        raise WeightsError(f"{path} names an unknown decoder architecture {arch}: {e}") from e
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as e:
        raise WeightsError(f"{path} does not match the decoder architecture: {e}") from e
    model.eval().requires_grad_(False)
    return model.to(device)


MANIFEST_HEADER = {
    "format": "torch.save dict {num_bits, arch, state_dict (float32), meta}; state_dict keys decoder.* "
              "(HiddenDecoder) and whitening.weight/bias",
    "dwt": "bior4.4, 2 levels, periodization; decoder input = LL2 of images in [0,1]",
}


def record_in_manifest(path: str | Path, provenance: dict[str, Any] | None = None) -> dict[str, Any]:
    """Record a decoder file written by :func:`save_decoder` in its directory's ``manifest.json``.

    The entry (sha256, size, bit length, ``provenance``) replaces any entry of the same name or bit length;
    the other files' entries stay, so exporting one bit length keeps the others loadable.  The manifest is
    written atomically.  Returns the new manifest."""
    path = Path(path)
    blob = torch.load(path, map_location="cpu", weights_only=False)
    k = int(blob["num_bits"])
    mpath = path.parent / MANIFEST
    manifest = json.loads(mpath.read_text()) if mpath.exists() else {}
    files = {n: e for n, e in manifest.get("files", {}).items() if n != path.name and e.get("num_bits") != k}
    files[path.name] = {"num_bits": k, "sha256": sha256_file(path), "bytes": path.stat().st_size,
                        **(provenance or {})}
    manifest = {**MANIFEST_HEADER, "files": dict(sorted(files.items(), key=lambda e: e[1]["num_bits"]))}
    with atomic_write(mpath, "w") as f:
        f.write(json.dumps(manifest, indent=1) + "\n")
    return manifest


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` through :func:`gsw._atomic.atomic_write` (creating the directory): readers never see
    a partial file and a failed write leaves ``path`` untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        torch.save(obj, f)


def save_decoder(
    decoder: HiddenDecoder, whitening: WhiteningLayer, path: str | Path, meta: dict[str, Any] | None = None
) -> str:
    """Write a decoder + whitening as a float32 state dict; returns its sha256."""
    arch = {"num_blocks": len(decoder.layers) - 1, "channels": decoder.layers[0][0].out_channels,
            "input_norm": decoder.input_norm}
    model = WatermarkDecoder(decoder.num_bits, **arch)
    model.decoder.load_state_dict(decoder.state_dict())
    model.whitening.load_state_dict(whitening.state_dict())
    sd = {k: v.detach().float().cpu().contiguous() if v.is_floating_point() else v.cpu()
          for k, v in model.state_dict().items()}
    blob = {"num_bits": decoder.num_bits, "arch": arch, "state_dict": sd,
            "meta": json.dumps(meta or {})}
    atomic_torch_save(blob, path)
    return sha256_file(path)


def read_provenance(path: str | Path) -> dict[str, Any]:
    """The provenance a decoder file was saved with (:func:`save_decoder`'s ``meta``; what the manifest records).

    Raises:
        WeightsError: the file is unreadable or not a gsw decoder file.
    """
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        return dict(json.loads(blob["meta"]))
    except Exception as e:  # noqa: BLE001 - any failure means a bad file
        raise WeightsError(f"cannot read the provenance of decoder weights {path}: {e}") from e
