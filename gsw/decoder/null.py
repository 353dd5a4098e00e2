"""What a decoder reads on unmarked images: the per-decoder null model behind calibrated p-values.

A shipped decoder's bits are not fair coins on unmarked content: each bit has its own P(bit = 1), which
also depends on the kind of content (photos, drawings, renders) and on whether the image was enlarged
before reading, and bits are correlated.  ``benchmarks/calibrate_null.py`` measures this on calibration
images and writes ``weights/null_k{bits}.json`` beside the weights (``null_k{bits}_klein.json`` for the decoder
read through :class:`gsw.decoder.KleinReadout`, ``--readout klein``): one :class:`Stratum` per (content kind,
reading direction) with enough images.

For a claimed message ``m``, bit ``i`` of an unmarked image matches with probability ``q_i = P(1)_i`` if
``m_i = 1`` else ``1 - P(1)_i``.  The p-value of ``x`` matching bits (:meth:`NullModel.tail_table`) is

    ``max( P(Bin(k, 1/2) >= x),  max over strata s of U_s(x) )``,

    ``U_s(x) = min(1, Q_c[ T(x; q*) ] * G(z, lambda))``

* ``T(x; q)`` is the Poisson-binomial tail (:func:`gsw.stats.poisson_binomial_sf`); ``Q_c`` its
  ``confidence`` quantile over :attr:`NullModel.draws` draws ``q*`` of the per-bit rates from their
  estimate (mean ``p1``, standard error ``p1_se`` between calibration *images*, so several readings of
  one image count once): an upper confidence bound for the rates' estimation error.  Bounding the tail
  as a whole rather than each ``q_i`` avoids stacking ``k`` worst cases that cannot happen together.
  The draws use a fixed seed: p-values are deterministic.
* ``G(z, lambda) = Phi(-z / sqrt(lambda)) / Phi(-z)`` (1 when ``z <= 0`` or ``lambda <= 1``) widens the
  tail for the measured correlation of the bits: ``lambda = Var(X) / sum_i q_i (1 - q_i)`` is the design
  effect of the number of matches ``X`` for this message under the stratum's bit correlation
  (``corr(match_i, match_j) = s_i s_j corr(bit_i, bit_j)``, ``s_i = +-1`` by ``m_i``) and
  ``z = (x - E X) / sd_indep(X)``: the ratio of the normal tails of a correlated and an independent sum
  with the same mean, applied to the exact independent tail.  Never below 1: correlations that narrow
  the distribution are not used.
* The maximum over strata is valid for content like any calibration stratum *and any mixture of them*
  (a mixture's tail is an average of its components' tails).  Readings of an enlarged image (factor > 1)
  use the ``"up"`` strata, all others the ``"down"`` strata.
* The fair-coin floor keeps the exact guarantee for a uniformly random message (a key): whatever the
  content, such a message matches like Binomial(k, 1/2), so the null model is only ever used to be more
  careful, never to claim more (e.g. on content unlike every calibration stratum).

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
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gsw._atomic import atomic_write
from gsw.decoder.zoo import WEIGHTS_DIR, WeightsError, _manifest, weights_path
from gsw.stats import binomial_p_value, poisson_binomial_pmf

__all__ = ["NULL_FORMAT", "NullModel", "NullModelError", "Stratum", "decoder_fingerprint", "fit_null_model",
           "is_holdout", "load_null_model", "null_path", "reading_direction"]

NULL_FORMAT = "gsw-null-model/2"
#: Salt of the calibration / hold-out split (:func:`is_holdout`); changing it changes the split.
SPLIT_SALT = "gsw-null-split-v1"
#: Strata with fewer calibration images than this are not formed (their readings are left out).
MIN_STRATUM_IMAGES = 20
DIRECTIONS = ("down", "up")
_EPS = 1e-6  # drawn per-bit rates are kept inside [_EPS, 1 - _EPS]


class NullModelError(ValueError):
    """A null-model file is missing or malformed, or belongs to another decoder / bit length."""


def is_holdout(name: str) -> bool:
    """Whether an unmarked image belongs to the HOLD-OUT split (never used for calibration).

    ``name`` is the image's path relative to the shared data folder, e.g. ``"unmarked/sun80/x.jpg"``;
    an image is held out when the first byte of ``sha256(SPLIT_SALT + "/" + name)`` is below 128 (half of
    the images, independent of their content and order)."""
    return hashlib.sha256(f"{SPLIT_SALT}/{name}".encode()).digest()[0] < 128


def reading_direction(factor: float) -> str:
    """``"up"`` for a reading of an enlarged image (factor > 1), else ``"down"``."""
    return "up" if factor > 1.0 + 1e-9 else "down"


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


def _normal_sf(z: float) -> float:
    return 0.5 * math.erfc(z / math.sqrt(2.0))


@dataclass
class Stratum:
    """Per-bit statistics of one kind of unmarked content read one way.

    Attributes:
        name: e.g. ``"photo/down"``.
        direction: ``"down"`` (read at factor <= 1) or ``"up"`` (read enlarged).
        images: calibration images behind it; readings: their readings.
        p1: [k] P(bit = 1).
        p1_se: [k] standard error of ``p1`` (between images).
        bit_corr: [k, k] correlation of the bits over the readings (diagonal 1).
    """

    name: str
    direction: str
    images: int
    readings: int
    p1: np.ndarray
    p1_se: np.ndarray
    bit_corr: np.ndarray

    def check(self, k: int) -> None:
        self.p1, self.p1_se, self.bit_corr = (np.asarray(a, dtype=np.float64) for a in (self.p1, self.p1_se,
                                                                                       self.bit_corr))
        for name, shape in (("p1", (k,)), ("p1_se", (k,)), ("bit_corr", (k, k))):
            value = getattr(self, name)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise NullModelError(f"stratum {self.name!r} field {name!r}: expected finite values of shape "
                                     f"{list(shape)}, got {list(value.shape)}")
        if self.p1.min() < 0 or self.p1.max() > 1 or self.p1_se.min() < 0:
            raise NullModelError(f"stratum {self.name!r}: p1 must lie in [0, 1] and p1_se be >= 0")
        if self.direction not in DIRECTIONS:
            raise NullModelError(f"stratum {self.name!r}: direction must be one of {DIRECTIONS}, got {self.direction!r}")

    def tail_bound(self, m: np.ndarray, confidence: float, draws: int) -> np.ndarray:
        """[k + 1] upper bound U(x), x = 0..k, for message bits ``m`` (see the module docstring)."""
        k = m.shape[0]
        z = np.random.default_rng(0).standard_normal((draws, k))
        rates = np.clip(self.p1 + z * self.p1_se, _EPS, 1.0 - _EPS)
        q = np.where(m == 1, rates, 1.0 - rates)  # [draws, k] P(bit i matches)
        tails = np.cumsum(poisson_binomial_pmf(q)[:, ::-1], axis=1)[:, ::-1]  # [draws, k + 1]
        bound = np.quantile(tails, confidence, axis=0, method="higher")
        q0 = np.where(m == 1, self.p1, 1.0 - self.p1)
        var = q0 * (1.0 - q0)
        sd = math.sqrt(max(var.sum(), 1e-12))
        e = np.where(m == 1, 1.0, -1.0) * np.sqrt(var)
        design = float(e @ self.bit_corr @ e) / sd**2
        if design > 1.0:
            for x in range(k + 1):
                zx = (x - q0.sum()) / sd
                if zx > 0:
                    bound[x] *= _normal_sf(zx / math.sqrt(design)) / max(_normal_sf(zx), 1e-300)
        return np.minimum(bound, 1.0)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "direction": self.direction, "images": self.images, "readings": self.readings,
                "p1": np.round(self.p1, 5).tolist(), "p1_se": np.round(self.p1_se, 5).tolist(),
                "bit_corr": np.round(self.bit_corr, 3).tolist()}


@dataclass
class NullModel:
    """A decoder's null model: its strata and the rules of the p-value (see the module docstring).

    Attributes:
        num_bits: k.
        strata: the calibration strata (none: the fair coin).
        decoder_sha256: sha256 of the decoder's weight file (the manifest's), "" if none.
        decoder_fingerprint: :func:`decoder_fingerprint` of the decoder, "" for a model not tied to one.
        calibration: provenance: data, split, scales, summaries.
        confidence: level of the upper confidence bound on the tail.
        draws: number of draws of the per-bit rates behind that bound.
    """

    num_bits: int
    strata: list[Stratum] = field(default_factory=list)
    decoder_sha256: str = ""
    decoder_fingerprint: str = ""
    calibration: dict[str, Any] = field(default_factory=dict)
    confidence: float = 0.95
    draws: int = 1000

    def __post_init__(self) -> None:
        if isinstance(self.num_bits, bool) or not isinstance(self.num_bits, int) or self.num_bits < 1:
            raise NullModelError(f"null model: num_bits must be a positive int, got {self.num_bits!r}")
        for s in self.strata:
            s.check(self.num_bits)
        if not 0.5 <= self.confidence < 1 or self.draws < 1:
            raise NullModelError(f"null model: confidence must be in [0.5, 1) and draws >= 1, "
                                 f"got {self.confidence}, {self.draws}")
        self._fair = np.array([binomial_p_value(x, self.num_bits) for x in range(self.num_bits + 1)])
        self._tables: dict[tuple[bytes, str], np.ndarray] = {}

    @classmethod
    def fair(cls, num_bits: int) -> "NullModel":
        """The fair-coin model (no strata): its p-values are the binomial ones."""
        return cls(num_bits)

    # ---------------------------------------------------------------------------------- p-values
    def tail_table(self, message: Any, direction: str = "down") -> np.ndarray:
        """p-value of each possible number of matching bits with ``message``.

        Args:
            message: [k] bits (0/1; tensor, array or list).
            direction: ``"down"`` or ``"up"`` (:func:`reading_direction` of the reading's factor); with no
                stratum of that direction, the strata of the other one are used.

        Returns:
            [k + 2] float64: entry ``x`` is the p-value of ``x`` matching bits (entry ``k + 1`` is 0).
        """
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
        m = _as_bits(message, self.num_bits, "message").reshape(-1)
        key = (np.packbits(m).tobytes(), direction)
        table = self._tables.get(key)
        if table is None:
            strata = [s for s in self.strata if s.direction == direction] or self.strata
            table = self._fair.copy()
            for s in strata:
                table = np.maximum(table, s.tail_bound(m, self.confidence, self.draws))
            table = np.append(np.minimum(table, 1.0), 0.0)
            table[0] = 1.0
            if len(self._tables) < 4096:
                self._tables[key] = table
        return table

    def p_values(self, bits: Any, message: Any, factors: Any = None) -> np.ndarray:
        """p-values of decoded bits against a message.

        Args:
            bits: [..., k] decoded bits (0/1).
            message: [k] the claimed message.
            factors: resize factor of each reading, broadcastable to ``bits.shape[:-1]`` (None: 1).

        Returns:
            [...] float64 p-values (:meth:`tail_table` at each reading's number of matching bits).
        """
        b = _as_bits(bits, self.num_bits, "decoded bits")
        m = _as_bits(message, self.num_bits, "message").reshape(-1)
        matches = (b == m).sum(axis=-1)
        up = np.broadcast_to(np.asarray(1.0 if factors is None else factors, dtype=np.float64) > 1.0 + 1e-9,
                             matches.shape)
        return np.where(up, self.tail_table(m, "up")[matches], self.tail_table(m, "down")[matches])

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
        return {"format": NULL_FORMAT, "num_bits": self.num_bits, "decoder_sha256": self.decoder_sha256,
                "decoder_fingerprint": self.decoder_fingerprint, "confidence": self.confidence,
                "draws": self.draws, "calibration": self.calibration, "strata": [s.to_dict() for s in self.strata]}

    def save(self, path: str | Path) -> Path:
        """Writes the model as JSON (atomically). Returns the path."""
        path = Path(path)
        text = json.dumps(self.to_dict(), indent=1)
        text = re.sub(r"\[\s*([-+0-9.eE,\s]+?)\s*\]", lambda mt: "[" + re.sub(r"\s+", "", mt.group(1)) + "]", text)
        with atomic_write(path, "w") as f:
            f.write(text + "\n")
        return path

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "null model") -> "NullModel":
        if not isinstance(d, dict) or d.get("format") != NULL_FORMAT:
            raise NullModelError(f"{source}: not a gsw null model (expected format {NULL_FORMAT!r})")
        try:
            strata = [Stratum(str(s["name"]), str(s["direction"]), int(s["images"]), int(s["readings"]),
                              np.asarray(s["p1"]), np.asarray(s["p1_se"]), np.asarray(s["bit_corr"]))
                      for s in d["strata"]]
            return cls(int(d["num_bits"]), strata, str(d.get("decoder_sha256", "")),
                       str(d.get("decoder_fingerprint", "")), dict(d.get("calibration", {})),
                       float(d.get("confidence", 0.95)), int(d.get("draws", 1000)))
        except KeyError as e:
            raise NullModelError(f"{source}: missing field {e.args[0]!r}") from e
        except NullModelError as e:
            raise NullModelError(f"{source}: {e}") from e
        except (TypeError, ValueError) as e:
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


def null_path(num_bits: int, weights_dir: str | Path | None = None, readout: str = "direct") -> Path:
    """Path of the shipped null model of the ``num_bits`` decoder (beside its weights), read directly or through
    ``readout`` (``"klein"``: :class:`gsw.decoder.KleinReadout` over it)."""
    return Path(weights_dir or WEIGHTS_DIR) / f"null_k{num_bits}{'' if readout == 'direct' else '_' + readout}.json"


def load_null_model(num_bits: int, path: str | Path | None = None, *,
                    weights_dir: str | Path | None = None, readout: str = "direct") -> NullModel:
    """Loads a null model and checks that it belongs to a ``num_bits`` decoder.

    Args:
        num_bits: bit length of the decoder it is used with.
        path: a null-model JSON file; default: the shipped one, which must also name the sha256 that the
            weights manifest lists for the shipped decoder.
        weights_dir: directory of the shipped files (tests).
        readout: the shipped model of the decoder read directly (``"direct"``) or through
            :class:`gsw.decoder.KleinReadout` (``"klein"``); ignored with ``path``.

    Raises:
        NullModelError: missing/malformed file, another bit length, or a shipped model whose decoder
            sha256 differs from the manifest's (the decoder was replaced without recalibrating).
    """
    shipped = path is None
    path = null_path(num_bits, weights_dir, readout) if shipped else Path(path)
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


# ------------------------------------------------------------------------------------------ fitting
def _stratum(name: str, direction: str, bits: np.ndarray, owner: np.ndarray) -> Stratum:
    """Per-image means (each image counts once), their spread, the bits' correlation over readings."""
    images, inverse = np.unique(owner, return_inverse=True)
    counts = np.bincount(inverse).astype(np.float64)
    per_image = np.zeros((len(images), bits.shape[1]))
    np.add.at(per_image, inverse, bits)
    per_image /= counts[:, None]
    n = len(images)
    se = per_image.std(0, ddof=1) / math.sqrt(n) if n > 1 else np.full(bits.shape[1], 0.5)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.corrcoef(bits, rowvar=False)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    return Stratum(name, direction, n, int(bits.shape[0]), per_image.mean(0), se, corr)


def fit_null_model(records: list[dict[str, Any]], num_bits: int, *, decoder: torch.nn.Module | None = None,
                   decoder_sha256: str = "", provenance: dict[str, Any] | None = None,
                   confidence: float = 0.95, draws: int = 1000,
                   min_images: int = MIN_STRATUM_IMAGES) -> NullModel:
    """Estimates a null model from decoded unmarked readings.

    Args:
        records: one dict per reading: ``name`` (the image it comes from), ``kind`` (content kind, e.g.
            "photo", "manga", "render"), ``factor`` (read factor), ``bits`` ([k] 0/1).
        num_bits: k.
        decoder: the decoder that produced the bits (its :func:`decoder_fingerprint` is stored).
        decoder_sha256: sha256 of its weight file.
        provenance: stored under ``calibration`` (data, split, versions).
        confidence, draws: see :class:`NullModel`.
        min_images: strata (kind x :func:`reading_direction`) with fewer images are left out.

    Returns:
        the model, one stratum per (kind, direction) with at least ``min_images`` images.
    """
    if not records:
        raise ValueError("no calibration readings")
    bits = _as_bits([r["bits"] for r in records], num_bits, "calibration bits").astype(np.float64)
    names = np.array([r["name"] for r in records])
    keys = np.array([f"{r['kind']}/{reading_direction(float(r['factor']))}" for r in records])
    strata, skipped = [], {}
    for key in sorted(set(keys.tolist())):
        sel = keys == key
        if len(set(names[sel].tolist())) < min_images:
            skipped[key] = int(sel.sum())
            continue
        strata.append(_stratum(key, key.rsplit("/", 1)[1], bits[sel], names[sel]))
    if not strata:
        raise ValueError(f"no stratum has {min_images} or more images")
    summary = {s.name: {"images": s.images, "readings": s.readings,
                        "max_abs_dev": round(float(np.abs(s.p1 - 0.5).max()), 4),
                        "mean_p1_se": round(float(s.p1_se.mean()), 4),
                        "bit_corr_mean_sq": round(float((s.bit_corr[~np.eye(num_bits, dtype=bool)] ** 2).mean()), 5)}
               for s in strata}
    calibration = {"images": len(set(names.tolist())), "readings": len(records), "strata": summary,
                   "left_out_readings": skipped, **(provenance or {})}
    return NullModel(num_bits, strata, decoder_sha256, decoder_fingerprint(decoder) if decoder is not None else "",
                     calibration, confidence, draws)
