"""Shared test helpers (imported by the test modules as `helpers`)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from gsw.gaussians import Gaussians

#: ../shared/data beside the project root (also present in CI).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def require(path: Path, what: str = "test data") -> Path:
    """Returns `path` if it exists; otherwise fails under CI (env CI set) and skips elsewhere."""
    if not Path(path).exists():
        message = f"missing {what}: {path}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return Path(path)


def random_model(n: int, degree: int = 3, seed: int = 0) -> Gaussians:
    """n seeded random Gaussians (unnormalised quaternions, small scales, SH coefficients in [-1, 1))."""
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g) * 2,
        sh=torch.rand(n, (degree + 1) ** 2, 3, generator=g) * 2 - 1,
    )


#: Python source that makes ``import gsw._C`` fail (prepend to ``python -c`` code run in a subprocess).
BLOCK_EXTENSION = """
import importlib.abc, sys
class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "gsw._C":
            raise ImportError("blocked for the test")
sys.meta_path.insert(0, _Block())
"""
