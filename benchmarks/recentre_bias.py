"""Per-bit bias of the shipped decoders on held-out photos, before and after re-centring the whitening (#22).

A measurement only (the shipped weights are not changed): the per-bit median of the whitened logits on the
CALIBRATION half of ``unmarked/{sun80,urban100,manga109}`` (:func:`gsw.decoder.null.is_holdout` false;
photos read as given) is subtracted from the logits of the HOLD-OUT half, and the largest deviation of a
bit's P(1) from 1/2 is tested against a fair decoder's sampling noise
(:func:`gsw.decoder.pretrain.evaluation.max_dev_p_value`) before and after, per content kind.  Also
what the exact randomization test relies on: the per-bit rate at which the held-out photos' bits match
FRESH messages of gsw's own generator (``match_random_messages``, ``detection_null.match_bias_test``).

    PYTHONPATH=. python benchmarks/recentre_bias.py --out benchmarks/results/recentre_bias.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from calibrate_null import DATA, ROOT, photo_files
from detection_null import match_bias_test
from gsw._atomic import atomic_write
from gsw.decoder.pretrain.evaluation import max_dev_p_value
from gsw.decoder.zoo import load_decoder
from gsw.mark.scales import read_images


def logits_of(data: Path, holdout: bool, decoder) -> tuple[np.ndarray, list[str], list]:
    from gsw.data.images import read_image

    files = [(n, k) for n, k in photo_files(data, holdout) if not n.startswith("bsds500")]
    imgs = [read_image(data / n)[:3] for n, _ in files]
    readings = read_images(imgs, decoder, factors=(1.0,))
    return np.stack([r.logits[0].numpy() for r in readings]), [k for _, k in files], readings


def deviation(bits: np.ndarray) -> dict:
    n, k = bits.shape
    dev = float(np.abs(bits.mean(0) - 0.5).max())
    return {"images": n, "max_abs_dev": round(dev, 4), "fair_p_value": max_dev_p_value(dev, n, k)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "recentre_bias.json")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--messages", type=int, default=1250, help="fresh random messages per held-out photo")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    res: dict = {}
    for k in args.bits:
        decoder = load_decoder(k)
        cal, _, _ = logits_of(args.data, False, decoder)
        hold, hold_kinds, hold_readings = logits_of(args.data, True, decoder)
        centre = np.median(cal, axis=0)
        out = {"calibration_images": len(cal), "median_shift_abs_max": round(float(np.abs(centre).max()), 4)}
        for kind in sorted(set(hold_kinds)):
            sel = np.array([kd == kind for kd in hold_kinds])
            out[kind] = {"before": deviation((hold[sel] > 0).astype(np.float64)),
                         "after": deviation((hold[sel] - centre > 0).astype(np.float64))}
        sel_all = np.ones(len(hold), dtype=bool)
        out["all"] = {"before": deviation((hold[sel_all] > 0).astype(np.float64)),
                      "after": deviation((hold - centre > 0).astype(np.float64))}
        out["match_random_messages"] = match_bias_test(hold_readings, args.messages)
        res[f"k{k}"] = out
        print(k, json.dumps(out), flush=True)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.out, "w") as f:
        f.write(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
