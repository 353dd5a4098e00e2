"""Power of the exact randomization test (issue #22) by per-bit weighting and scale-selection rule, on the CPU.

The built-in scene watermarked with the ``gsw demo`` defaults (32 bits; ``detection_null.marked_demo``,
cached), views NOT used for embedding, clean at 0.5x-3x the 256-px embedding size and at 1x under image
attacks (JPEG, noise, blur, brightness: weaker marks, where the weighting matters).  Two view sets:

* ``--views tuning``: 24 orbit views at elevation 45 deg (azimuths between the embedding views'): the
  weighting and the selection rule are chosen on these;
* ``--views holdout``: the demo's 24 held-out views (elevation 30 deg, the azimuths between the embedding
  views): the chosen rule's power is reported on these.

Rules compared on the same readings (detection rate at 1e-6 and 1e-3, median log10 p; single views and the
24 cyclic sets of 10 views):

* ``old``: the number of matching bits of the image as given, fair coin (Fisher over frames);
* ``calibrated``: the chosen-message rule (:func:`gsw.mark.evidence.score_messages` with
  ``origin="chosen"``: null model, weighted Bonferroni over the readings, Hommel over frames);
* ``exact/<weighting>``: the random-message rule (most confident reading, pooled logits over frames),
  weighting ``sign`` / ``rank`` / ``magnitude``;
* ``exact-bonferroni/<weighting>``: the exact per-reading p-values combined with the weighted Bonferroni of
  :func:`gsw.mark.evidence.reading_weights` instead of the confidence choice (sets: Hommel).

    PYTHONPATH=. python benchmarks/weighting_power.py --views tuning --out benchmarks/results/weighting_tuning.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from calibrate_null import ROOT, render_all
from detection_null import marked_demo
from gsw._atomic import atomic_write
from gsw.mark.evidence import reading_weights, score_messages, shipped_null_model
from gsw.mark.randomization import WEIGHTINGS, exact_p_values
from gsw.mark.scales import read_images
from gsw.stats import binomial_p_value, bonferroni_p_value, fisher_combined_p_value, hommel_combined_p_value

SCALES = (0.5, 1.0, 1.5, 2.0, 3.0)
LEVELS = (1e-6, 1e-3)


def attacks() -> dict:
    from gsw.attacks import ops

    return {"jpeg50": lambda x: ops.jpeg(x, 50), "jpeg25": lambda x: ops.jpeg(x, 25),
            "noise0.08": lambda x: ops.gaussian_noise(x, 0.08), "blur1": lambda x: ops.gaussian_blur(x, 1.0),
            "bright1.5": lambda x: ops.brightness(x, 1.5)}


def summary(p: np.ndarray) -> dict:
    p = np.asarray(p, dtype=np.float64)
    out = {f"det_{lv:g}": float((p <= lv).mean()) for lv in LEVELS}
    out["median_log10_p"] = float(np.median(np.log10(np.maximum(p, 1e-300))))
    return out


def rules(readings, msg: np.ndarray, null) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """rule -> (per-view p [V], per-set p [V]) for the 24 cyclic sets of 10 views."""
    v = len(readings)
    sets = [[(i + j) % v for j in range(10)] for i in range(v)]
    first = np.array([int((r.bits[0].numpy() == msg).sum()) for r in readings])
    old = np.array([binomial_p_value(int(x), len(msg)) for x in first])
    out = {"old": (old, np.array([fisher_combined_p_value(old[s]) for s in sets]))}
    cal = score_messages(readings, msg[None], null, origin="chosen").p_values[:, 0]
    out["calibrated"] = (cal, np.array([float(hommel_combined_p_value(cal[s])) for s in sets]))
    for w in WEIGHTINGS:
        single = score_messages(readings, msg[None], origin="random", weighting=w).p_values[:, 0]
        pooled = np.array([score_messages([readings[i] for i in s], msg[None], origin="random",
                                          weighting=w).combined[0] for s in sets])
        out[f"exact/{w}"] = (single, pooled)
        per = [bonferroni_p_value(exact_p_values(r.logits, msg[None], w)[0][:, 0], weights=reading_weights(r.confidence))
               for r in readings]
        bon = np.array([float(x) for x in per])
        out[f"exact-bonferroni/{w}"] = (bon, np.array([float(hommel_combined_p_value(bon[s])) for s in sets]))
    return out


def measure(images, msg, decoder, null, known_only: bool) -> dict:
    res = {}
    modes = {"known_size": dict(embed_size=(256, 256))}
    if not known_only:
        modes["search"] = {}
    for mode, kw in modes.items():
        rs = read_images(images, decoder, **kw)
        acc = float(np.mean([(r.bits[0].numpy() == msg).mean() for r in rs]))
        res[mode] = {"bit_accuracy_first_reading": acc}
        for name, (single, sets) in rules(rs, msg, null).items():
            res[mode][name] = {"single": summary(single), "sets_of_10": summary(sets)}
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", choices=["tuning", "holdout"], default="tuning")
    ap.add_argument("--cache", type=Path, default=ROOT / "build" / "detection_null")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from gsw.decoder.zoo import load_decoder
    from gsw.scenes import default_cameras

    t0 = time.perf_counter()
    out_path = args.out or ROOT / "benchmarks" / "results" / f"weighting_{args.views}.json"
    g, message, bg = marked_demo(args.cache)
    msg = message.numpy().astype(np.int8)
    decoder, null = load_decoder(32), shipped_null_model(32)
    cams = (default_cameras(24, 256, 256, elevation_deg=45.0, azimuth_offset_deg=3.75) if args.views == "tuning"
            else default_cameras(24, 256, 256, azimuth_offset_deg=180.0 / 24))
    res: dict = {"views": args.views, "machine": f"{platform.processor() or platform.machine()}, "
                 f"{torch.get_num_threads()} threads", "torch": torch.__version__, "conditions": {}}
    base = render_all(g, cams, bg)
    for s in SCALES:
        imgs = base if s == 1.0 else render_all(g, [c.scaled(s) for c in cams], bg)
        res["conditions"][f"{s:g}x"] = measure(imgs, msg, decoder, null, known_only=False)
        print(f"{s:g}x done {time.perf_counter() - t0:.0f} s", flush=True)
    for name, fn in attacks().items():
        imgs = [fn(im).clamp(0, 1) for im in base]
        res["conditions"][name] = measure(imgs, msg, decoder, null, known_only=True)
        print(f"{name} done {time.perf_counter() - t0:.0f} s", flush=True)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out_path, "w") as f:
        f.write(json.dumps(res, indent=1) + "\n")
    for cond, r in res["conditions"].items():
        for mode, rr in r.items():
            line = " ".join(f"{k}={v['single']['det_1e-06']:.2f}/{v['sets_of_10']['det_1e-06']:.2f}"
                            f"({v['single']['median_log10_p']:.1f})" for k, v in rr.items() if isinstance(v, dict))
            print(f"{cond:10s} {mode:10s} acc={rr['bit_accuracy_first_reading']:.3f} {line}")


if __name__ == "__main__":
    main()
