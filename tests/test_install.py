"""Installation: declared dependencies, the torch the extension was built against (and the clear error
under another torch), the README install block that .ci/fresh_install.sh runs, and CMake's advice when
the build cannot see torch. The fresh-venv run itself is the CI step .ci/fresh_install.sh."""

from __future__ import annotations

import ast
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import gsw

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
#: import name -> distribution name, where they differ.
DIST_OF = {"PIL": "pillow"}


def _requirement_names(reqs: list[str]) -> set[str]:
    return {re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower() for r in reqs}


def _third_party_imports(module_level: bool) -> set[str]:
    """Top-level names of non-stdlib modules imported by gsw/ (at module level, or only inside functions)."""
    found: set[str] = set()
    for path in (ROOT / "gsw").rglob("*.py"):
        tree = ast.parse(path.read_text(), str(path))
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            in_try = any(isinstance(n, ast.Try) and node in ast.walk(n) for n in tree.body)
            if (id(node) in top or in_try) != module_level:
                continue
            found |= {n.split(".")[0] for n in names}
    return {n for n in found if n not in sys.stdlib_module_names and n not in ("gsw", "__future__")}


def test_runtime_dependencies_are_declared() -> None:
    declared = _requirement_names(PYPROJECT["project"]["dependencies"])
    used = {DIST_OF.get(n, n).lower() for n in _third_party_imports(module_level=True)}
    assert used <= declared, f"imported at module level but not in [project].dependencies: {used - declared}"
    assert {"torch", "numpy", "kornia", "pillow"} <= declared


def test_lazily_imported_optional_packages_have_extras() -> None:
    extras = PYPROJECT["project"]["optional-dependencies"]
    lazy = _third_party_imports(module_level=False) - _third_party_imports(module_level=True)
    declared = _requirement_names(PYPROJECT["project"]["dependencies"])
    covered = declared | {"kornia_rs"}  # kornia_rs: a dependency of kornia (faster JPEG decoding when present)
    for group in extras.values():
        covered |= _requirement_names(group)
    assert {DIST_OF.get(n, n).lower() for n in lazy} <= covered
    assert _requirement_names(extras["video"]) == {"av"} and _requirement_names(extras["plots"]) == {"matplotlib"}
    assert "pycolmap" in _requirement_names(extras["colmap"]) and "pytest" in _requirement_names(extras["test"])


def test_torch_is_not_a_build_requirement() -> None:
    # An isolated build would otherwise fetch a torch other than the one the extension must run with.
    assert "torch" not in _requirement_names(PYPROJECT["build-system"]["requires"])


def test_weights_are_package_data() -> None:
    assert PYPROJECT["tool"]["scikit-build"]["wheel"]["packages"] == ["gsw"]
    files = [ROOT / "gsw" / "metrics" / "weights" / f"lpips_{n}.npz" for n in ("vgg", "alex")]
    assert all(f.is_file() for f in files)
    if shutil.which("git") and (ROOT / ".git").exists():  # scikit-build-core leaves git-ignored files out
        out = subprocess.run(["git", "-C", str(ROOT), "check-ignore", *map(str, files)], capture_output=True)
        assert out.returncode == 1, out.stdout


# ------------------------------------------------------------------------ the torch it was built with
def test_build_info_records_the_torch_it_was_built_against() -> None:
    from gsw import _ext

    info = gsw.build_info()
    assert info["built_with_torch"] == torch.__version__ == info["torch"]  # this suite runs with the build's torch
    origin = importlib.util.find_spec("gsw._C").origin
    assert _ext.built_with_torch(origin) == info["built_with_torch"]  # readable without loading the module


def test_mismatch_message_names_both_versions_and_the_rebuild() -> None:
    from gsw._ext import REBUILD_HINT, torch_mismatch_message

    msg = torch_mismatch_message("2.12.1+cu126", "2.13.0+cpu")
    assert "2.12.1+cu126" in msg and "2.13.0+cpu" in msg and REBUILD_HINT in msg
    assert "--no-build-isolation" in REBUILD_HINT
    assert torch_mismatch_message("2.13.1", "2.13.0+cpu") is None  # same major.minor
    assert torch_mismatch_message(None, "2.13.0") is None and torch_mismatch_message("unknown", "2.13.0") is None


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_loaded_extension_under_another_torch_raises() -> None:
    out = _run("import torch\ntorch.__version__ = '9.1.0'\nimport gsw._ext")
    assert out.returncode != 0
    assert f"built against torch {torch.__version__}, but torch 9.1.0 is installed" in out.stderr
    assert "--no-build-isolation" in out.stderr


def test_unloadable_extension_under_another_torch_names_both_versions(tmp_path: Path) -> None:
    fake = tmp_path / "_C.so"
    fake.write_bytes(b"\x7fELF junk gsw-built-with-torch=1.99.0\0 more junk")
    code = f"""
import importlib.abc, importlib.machinery, sys
class _Loader(importlib.abc.Loader):
    def create_module(self, spec):
        raise ImportError("undefined symbol: _ZN3c104impl8GPUTrace")
    def exec_module(self, module):
        pass
class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "gsw._C":
            return importlib.machinery.ModuleSpec(name, _Loader(), origin={str(fake)!r})
sys.meta_path.insert(0, _Finder())
import gsw._ext
"""
    out = _run(code)
    assert out.returncode != 0
    assert f"built against torch 1.99.0, but torch {torch.__version__} is installed" in out.stderr
    assert "undefined symbol" in out.stderr and "--force-reinstall" in out.stderr


# ------------------------------------------------------------------------------ README install block
def _readme_install_block() -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Install into your own environment"):]
    section = section[: section.index("\n## ", 3)]
    return re.search(r"```bash\n(.*?)```", section, re.S).group(1)


def test_fresh_install_script_runs_the_readme_block_verbatim() -> None:
    out = subprocess.run(["bash", str(ROOT / ".ci" / "fresh_install.sh"), "--print-commands"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout == _readme_install_block()
    lines = [ln.split("#")[0].strip() for ln in out.stdout.splitlines()]
    assert lines[0].startswith("pip install torch") and "pip install --no-build-isolation ." in lines


def test_ci_runs_the_fresh_install_after_the_tests() -> None:
    steps = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()
             if ln.strip() and not ln.startswith("#") and not ln.startswith(("set ", "cd "))]
    assert steps.index("make test") < steps.index("bash .ci/fresh_install.sh")


# ------------------------------------------------------------------------ CMake without a usable torch
def test_cmake_explains_a_build_that_cannot_import_torch(tmp_path: Path) -> None:
    base = Path(sys.base_prefix) / "bin" / f"python{sys.version_info.major}.{sys.version_info.minor}"
    cmake = shutil.which("cmake") or str(Path(sys.executable).parent / "cmake")
    if not base.is_file() or not Path(cmake).is_file():
        pytest.skip("needs cmake and the base interpreter of this venv")
    if subprocess.run([str(base), "-c", "import torch"], capture_output=True).returncode == 0:
        pytest.skip("the base interpreter imports torch: no Python without torch to configure with")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([cmake, "-S", str(ROOT), "-B", str(tmp_path), f"-DPython_EXECUTABLE={base}"],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode != 0
    assert "cannot import torch" in out.stderr and "pip install --no-build-isolation ." in out.stderr
