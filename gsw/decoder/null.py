"""What a decoder reads on unmarked images: the per-decoder null model behind calibrated p-values.

A shipped decoder's bits are not fair coins on unmarked content: each bit has its own P(bit = 1),
measured on calibration images (``benchmarks/calibrate_null.py`` writes ``weights/null_k{bits}.json``
beside the weights).  For a claimed message ``m`` bit ``i`` of an unmarked image matches with probability
``q_i = P(1)_i`` if ``m_i = 1`` else ``1 - P(1)_i``, so the number of matching bits follows a
Poisson-binomial law (:func:`gsw.stats.poisson_binomial_sf`) rather than Binomial(k, 1/2): a message that
agrees with the biases matches unmarked images more often than the fair coin says.

The p-value of ``x`` matching bits under a :class:`NullModel` (:meth:`NullModel.tail_table`) is

    ``max( P(Bin(k, 1/2) >= x),  U_x )``

* ``U_x`` is an upper confidence bound (level :attr:`NullModel.confidence`) on the Poisson-binomial tail
  for the estimation error of ``P(1)``: the tail is evaluated for :attr:`NullModel.draws` draws of the
  per-bit rates from the normal approximation of their estimate (mean :attr:`NullModel.p1`, covariance
  :attr:`NullModel.p1_cov`, computed between calibration *images*, not readings, so several readings of
  one image count once), and the ``confidence`` quantile is taken.  The draws use a fixed seed: the
  p-value is a deterministic function of (model, message, matches).  Bounding the tail as a whole
  rather than each ``q_i`` separately avoids stacking ``k`` worst cases that cannot happen together.
* the fair-coin floor keeps the exact guarantee for a uniformly random message (a key): whatever the
  content, such a message matches like Binomial(k, 1/2), so the null model is only ever used to be more
  careful, never to claim more than the fair coin (e.g. for content unlike the calibration images, where
  the measured ``P(1)`` may not hold).
* bits are treated as independent given the rates; the measured correlations between bits are stored
  (:attr:`NullModel.bit_corr`, summary in :attr:`NullModel.calibration`) so that this can be checked
  (BENCHMARKS.md, "Detection statistics").

The calibration / hold-out split of the shared unmarked photos is fixed by :func:`is_holdout`.

Example:
    >>> import numpy as np
    >>> null = NullModel.fair(32)
    >>> float(null.tail_table(np.ones(32))[30]) == binomial_p_value(30, 32)
    True
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.decoder.zoo import WEIGHTS_DIR, WeightsError, _manifest, weights_path
from gsw.stats import binomial_p_value, poisson_binomial_pmf

__all__ = ["NULL_FORMAT", "NullModel", "NullModelError", "decoder_fingerprint", "fit_null_model",
           "is_holdout", "load_null_model", "null_path"]

NULL_FORMAT = "gsw-null-model/1"
#: Salt of the calibration / hold-out split (:func:`is_holdout`); changing it changes the split.
SPLIT_SALT = "gsw-null-split-v1"
_EPS = 1e-6  # per-bit rates are kept inside [_EPS, 1 - _EPS]


class NullModelError(ValueError):
    """A null-model file is missing or malformed, or belongs to another decoder / bit length."""


def is_holdout(name: str) -> bool:
    """Whether an unmarked image belongs to the HOLD-OUT split (never used for calibration).

    ``name`` is the image's path relative to the shared data folder, e.g. ``"unmarked/sun80/x.jpg"``;
    an image is held out when the first byte of ``sha256(SPLIT_SALT + "/" + name)`` is below 128 (half of
    the images, independent of their content and order)."""
    return hashlib.sha256(f"{SPLIT_SALT}/{name}".encode()).digest()[0] < 128


def decoder_fingerprint(decoder: torch.nn.Module) -> str:
    """sha256 of a decoder's weights (names, dtypes, shapes and float32 values of its state dict, in
    name order): identifies the network independently of how its file was written."""
    h = hashlib.sha256()
    for name, value in sorted(decoder.state_dict().items()):
        t = value.detach().cpu().contiguous()
        t = t.float() if t.is_floating_point() else t
        h.update(f"{name}|{t.dtype}|{list(t.shape)}|".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def _as_bits(values: Any, num_bits: int, what: str) -> np.ndarray:
    a = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values)
    if a.ndim == 0 or a.shape[-1] != num_bits:
        raise ValueError(f"{what} has shape {list(a.shape)}; expected [..., {num_bits}] ({num_bits}-bit null model)")
    if not np.all((a == 0) | (a == 1)):
        raise ValueError(f"{what} must hold bits (0 or 1)")
    return a.astype(np.int8)


@dataclass
class NullModel:
    """Per-bit statistics of a decoder on unmarked images (see the module docstring).

    Attributes:
        num_bits: k.
        p1: [k] P(bit = 1) on unmarked images.
        p1_cov: [k, k] covariance of the estimate ``p1`` (between calibration images / n).
        bit_corr: [k, k] correlation of the bits over the calibration readings (diagonal 1).
        decoder_sha256: sha256 of the decoder's weight file (the manifest's), "" if none.
        decoder_fingerprint: :func:`decoder_fingerprint` of the decoder, "" for a model not tied to one.
        calibration: provenance: images and readings per kind, split, scales, summaries.
        confidence: level of the upper confidence bound on the tail.
        draws: number of draws of the per-bit rates behind that bound.
    """

    num_bits: int
    p1: np.ndarray
    p1_cov: np.ndarray
    bit_corr: np.ndarray
    decoder_sha256: str = ""
    decoder_fingerprint: str = ""
    calibration: dict[str, Any] = field(default_factory=dict)
    confidence: float = 0.95
    draws: int = 2000

    def __post_init__(self) -> None:
        k = self.num_bits
        self.p1 = np.asarray(self.p1, dtype=np.float64)
        self.p1_cov = np.asarray(self.p1_cov, dtype=np.float64)
        self.bit_corr = np.asarray(self.bit_corr, dtype=np.float64)
        for name, shape in (("p1", (k,)), ("p1_cov", (k, k)), ("bit_corr", (k, k))):
            value = getattr(self, name)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise NullModelError(f"null model field {name!r}: expected finite values of shape {list(shape)}, "
                                     f"got {list(value.shape)}")
        if self.p1.min() < 0 or self.p1.max() > 1:
            raise NullModelError("null model field 'p1' must lie in [0, 1]")
        if not 0.5 <= self.confidence < 1 or self.draws < 1:
            raise NullModelError(f"null model: confidence must be in [0.5, 1) and draws >= 1, "
                                 f"got {self.confidence}, {self.draws}")
        self._tables: dict[bytes, np.ndarray] = {}
        self._rates: np.ndarray | None = None

    @classmethod
    def fair(cls, num_bits: int) -> "NullModel":
        """The fair-coin model (every P(1) = 1/2 exactly): its p-values are the binomial ones."""
        return cls(num_bits, np.full(num_bits, 0.5), np.zeros((num_bits, num_bits)), np.eye(num_bits))

    # ---------------------------------------------------------------------------------- p-values
    def _rate_draws(self) -> np.ndarray:
        """[draws, k] per-bit P(1) drawn from the estimate's normal approximation (fixed seed)."""
        if self._rates is None:
            vals, vecs = np.linalg.eigh((self.p1_cov + self.p1_cov.T) / 2)
            root = vecs * np.sqrt(np.clip(vals, 0.0, None))
            z = np.random.default_rng(0).standard_normal((self.draws, self.num_bits))
            self._rates = np.clip(self.p1 + z @ root.T, _EPS, 1.0 - _EPS)
        return self._rates

    def tail_table(self, message: Any) -> np.ndarray:
        """p-value of each possible number of matching bits with ``message``.

        Args:
            message: [k] bits (0/1; tensor, array or list).

        Returns:
            [k + 2] float64: entry ``x`` is the p-value of ``x`` matching bits (entry ``k + 1`` is 0), the
            maximum of the fair-coin tail and the upper confidence bound on the Poisson-binomial tail.
        """
        m = _as_bits(message, self.num_bits, "message").reshape(-1)
        key = np.packbits(m).tobytes()
        table = self._tables.get(key)
        if table is None:
            rates = self._rate_draws()
            q = np.where(m[None, :] == 1, rates, 1.0 - rates)  # [draws, k] P(bit i matches)
            pmf = poisson_binomial_pmf(q)
            tails = np.cumsum(pmf[:, ::-1], axis=1)[:, ::-1]  # [draws, k + 1]
            bound = np.quantile(tails, self.confidence, axis=0, method="higher")
            fair = np.array([binomial_p_value(x, self.num_bits) for x in range(self.num_bits + 1)])
            table = np.append(np.minimum(1.0, np.maximum(fair, bound)), 0.0)
            table[0] = 1.0
            if len(self._tables) < 4096:
                self._tables[key] = table
        return table

    def p_values(self, bits: Any, message: Any) -> np.ndarray:
        """p-values of decoded bits against a message.

        Args:
            bits: [..., k] decoded bits of images (0/1).
            message: [k] the claimed message.

        Returns:
            [...] float64 p-values (:meth:`tail_table` at each image's number of matching bits).
        """
        b = _as_bits(bits, self.num_bits, "decoded bits")
        m = _as_bits(message, self.num_bits, "message").reshape(-1)
        return self.tail_table(m)[(b == m).sum(axis=-1)]

    # ---------------------------------------------------------------------------------- files
    def check_decoder(self, decoder: torch.nn.Module) -> None:
        """Raises :class:`NullModelError` unless ``decoder`` is the one this model was calibrated for."""
        k = getattr(decoder, "num_bits", self.num_bits)
        if k != self.num_bits:
            raise NullModelError(f"null model of a {self.num_bits}-bit decoder given with a {k}-bit decoder")
        if self.decoder_fingerprint:
            actual = decoder_fingerprint(decoder)
            if actual != self.decoder_fingerprint:
                raise NullModelError(
                    f"null model was calibrated for the decoder with fingerprint {self.decoder_fingerprint[:16]}... "
                    f"(weights sha256 {self.decoder_sha256[:16]}...), not for this decoder ({actual[:16]}...): "
                    "recalibrate it (benchmarks/calibrate_null.py) or pass the matching null model")

    def to_dict(self) -> dict[str, Any]:
        r = lambda a: np.round(a, 6).tolist()  # noqa: E731
        return {"format": NULL_FORMAT, "num_bits": self.num_bits, "decoder_sha256": self.decoder_sha256,
                "decoder_fingerprint": self.decoder_fingerprint, "confidence": self.confidence,
                "draws": self.draws, "p1": r(self.p1), "p1_cov": np.round(self.p1_cov, 9).tolist(),
                "bit_corr": np.round(self.bit_corr, 4).tolist(), "calibration": self.calibration}

    def save(self, path: str | Path) -> Path:
        """Writes the model as JSON (atomically). Returns the path."""
        path = Path(path)
        with atomic_write(path, "w") as f:
            f.write(json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "null model") -> "NullModel":
        if not isinstance(d, dict) or d.get("format") != NULL_FORMAT:
            raise NullModelError(f"{source}: not a gsw null model (expected format {NULL_FORMAT!r})")
        try:
            return cls(int(d["num_bits"]), np.asarray(d["p1"]), np.asarray(d["p1_cov"]), np.asarray(d["bit_corr"]),
                       str(d.get("decoder_sha256", "")), str(d.get("decoder_fingerprint", "")),
                       dict(d.get("calibration", {})), float(d.get("confidence", 0.95)), int(d.get("draws", 2000)))
        except KeyError as e:
            raise NullModelError(f"{source}: missing field {e.args[0]!r}") from e
        except (TypeError, ValueError) as e:
            if isinstance(e, NullModelError):
                raise NullModelError(f"{source}: {e}") from e
            raise NullModelError(f"{source}: malformed field: {e}") from e

    @classmethod
    def load(cls, path: str | Path) -> "NullModel":
        path = Path(path)
        if not path.is_file():
            raise NullModelError(f"null model file not found: {path}")
        try:
            d = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise NullModelError(f"null model file {path} is not valid JSON: {e}") from e
        return cls.from_dict(d, str(path))


