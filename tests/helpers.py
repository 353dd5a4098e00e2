"""Shared test helpers (imported by the test modules as `helpers`)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

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
