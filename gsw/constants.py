"""Rasterizer constants, read from the compiled extension (single source: csrc/core/constants.h).

Example:
    >>> from gsw.constants import ALPHA_MIN, TILE_SIZE
    >>> TILE_SIZE
    16
"""

from __future__ import annotations

from gsw._ext import _C

_constants = _C.constants

TILE_SIZE: int = int(_constants["TILE_SIZE"])
NEAR_PLANE: float = float(_constants["NEAR_PLANE"])
COV2D_DILATION: float = float(_constants["COV2D_DILATION"])
FRUSTUM_CLAMP: float = float(_constants["FRUSTUM_CLAMP"])
RADIUS_SIGMAS: float = float(_constants["RADIUS_SIGMAS"])
EIGEN_FLOOR: float = float(_constants["EIGEN_FLOOR"])
ALPHA_MAX: float = float(_constants["ALPHA_MAX"])
ALPHA_MIN: float = float(_constants["ALPHA_MIN"])
T_MIN: float = float(_constants["T_MIN"])
SKIP_LOG_MARGIN: float = float(_constants["SKIP_LOG_MARGIN"])
MAX_SH_DEGREE: int = int(_constants["MAX_SH_DEGREE"])
SH_COLOR_OFFSET: float = float(_constants["SH_COLOR_OFFSET"])
SH_C0: float = float(_constants["SH_C0"])
SH_C1: float = float(_constants["SH_C1"])
SH_C2: tuple[float, ...] = tuple(float(v) for v in _constants["SH_C2"])
SH_C3: tuple[float, ...] = tuple(float(v) for v in _constants["SH_C3"])

__all__ = [
    "TILE_SIZE", "NEAR_PLANE", "COV2D_DILATION", "FRUSTUM_CLAMP", "RADIUS_SIGMAS", "EIGEN_FLOOR",
    "ALPHA_MAX", "ALPHA_MIN", "T_MIN", "SKIP_LOG_MARGIN", "MAX_SH_DEGREE", "SH_COLOR_OFFSET", "SH_C0", "SH_C1",
    "SH_C2", "SH_C3",
]
