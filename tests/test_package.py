"""Package layout: lazy top-level names, subpackages that work without the compiled extension."""

from __future__ import annotations

import subprocess
import sys

import pytest

from helpers import BLOCK_EXTENSION



@pytest.mark.parametrize("module", ["gsw.decoder", "gsw.attacks", "gsw.attacks.layers", "gsw.metrics",
                                    "gsw.metrics.lpips", "gsw.stats"])
def test_torch_only_subpackages_import_without_the_extension(module: str) -> None:
    code = BLOCK_EXTENSION + f"import {module}\nassert 'gsw._C' not in sys.modules\nprint('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_rendering_without_the_extension_names_the_problem() -> None:
    code = BLOCK_EXTENSION + "import gsw\ngsw.rasterize"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "compiled rasterizer extension (gsw._C) could not be loaded" in out.stderr
    assert "--no-build-isolation" in out.stderr


def test_top_level_names_resolve_lazily() -> None:
    import gsw

    for name in gsw.__all__:
        assert getattr(gsw, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        gsw.nope  # noqa: B018


def test_python_dash_m_gsw_runs_the_cli() -> None:
    out = subprocess.run([sys.executable, "-m", "gsw", "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "embed" in out.stdout
