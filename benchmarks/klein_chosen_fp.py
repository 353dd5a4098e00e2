"""False positives of CHOSEN messages read through `KleinReadout`, on HOLD-OUT data only: with the fair coin (what
`gsw verify --chosen-message --readout klein` computed before the readout had a null model) and with the null model
calibrated through the readout where one ships (``benchmarks/calibrate_null.py --readout klein``).

The direct readout needs a calibrated null model for chosen messages because its bits lean on unmarked content (a
message that lines up with the lean passes the fair-coin test far too often: BENCHMARKS.md, "Detection statistics").
KleinReadout is fair per bit by symmetry; this measures whether the fair-coin p-value (binomial tail of the matching
bits, the scale search paid by the weighted Bonferroni, :func:`gsw.mark.evidence.score_messages` with
``NullModel.fair``) holds its level on unmarked images for:

* random messages (a shared pool of ``--messages``);
* messages aligned with the DIRECT decoder's calibrated lean (each calibration stratum's majority pattern, with
  0-3 random bits flipped, 100 per kind): the messages that fooled the fair coin through the direct readout;
* messages aligned with the hold-out readings' own majority pattern through KleinReadout (chosen knowing the test
  images: an adversarial stress test, 100 per kind).

Data: the 144 held-out photos and manga pages (:func:`gsw.decoder.null.is_holdout`), read with the scale search, and
the 32 held-out renders of ``benchmarks/detection_null.py`` (256 px) read at their known size.

    PYTHONPATH=. python benchmarks/klein_chosen_fp.py --data ../shared/data --out benchmarks/results/klein_chosen_fp.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibrate_null import DATA, ROOT  # noqa: E402
from detection_null import aligned_messages, as_given, holdout_photos, holdout_renders, rates, readings_of  # noqa: E402
from gsw._atomic import atomic_write  # noqa: E402
from gsw.decoder import KleinReadout  # noqa: E402
from gsw.decoder.null import NullModel, NullModelError, load_null_model  # noqa: E402
from gsw.decoder.zoo import load_decoder  # noqa: E402
from gsw.mark.evidence import score_messages  # noqa: E402


def chosen_p(readings, msgs: np.ndarray, model: NullModel) -> np.ndarray:
    """[images x messages] p-values of the chosen-message rule with ``model`` (the fair coin: verify's rule for a
    decoder without a null model; or the null model calibrated through the readout)."""
    return score_messages(readings, msgs, model, origin="chosen").p_values


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--messages", type=int, default=1250)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "klein_chosen_fp.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    k = args.bits
    decoder = KleinReadout(load_decoder(k)).eval()
    photos = holdout_photos(args.data)
    kinds = [kind for _, kind, _ in photos]
    photo_readings = readings_of([img for _, _, img in photos], decoder)
    t_photos = time.perf_counter() - t0
    renders = holdout_renders(args.data)
    render_readings = [as_given(r) for r in readings_of(renders, decoder, embed_size=(256, 256))]
    t_read = time.perf_counter() - t0
    direct_null = load_null_model(k)
    models = {"fair": NullModel.fair(k)}
    try:  # the null model calibrated through the readout, where one ships (calibrate_null.py --readout klein)
        models["calibrated"] = load_null_model(k, readout="klein")
        models["calibrated"].check_decoder(decoder)
    except NullModelError as e:
        print(f"no calibrated null model through the readout: {e}", flush=True)
    out: dict = {"bits": k, "messages": args.messages, "photos": len(photos), "renders": len(renders)}
    groups = {kind: [r for r, kd in zip(photo_readings, kinds) if kd == kind] for kind in sorted(set(kinds))}
    groups["render"] = render_readings
    for name, model in models.items():
        gen = np.random.default_rng(2026)  # the same messages for every model
        pool = gen.integers(0, 2, (args.messages, k)).astype(np.int8)
        for kind, readings in groups.items():
            row = {"images": len(readings), "random": rates(chosen_p(readings, pool, model))}
            stratum = next(s for s in direct_null.strata if s.name == f"{kind}/down")
            row["aligned_direct_lean"] = rates(chosen_p(readings, aligned_messages(stratum.p1, 100, gen), model))
            own = np.stack([r.bits[int(r.confidence.argmax())].numpy() for r in readings]).mean(0)
            row["aligned_own_lean"] = rates(chosen_p(readings, aligned_messages(own, 100, gen), model))
            row["own_majority_p1_max_dev"] = float(np.abs(own - 0.5).max())
            out.setdefault(name, {})[kind] = row
            print(name, kind, json.dumps({key: (v if not isinstance(v, dict) else
                                                {lv: v[lv]["count"] for lv in ("0.01", "0.001", "1e-06") if lv in v})
                                          for key, v in row.items()}), flush=True)
    out["machine"] = {"python": platform.python_version(), "torch": torch.__version__, "threads": args.threads,
                      "processor": platform.processor() or platform.machine()}
    out["seconds"] = {"read_photos": t_photos, "read_all": t_read, "total": time.perf_counter() - t0}
    with atomic_write(args.out, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {args.out} in {out['seconds']['total']:.0f} s")


if __name__ == "__main__":
    main()