def null_path(num_bits: int, weights_dir: str | Path | None = None) -> Path:
    """Path of the shipped null model of the ``num_bits`` decoder (beside its weights)."""
    return Path(weights_dir or WEIGHTS_DIR) / f"null_k{num_bits}.json"


def load_null_model(num_bits: int, path: str | Path | None = None, *,
                    weights_dir: str | Path | None = None) -> NullModel:
    """Loads a null model and checks that it belongs to a ``num_bits`` decoder.

    Args:
        num_bits: bit length of the decoder it is used with.
        path: a null-model JSON file; default: the shipped one, which must also name the sha256 that the
            weights manifest lists for the shipped decoder.
        weights_dir: directory of the shipped files (tests).

    Raises:
        NullModelError: missing/malformed file, another bit length, or a shipped model whose decoder
            sha256 differs from the manifest's (the decoder was replaced without recalibrating).
    """
    shipped = path is None
    path = null_path(num_bits, weights_dir) if shipped else Path(path)
    model = NullModel.load(path)
    if model.num_bits != num_bits:
        raise NullModelError(f"{path} is the null model of a {model.num_bits}-bit decoder, {num_bits} bits were asked for")
    if shipped:
        wdir = Path(weights_dir or WEIGHTS_DIR)
        try:
            entry = _manifest(wdir).get("files", {}).get(weights_path(num_bits, wdir).name, {})
        except WeightsError as e:
            raise NullModelError(f"cannot check {path} against the decoder: {e}") from e
        if entry.get("sha256") != model.decoder_sha256:
            raise NullModelError(f"{path} was calibrated for decoder weights sha256 {model.decoder_sha256[:16]}..., "
                                 f"but the manifest lists {str(entry.get('sha256'))[:16]}...: recalibrate "
                                 "(benchmarks/calibrate_null.py)")
    return model


