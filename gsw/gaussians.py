"""The :class:`Gaussians` container: a 3D Gaussian Splatting model in its raw (pre-activation) parameters.

Storage follows the INRIA 3DGS conventions (see ``GUIDE.md`` section 3):

- ``means`` are world-space positions,
- ``log_scales`` are per-axis log standard deviations (``scales = exp(log_scales)``),
- ``quats`` are unnormalised quaternions ``(w, x, y, z)`` (``rotations`` normalises them),
- ``opacity_logits`` are pre-sigmoid opacities,
- ``sh`` holds the spherical-harmonic colour coefficients ``[N, K, 3]`` with ``K = (d + 1)^2``;
  ``sh[:, 0]`` is the DC term (``f_dc``) and ``sh[:, 1:]`` the higher orders (``f_rest``) in
  coefficient-major order, i.e. ``sh[n, k, c]`` is coefficient ``k`` of colour channel ``c``.

Example:
    >>> import torch
    >>> from gsw.gaussians import Gaussians
    >>> g = Gaussians.empty(sh_degree=1)
    >>> len(g), g.sh_degree
    (0, 1)
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Sequence, Union

import torch
from torch import Tensor

__all__ = [
    "Gaussians", "cat_gaussians", "sh_degree_to_num_coeffs", "num_coeffs_to_sh_degree", "rgb_to_sh_dc",
    "sh_dc_to_rgb", "quat_to_rotmat", "rotmat_to_quat",
]

_MAX_DEGREE = 3

Index = Union[int, slice, Tensor, Sequence[int]]


def sh_degree_to_num_coeffs(degree: int) -> int:
    """Number of SH coefficients per colour channel for a degree: ``(degree + 1)^2``.

    Args:
        degree: SH degree in ``0..3``.

    Returns:
        ``K`` in ``{1, 4, 9, 16}``.

    Raises:
        ValueError: if the degree is outside ``0..3``.
    """
    if not isinstance(degree, int) or isinstance(degree, bool) or not 0 <= degree <= _MAX_DEGREE:
        raise ValueError(f"SH degree must be an int in 0..{_MAX_DEGREE}, got {degree!r}")
    return (degree + 1) ** 2


def num_coeffs_to_sh_degree(num_coeffs: int) -> int:
    """Inverse of :func:`sh_degree_to_num_coeffs`.

    Args:
        num_coeffs: ``K``, the number of SH coefficients per channel.

    Returns:
        The SH degree ``d`` with ``(d + 1)^2 == K``.

    Raises:
        ValueError: if ``K`` is not one of 1, 4, 9, 16.
    """
    for d in range(_MAX_DEGREE + 1):
        if (d + 1) ** 2 == num_coeffs:
            return d
    raise ValueError(f"number of SH coefficients must be 1, 4, 9 or 16 (degree 0..3), got {num_coeffs}")


def sh_dc_to_rgb(f_dc: Tensor) -> Tensor:
    """View-independent colour of a DC SH coefficient: ``rgb = SH_COLOR_OFFSET + SH_C0 * f_dc``.

    The one implementation of this conversion (the constants come from the compiled extension,
    :mod:`gsw.constants`, imported on first call so that this module imports without it).

    Args:
        f_dc: ``[..., 3]`` DC coefficients (``sh[:, 0]``), any float dtype/device.

    Returns:
        ``[..., 3]`` RGB, same dtype/device, not clamped.
    """
    from gsw.constants import SH_C0, SH_COLOR_OFFSET  # noqa: PLC0415 - needs the compiled extension

    return SH_COLOR_OFFSET + SH_C0 * f_dc


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """Inverse of :func:`sh_dc_to_rgb`: ``f_dc = (rgb - SH_COLOR_OFFSET) / SH_C0``.

    Args:
        rgb: ``[..., 3]`` colours (usually in ``[0, 1]``), any float dtype/device.

    Returns:
        ``[..., 3]`` DC SH coefficients, same dtype/device.
    """
    from gsw.constants import SH_C0, SH_COLOR_OFFSET  # noqa: PLC0415 - needs the compiled extension

    return (rgb - SH_COLOR_OFFSET) / SH_C0



def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrices of quaternions ``(w, x, y, z)`` (normalised first).

    Args:
        q: ``[..., 4]`` quaternions.

    Returns:
        ``[..., 3, 3]`` rotation matrices (``R @ v`` rotates ``v``).
    """
    q = torch.nn.functional.normalize(q, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(r: Tensor) -> Tensor:
    """Unit quaternions ``(w, x, y, z)`` with ``w >= 0`` of rotation matrices (inverse of :func:`quat_to_rotmat`).

    Each quaternion is computed from the largest of ``1 + trace`` and ``1 + 2 r_ii - trace`` (Shepperd's
    method), which keeps it accurate for every rotation angle.

    Args:
        r: ``[..., 3, 3]`` rotation matrices.

    Returns:
        ``[..., 4]`` unit quaternions.
    """
    m = r.reshape(-1, 3, 3)
    r00, r11, r22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    trace = r00 + r11 + r22
    # Candidate k has its k-th component (w, x, y, z) computed from the diagonal, the others from sums.
    four = torch.stack([1 + trace, 1 + 2 * r00 - trace, 1 + 2 * r11 - trace, 1 + 2 * r22 - trace], dim=1)
    big = torch.sqrt(four.clamp_min(1e-12))  # 2 |q_k|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s10, s20, s21 = m[:, 1, 0] + m[:, 0, 1], m[:, 2, 0] + m[:, 0, 2], m[:, 2, 1] + m[:, 1, 2]
    candidates = torch.stack([
        torch.stack([big[:, 0] ** 2, d21, d02, d10], dim=1) / (2 * big[:, :1]),
        torch.stack([d21, big[:, 1] ** 2, s10, s20], dim=1) / (2 * big[:, 1:2]),
        torch.stack([d02, s10, big[:, 2] ** 2, s21], dim=1) / (2 * big[:, 2:3]),
        torch.stack([d10, s20, s21, big[:, 3] ** 2], dim=1) / (2 * big[:, 3:4]),
    ], dim=1)
    q = candidates[torch.arange(len(m)), four.argmax(dim=1)]
    q = torch.nn.functional.normalize(q, dim=-1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(r.shape[:-2] + (4,))


@dataclass(eq=False)
class Gaussians:
    """A set of ``N`` 3D Gaussians in raw (pre-activation) parameters.

    All tensors share one device and one floating-point dtype.

    Attributes:
        means: ``[N, 3]`` centres, world frame.
        log_scales: ``[N, 3]`` log of the per-axis standard deviations, Gaussian's local frame.
        quats: ``[N, 4]`` rotation local-to-world as unnormalised quaternions ``(w, x, y, z)``.
        opacity_logits: ``[N]`` opacities before the sigmoid.
        sh: ``[N, K, 3]`` SH colour coefficients, ``K = (d + 1)^2`` with ``d`` in ``0..3``;
            ``sh[:, 0]`` is ``f_dc``, ``sh[:, 1:]`` is ``f_rest`` (coefficient-major).
    """

    means: Tensor
    log_scales: Tensor
    quats: Tensor
    opacity_logits: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, Tensor):
                raise ValueError(f"Gaussians.{f.name} must be a torch.Tensor, got {type(value).__name__}")
            if not value.is_floating_point():
                raise ValueError(f"Gaussians.{f.name} must be a floating-point tensor, got dtype {value.dtype}")
        if self.means.dim() != 2 or self.means.shape[1] != 3:
            raise ValueError(f"Gaussians.means must have shape [N, 3], got {list(self.means.shape)}")
        n = self.means.shape[0]
        for name, shape, text in (
            ("log_scales", (n, 3), "[N, 3]"),
            ("quats", (n, 4), "[N, 4]"),
            ("opacity_logits", (n,), "[N]"),
        ):
            actual = tuple(getattr(self, name).shape)
            if actual != shape:
                raise ValueError(f"Gaussians.{name} must have shape {text} with N={n}, got {list(actual)}")
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh must have shape [N, K, 3] with N={n}, got {list(self.sh.shape)}")
        try:
            num_coeffs_to_sh_degree(self.sh.shape[1])
        except ValueError as exc:
            raise ValueError(f"Gaussians.sh: {exc}") from None
        for f in fields(self):
            value = getattr(self, f.name)
            if value.device != self.means.device:
                raise ValueError(
                    f"Gaussians.{f.name} is on {value.device} but means is on {self.means.device}"
                )
            if value.dtype != self.means.dtype:
                raise ValueError(f"Gaussians.{f.name} has dtype {value.dtype} but means has {self.means.dtype}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(
        cls,
        sh_degree: int = 3,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> "Gaussians":
        """Zero Gaussians of a given SH degree.

        Args:
            sh_degree: SH degree in ``0..3``.
            dtype: floating-point dtype.
            device: device (default CPU).

        Returns:
            A :class:`Gaussians` with ``N = 0``.
        """
        k = sh_degree_to_num_coeffs(sh_degree)
        kw = {"dtype": dtype, "device": device}
        return cls(
            means=torch.zeros(0, 3, **kw),
            log_scales=torch.zeros(0, 3, **kw),
            quats=torch.zeros(0, 4, **kw),
            opacity_logits=torch.zeros(0, **kw),
            sh=torch.zeros(0, k, 3, **kw),
        )

    @classmethod
    def cat(cls, items: Sequence["Gaussians"]) -> "Gaussians":
        """Concatenate along ``N``; see :func:`cat_gaussians`."""
        return cat_gaussians(items)

    # ------------------------------------------------------------------ basic properties
    @property
    def num_gaussians(self) -> int:
        """``N``, the number of Gaussians."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def sh_degree(self) -> int:
        """SH degree ``d`` in ``0..3`` (``K = (d + 1)^2``)."""
        return num_coeffs_to_sh_degree(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        """Device of every tensor."""
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating-point dtype of every tensor."""
        return self.means.dtype

    @property
    def scales(self) -> Tensor:
        """``[N, 3]`` per-axis standard deviations ``exp(log_scales)``."""
        return self.log_scales.exp()

    @property
    def opacities(self) -> Tensor:
        """``[N]`` opacities in ``(0, 1)``: ``sigmoid(opacity_logits)``."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def rotations(self) -> Tensor:
        """``[N, 4]`` unit quaternions ``(w, x, y, z)`` (a zero quaternion stays zero)."""
        return torch.nn.functional.normalize(self.quats, dim=-1)

    def parameters(self) -> dict[str, Tensor]:
        """The raw tensors by field name (``means``, ``log_scales``, ``quats``, ``opacity_logits``, ``sh``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def _map(self, fn) -> "Gaussians":
        return Gaussians(**{name: fn(t) for name, t in self.parameters().items()})

    # ------------------------------------------------------------------ conversions
    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Gaussians":
        """Move and/or cast every tensor.

        Args:
            device: target device (unchanged if ``None``).
            dtype: target floating-point dtype (unchanged if ``None``).

        Returns:
            A new :class:`Gaussians` (tensors are shared when nothing changes).
        """
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def clone(self) -> "Gaussians":
        """Deep copy of every tensor (autograd history is kept, like ``Tensor.clone``)."""
        return self._map(lambda t: t.clone())

    def detach(self) -> "Gaussians":
        """Tensors detached from the autograd graph (storage shared)."""
        return self._map(lambda t: t.detach())

    def requires_grad_(self, requires_grad: bool = True) -> "Gaussians":
        """Set ``requires_grad`` on every tensor in place.

        Returns:
            ``self``, for chaining.
        """
        for t in self.parameters().values():
            t.requires_grad_(requires_grad)
        return self

    def __getitem__(self, index: Index) -> "Gaussians":
        """Select Gaussians along ``N``.

        Args:
            index: an ``int`` (gives ``N = 1``), a ``slice``, a bool mask ``[N]`` or an integer index
                tensor/sequence ``[M]``.

        Returns:
            The selected Gaussians (a view for ``int``/``slice``, a copy otherwise).
        """
        n = self.num_gaussians
        if isinstance(index, bool):
            raise TypeError("Gaussians cannot be indexed with a bool")
        if isinstance(index, int):
            i = index + n if index < 0 else index
            if not 0 <= i < n:
                raise IndexError(f"index {index} is out of range for {n} Gaussians")
            index = slice(i, i + 1)
        elif not isinstance(index, (slice, Tensor)):
            index = torch.as_tensor(index, dtype=torch.long)
        if isinstance(index, Tensor):
            if index.dtype == torch.bool:
                if index.shape != (n,):
                    raise IndexError(f"bool mask must have shape [{n}], got {list(index.shape)}")
            elif index.dtype not in (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8):
                raise IndexError(f"index tensor must be bool or integer, got {index.dtype}")
            elif index.dim() != 1:
                raise IndexError(f"index tensor must be 1-D, got shape {list(index.shape)}")
            index = index.to(self.device)
            if index.dtype != torch.bool:
                index = index.long()
        return self._map(lambda t: t[index])

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """Truncate or zero-pad the SH coefficients to another degree.

        Args:
            degree: target SH degree in ``0..3``.

        Returns:
            New Gaussians with ``sh [N, (degree + 1)^2, 3]``; other tensors are shared.
        """
        k = sh_degree_to_num_coeffs(degree)
        k0 = self.sh.shape[1]
        if k <= k0:
            sh = self.sh[:, :k]
        else:
            pad = self.sh.new_zeros(self.num_gaussians, k - k0, 3)
            sh = torch.cat([self.sh, pad], dim=1)
        return Gaussians(self.means, self.log_scales, self.quats, self.opacity_logits, sh)

    def check_finite(self) -> "Gaussians":
        """Raise if any parameter is NaN or infinite.

        Returns:
            ``self``, for chaining.

        Raises:
            ValueError: naming every offending field and how many Gaussians (rows) are affected.
        """
        problems = []
        for name, t in self.parameters().items():
            bad = ~torch.isfinite(t.detach())
            if bad.any():
                rows = int(bad.reshape(t.shape[0], -1).any(dim=1).sum()) if t.dim() > 1 else int(bad.sum())
                problems.append(f"{name}: {rows} of {self.num_gaussians} rows contain NaN/Inf")
        if problems:
            raise ValueError("non-finite Gaussian parameters: " + "; ".join(problems))
        return self

    def __repr__(self) -> str:
        return (
            f"Gaussians(N={self.num_gaussians}, sh_degree={self.sh_degree}, "
            f"dtype={self.dtype}, device={self.device})"
        )


def cat_gaussians(items: Sequence[Gaussians]) -> Gaussians:
    """Concatenate Gaussians along ``N``.

    Inputs of lower SH degree are zero-padded to the highest degree present (which renders identically).

    Args:
        items: one or more :class:`Gaussians` on the same device with the same dtype.

    Returns:
        The concatenation, ``N = sum(len(g) for g in items)``.

    Raises:
        ValueError: if ``items`` is empty or devices/dtypes differ.
    """
    items = list(items)
    if not items:
        raise ValueError("cat_gaussians needs at least one Gaussians")
    for g in items[1:]:
        if g.device != items[0].device or g.dtype != items[0].dtype:
            raise ValueError(
                f"cannot concatenate Gaussians on {g.device}/{g.dtype} with {items[0].device}/{items[0].dtype}"
            )
    degree = max(g.sh_degree for g in items)
    items = [g.with_sh_degree(degree) if g.sh_degree != degree else g for g in items]
    return Gaussians(
        **{name: torch.cat([g.parameters()[name] for g in items], dim=0) for name in items[0].parameters()}
    )