def _round(a: np.ndarray, d: int = 4) -> list:
    return np.round(np.asarray(a, dtype=np.float64), d).tolist()


def fit_null_model(records: list[dict[str, Any]], num_bits: int, *, decoder: torch.nn.Module | None = None,
                   decoder_sha256: str = "", provenance: dict[str, Any] | None = None,
                   confidence: float = 0.95, draws: int = 2000) -> NullModel:
    """Estimates a null model from decoded unmarked readings.

    Args:
        records: one dict per reading: ``name`` (the image it comes from), ``kind`` (e.g. "photo",
            "manga", "render"), ``factor`` (read factor), ``bits`` ([k] 0/1).
        num_bits: k.
        decoder: the decoder that produced the bits (its :func:`decoder_fingerprint` is stored).
        decoder_sha256: sha256 of its weight file.
        provenance: stored under ``calibration`` (data, split, versions).
        confidence, draws: see :class:`NullModel`.

    Returns:
        the model: ``p1`` is the mean over images of each image's mean over its readings (every image
        counts once), ``p1_cov`` the covariance of those per-image means divided by the number of images,
        ``bit_corr`` the correlation of the bits over all readings.
    """
    if not records:
        raise ValueError("no calibration readings")
    names = sorted({r["name"] for r in records})
    index = {n: i for i, n in enumerate(names)}
    bits = _as_bits([r["bits"] for r in records], num_bits, "calibration bits").astype(np.float64)
    owner = np.array([index[r["name"]] for r in records])
    counts = np.bincount(owner, minlength=len(names)).astype(np.float64)
    per_image = np.zeros((len(names), num_bits))
    np.add.at(per_image, owner, bits)
    per_image /= counts[:, None]
    n = len(names)
    p1 = per_image.mean(0)
    p1_cov = np.cov(per_image, rowvar=False) / n if n > 1 else np.zeros((num_bits, num_bits))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.corrcoef(bits, rowvar=False)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    kinds: dict[str, Any] = {}
    kind_of = {r["name"]: r["kind"] for r in records}
    for kind in sorted(set(kind_of.values())):
        sel = np.array([kind_of[nm] == kind for nm in names])
        kp = per_image[sel].mean(0)
        kinds[kind] = {"images": int(sel.sum()), "readings": int(counts[sel].sum()), "p1": _round(kp, 3),
                       "max_abs_dev": round(float(np.abs(kp - 0.5).max()), 4)}
    factors: dict[str, Any] = {}
    for f in sorted({round(float(r["factor"]), 4) for r in records}):
        sel = np.array([round(float(r["factor"]), 4) == f for r in records])
        fp = bits[sel].mean(0)
        factors[f"{f:g}"] = {"readings": int(sel.sum()), "max_abs_dev": round(float(np.abs(fp - 0.5).max()), 4)}
    off = corr[~np.eye(num_bits, dtype=bool)]
    calibration = {
        "images": n, "readings": len(records), "kinds": kinds, "factors": factors,
        "max_abs_dev": round(float(np.abs(p1 - 0.5).max()), 4),
        "p1_se": _round(np.sqrt(np.diag(p1_cov)), 4),
        "bit_corr_mean_abs": round(float(np.abs(off).mean()), 4) if off.size else 0.0,
        "bit_corr_max_abs": round(float(np.abs(off).max()), 4) if off.size else 0.0,
        **(provenance or {}),
    }
    return NullModel(num_bits, p1, p1_cov, corr, decoder_sha256,
                     decoder_fingerprint(decoder) if decoder is not None else "", calibration, confidence, draws)
