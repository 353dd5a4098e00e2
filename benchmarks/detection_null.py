"""False positives and power of the detector: old (fair coin + Fisher), calibrated (chosen messages) and exact (random).

HOLD-OUT data only (never used by ``benchmarks/calibrate_null.py``):

* photos: the held-out half of ``unmarked/{sun80,urban100,manga109}`` (:func:`gsw.decoder.null.is_holdout`);
* renders: the built-in scene with another seed (1) from an orbit at 15 deg elevation, and the PLY fixture
  seen with another up axis (-y) from 10 deg elevation, 256 px;
* near-duplicate sets of 40 frames (and the 4 disjoint sets of 10 inside each): renders from cameras
  jittered by N(0, (5e-4 x orbit radius)^2) per axis (2 mm at 4 m) around a held-out view, read at their
  known size; photos downscaled to 240 px (long side) with 0.98-1.02 rescaling and 1-3 px shifts, read with
  the scale search.

Each image (set) is decoded once and tested against a pool of random messages (the same pool for every
image), so one run holds tens of thousands of (image set, message) pairs.  Old: binomial(k, 1/2) p-value
at the image as given, Fisher over frames.  New (``new_*``, the rule for CHOSEN messages):
:func:`gsw.mark.evidence.score_messages` with ``origin="chosen"`` (null model with the reading direction of
each reading, the scale search as a weighted Bonferroni unless the size is known, Hommel over frames).
Exact (``exact_*``, the rule of ``gsw.verify`` for RANDOM messages, ``origin="random"``: signed-rank
randomization test of the most confident reading, pooled logits over frames) on the same readings and
the same message pool, and (``exact_*_fresh``) with fresh messages for every image (set), so that
pairs are independent given the images; ``exact_*_one`` tests one fresh message per image (set): the
rate over independent images.  ``--skip-calibrated`` leaves the (unchanged, slow) ``new_*`` rows out.

Power: the built-in scene watermarked with the ``gsw demo`` defaults (256 px, 24 views, 8 epochs, 32 bits,
AlexNet LPIPS, seed 0; cached in ``--cache``), 24 held-out views rendered at 0.5x-3x the size (intrinsics
scaled), single views and sets of 10 views.

    PYTHONPATH=. python benchmarks/detection_null.py --data ../shared/data \\
        --out benchmarks/results/detection_null.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from calibrate_null import DATA, ROOT, fixture_orbit, photo_files, render_all
from gsw._atomic import atomic_write
from gsw.decoder.null import load_null_model
from gsw.decoder.pretrain.evaluation import max_dev_p_value
from gsw.decoder.zoo import load_decoder
from gsw.mark.evidence import score_messages
from gsw.mark.scales import SEARCH_FACTORS, Reading, read_images
from gsw.stats import binomial_p_value, clopper_pearson, fisher_combined_p_value

LEVELS = (1e-2, 1e-3, 1e-6)
POWER_SCALES = (0.5, 1.0, 1.5, 2.0, 3.0)


# ------------------------------------------------------------------------------------------- hold-out data
def holdout_photos(data: Path) -> list[tuple[str, str, torch.Tensor]]:
    from gsw.data.images import read_image

    return [(n, k, (read_image(data / n)[:3] * 255).round().to(torch.uint8)) for n, k in photo_files(data, True)]


def _scene(data: Path, which: str, n: int, size: int, offset: float = 0.0):
    """(gaussians, cameras, background, orbit radius) of a held-out render source."""
    from gsw.scenes import default_cameras, default_scene

    if which == "default":
        scene = default_scene(seed=1)
        cams = default_cameras(n, size, size, elevation_deg=15.0, azimuth_offset_deg=7.5 + offset)
        return scene.gaussians, cams, scene.background, 4.0
    g, cams = fixture_orbit(data, n, size, up=(0.0, -1.0, 0.0), radius_scale=0.9, elevation=10.0, offset=offset)
    return g, cams, (0.0, 0.0, 0.0), 900.0 * 0.9


def holdout_renders(data: Path, size: int = 256) -> list[torch.Tensor]:
    out = []
    for which in ("default", "fixture"):
        g, cams, bg, _ = _scene(data, which, 16, size)
        out += render_all(g, cams, bg)
    return out


def jittered(cam, sigma: float, gen: torch.Generator, center):
    from gsw.camera import Camera

    up = -cam.R[1].double()  # the camera's up axis (OpenCV: y down)
    eye = cam.center.double() + sigma * torch.randn(3, generator=gen, dtype=torch.float64)
    target = torch.as_tensor(center, dtype=torch.float64) + sigma * torch.randn(3, generator=gen, dtype=torch.float64)
    return Camera.look_at(eye.tolist(), target.tolist(), up.tolist(), cam.fov_x, cam.width, cam.height)


def render_sets(data: Path, sets_per_scene: int, frames: int, size: int = 256) -> list[list[torch.Tensor]]:
    """Near-duplicate frames: camera positions (and look-at points) jittered by 5e-4 x the orbit radius."""
    from gsw.scenes import DEFAULT_SCENE_CENTER

    gen = torch.Generator().manual_seed(7)
    out = []
    for which in ("default", "fixture"):
        g, cams, bg, radius = _scene(data, which, sets_per_scene, size, offset=3.0)
        center = DEFAULT_SCENE_CENTER if which == "default" else g.means.median(0).values.double().tolist()
        for cam in cams:
            out.append(render_all(g, [jittered(cam, 5e-4 * radius, gen, center) for _ in range(frames)], bg))
    return out


def photo_sets(photos, n_sets: int, frames: int, long_side: int = 240) -> list[list[torch.Tensor]]:
    """Near-duplicate frames of held-out photos: rescaled by U(0.98, 1.02) around a long side of
    ``long_side + 16`` px, then a ``long_side`` crop shifted by 1-3 px (random sign) from the centre."""
    from gsw.data.images import resize_image

    gen = torch.Generator().manual_seed(11)
    step = max(1, len(photos) // n_sets)
    out = []
    for _, _, img in photos[::step][:n_sets]:
        h0, w0 = img.shape[-2:]
        r = long_side / max(h0, w0)
        h, w = round(h0 * r), round(w0 * r)
        frames_ = []
        for _ in range(frames):
            s = 0.98 + 0.04 * float(torch.rand(1, generator=gen))
            big = resize_image(img.float() / 255, round(h0 * r * s * 1.07), round(w0 * r * s * 1.07))
            dy, dx = (int(v) * (1 if float(torch.rand(1, generator=gen)) < 0.5 else -1)
                      for v in torch.randint(1, 4, (2,), generator=gen))
            y0, x0 = (big.shape[-2] - h) // 2 + dy, (big.shape[-1] - w) // 2 + dx
            frames_.append(big[:, y0 : y0 + h, x0 : x0 + w].clamp(0, 1))
        out.append(frames_)
    return out


# ------------------------------------------------------------------------------------------- p-values
def readings_of(images, decoder, *, embed_size=None, factors=SEARCH_FACTORS) -> list[Reading]:
    """Every reading of each image (reading 0: the image as given, or at its known size)."""
    return read_images(images, decoder, embed_size=embed_size, factors=factors)


def first_bits(readings: list[Reading]) -> np.ndarray:
    """[N, k] bits of each image's first reading."""
    return np.stack([r.bits[0].numpy().astype(np.int8) for r in readings])


def as_given(r: Reading) -> Reading:
    """The first reading alone (the image as given / at its known size: no search)."""
    return Reading(r.factors[:1], r.sizes[:1], r.logits[:1])


def match_counts(bits: np.ndarray, msgs: np.ndarray) -> np.ndarray:
    """bits [..., k], msgs [M, k] -> matches [..., M]."""
    b = bits.astype(np.int32)
    m = msgs.astype(np.int32)
    return b @ m.T + (1 - b) @ (1 - m).T


def old_p(matches: np.ndarray, k: int) -> np.ndarray:
    table = np.array([binomial_p_value(x, k) for x in range(k + 1)])
    return table[matches]


def fisher_sets(p: np.ndarray) -> np.ndarray:
    """p [F, M] -> Fisher over F for each message [M]."""
    return np.array([fisher_combined_p_value(p[:, j]) for j in range(p.shape[1])])


def rates(p: np.ndarray) -> dict:
    p = np.asarray(p).ravel()
    out = {"pairs": int(p.size)}
    for lv in LEVELS:
        c = int((p <= lv).sum())
        lo, hi = clopper_pearson(c, p.size)
        out[f"{lv:g}"] = {"count": c, "rate": c / p.size, "ci95": [lo, hi]}
    return out


#: Skip the calibrated (chosen-message) rows (set by ``--skip-calibrated``).
SKIP_CALIBRATED = False
#: Messages drawn afresh for every image (set) in the ``*_fresh`` rows.
FRESH = np.random.default_rng(12345)


def exact_rows(groups: list[list[Reading]], msgs: np.ndarray, prefix: str) -> dict:
    """The exact test (random messages) of each group of readings (one image, or a set's frames):
    the shared message pool, fresh messages per group, one fresh message per group."""
    shared, fresh, one = [], [], []
    for group in groups:
        shared.append(score_messages(group, msgs).combined)
        fresh.append(score_messages(group, FRESH.integers(0, 2, msgs.shape).astype(np.int8)).combined)
        one.append(score_messages(group, FRESH.integers(0, 2, (1, msgs.shape[1])).astype(np.int8)).combined)
    return {prefix: rates(np.concatenate(shared)), f"{prefix}_fresh": rates(np.concatenate(fresh)),
            f"{prefix}_one": rates(np.concatenate(one))}


def set_results(sets: list[list[Reading]], msgs: np.ndarray, null, k: int, size: int) -> dict:
    """sets: per set, its frames' readings. Sets of ``size`` frames: the disjoint consecutive groups of each
    set."""
    groups = [frames[start : start + size] for frames in sets for start in range(0, len(frames) - size + 1, size)]
    out = {"sets": len(groups), "old": rates(np.concatenate([fisher_sets(old_p(match_counts(first_bits(g), msgs), k))
                                                             for g in groups]))}
    if not SKIP_CALIBRATED:
        out["new"] = rates(np.concatenate([score_messages(g, msgs, null, origin="chosen").combined for g in groups]))
    return out | exact_rows(groups, msgs, "exact")


def singles(readings: list[Reading], msgs: np.ndarray, null, k: int, *, exact: bool = True) -> dict:
    """readings: per image (reading 0 = the image as given; renders: their known size)."""
    known = [as_given(r) for r in readings]
    out = {"images": len(readings), "old": rates(old_p(match_counts(first_bits(readings), msgs), k))}
    if not SKIP_CALIBRATED:
        out["new_known_size"] = rates(score_messages(known, msgs, null, origin="chosen").p_values)
    if exact:
        out |= exact_rows([[r] for r in known], msgs, "exact_known_size")
    if max(len(r.factors) for r in readings) > 1:
        if not SKIP_CALIBRATED:
            out["new_search"] = rates(score_messages(readings, msgs, null, origin="chosen").p_values)
        if exact:
            out |= exact_rows([[r] for r in readings], msgs, "exact_search")
    return out


def match_bias_test(readings: list[Reading], count: int) -> dict:
    """What the exact test relies on: over random messages, each bit of the (most confident) reading matches
    the message's bit with probability 1/2. Each image is paired with ``count`` FRESH messages from gsw's own
    generator (:func:`gsw.mark.message.random_message`, OS entropy), so that, given the images, every
    (image, message, bit) match is an independent fair coin and ``max_dev_p_value`` with n = pairs is the
    right reference. (With one message pool shared by all images the per-bit match counts of biased bits
    are not binomial: one message bit decides the match for every image at once.)"""
    from gsw.mark.message import random_message

    bits = np.stack([r.bits[int(r.confidence.argmax())].numpy().astype(np.int8) for r in readings])  # [N, k]
    k = bits.shape[1]
    msgs = np.stack([random_message(k).numpy().astype(np.int8) for _ in range(len(bits) * count)])
    match = (np.repeat(bits, count, axis=0) == msgs)  # [N * count, k]
    dev = float(np.abs(match.mean(0) - 0.5).max())
    return {"pairs": int(match.shape[0]), "max_abs_dev_from_half": dev,
            "fair_p_value": max_dev_p_value(dev, match.shape[0], k)}


def bias_test(bits: np.ndarray, stratum) -> dict:
    """Per-bit P(1) of held-out images (one reading each) vs a fair decoder's sampling noise
    (``max_dev_p_value``: P(max_i |P(1)_i - 1/2| >= observed) for n images of k fair independent bits) and
    vs the calibration stratum of the same kind (simulated: n draws of Bernoulli(rate) per bit, the rates
    drawn from the stratum's estimate and its standard error)."""
    n, k = bits.shape
    p1 = bits.mean(0)
    dev = float(np.abs(p1 - 0.5).max())
    gen = np.random.default_rng(3)
    obs = float(np.abs(p1 - stratum.p1).max())
    rate = np.clip(stratum.p1 + gen.standard_normal((4000, k)) * stratum.p1_se, 0, 1)
    sim = np.abs(gen.binomial(n, rate) / n - stratum.p1).max(1)
    return {"images": n, "max_abs_dev_from_half": dev, "fair_decoder_p_value": max_dev_p_value(dev, n, k),
            "worst_bit": int(np.abs(p1 - 0.5).argmax()), "stratum": stratum.name,
            "max_abs_dev_from_stratum": obs, "stratum_p_value": float((sim >= obs - 1e-12).mean()),
            "p1": np.round(p1, 3).tolist()}


def aligned_messages(p1: np.ndarray, count: int, gen: np.random.Generator) -> np.ndarray:
    """The message that agrees with every bias ``p1`` (a calibration stratum's), and copies with 1-3
    random bits flipped."""
    base = (p1 > 0.5).astype(np.int8)
    out = np.repeat(base[None], count, axis=0)
    for row in out[1:]:
        row[gen.choice(len(base), gen.integers(1, 4), replace=False)] ^= 1
    return out


def aligned_singles(readings: list[Reading], kinds: list[str], null, gen, k: int) -> dict:
    """False positives of messages aligned with the biases of each held-out kind's calibration stratum."""
    out = {}
    for kind in sorted(set(kinds)):
        stratum = next(s for s in null.strata if s.name == f"{kind}/down")
        msgs = aligned_messages(stratum.p1, 100, gen)
        out[kind] = singles([r for r, kd in zip(readings, kinds) if kd == kind], msgs, null, k, exact=False)
        # what the exact test would say about these (NOT random) messages: it is not valid for them
        out[kind] |= {"exact_not_valid_for_chosen": rates(score_messages(
            [as_given(r) for r, kd in zip(readings, kinds) if kd == kind], msgs).p_values)}
    return out


# ------------------------------------------------------------------------------------------- power
def marked_demo(cache: Path):
    """The built-in scene watermarked with the ``gsw demo`` defaults (cached)."""
    from gsw.gaussians import Gaussians
    from gsw.mark.embed import EmbedConfig, embed
    from gsw.mark.loss import LossWeights
    from gsw.mark.message import random_message
    from gsw.scenes import default_scene

    path = cache / "demo_marked_256_k32_seed0.pt"
    if not path.is_file():
        scene = default_scene(width=256, height=256, n_cameras=24)
        bg = tuple(float(v) for v in torch.as_tensor(scene.background).flatten())
        cfg = EmbedConfig(epochs=8, background=bg, seed=0, lpips_net="alex", weights=LossWeights())
        res = embed(scene.gaussians, scene.cameras, message=random_message(32, seed=0), num_bits=32, config=cfg,
                    progress=False)
        g = res.gaussians
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(dict(means=g.means, log_scales=g.log_scales, quats=g.quats, opacity_logits=g.opacity_logits,
                        sh=g.sh, message=res.message, bg=bg), path)
    d = torch.load(path)
    return Gaussians(d["means"], d["log_scales"], d["quats"], d["opacity_logits"], d["sh"]), d["message"], d["bg"]


def power(decoder, null, cache: Path) -> dict:
    from gsw.scenes import default_cameras
    from gsw.stats import hommel_combined_p_value

    g, msg, bg = marked_demo(cache)
    m = msg.numpy().astype(np.int8)
    cams = default_cameras(24, 256, 256, azimuth_offset_deg=180.0 / 24)  # the demo's held-out views
    out = {}
    for s in POWER_SCALES:
        imgs = render_all(g, [c.scaled(s) for c in cams], bg)
        rs = read_images(imgs, decoder)
        known = readings_of(imgs, decoder, embed_size=(256, 256))
        mt_s = np.stack([match_counts(r.bits.numpy().astype(np.int8), m[None])[:, 0] for r in rs])  # [V, S]
        p_old = old_p(mt_s[:, 0], 32)
        sc_known = score_messages(known, m[None], null, origin="chosen")
        sc_search = score_messages(rs, m[None], null, origin="chosen")
        ex_known, ex_search = score_messages(known, m[None]).p_values[:, 0], score_messages(rs, m[None]).p_values[:, 0]
        p_known, p_search = sc_known.p_values[:, 0], sc_search.p_values[:, 0]
        conf = [int(r.confidence.argmax()) for r in rs]
        best = [int(np.argmax(mt)) for mt in mt_s]
        sets = [[(i + j) % 24 for j in range(10)] for i in range(24)]  # 24 sets of 10 held-out views
        det = lambda p: float(np.mean(np.asarray(p) <= 1e-6))  # noqa: E731
        out[f"{s:g}x"] = {
            "size": list(imgs[0].shape[-2:]), "views": len(imgs),
            "bit_acc_as_given": float(mt_s[:, 0].mean() / 32),
            "bit_acc_known_size": float(sc_known.matches[:, 0].mean() / 32),
            "bit_acc_search_best": float(mt_s.max(1).mean() / 32),
            "single": {"old": det(p_old), "new_known_size": det(p_known), "new_search": det(p_search),
                       "exact_known_size": det(ex_known), "exact_search": det(ex_search)},
            "sets_of_10": {"old": det([fisher_combined_p_value(p_old[st]) for st in sets]),
                           "new_known_size": det([hommel_combined_p_value(p_known[st]) for st in sets]),
                           "new_search": det([hommel_combined_p_value(p_search[st]) for st in sets]),
                           "exact_known_size": det([score_messages([known[i] for i in st], m[None]).combined[0]
                                                    for st in sets]),
                           "exact_search": det([score_messages([rs[i] for i in st], m[None]).combined[0]
                                                for st in sets])},
            "median_p": {"old": float(np.median(p_old)), "new_known_size": float(np.median(p_known)),
                         "new_search": float(np.median(p_search))},
            "factor_most_matches": {f"{rs[0].factors[i]:.3g}": best.count(i) for i in sorted(set(best))},
            "most_confident_is_most_matches": float(np.mean([mt[c] == mt.max() for c, mt in zip(conf, mt_s)])),
        }
        print(f"power {s}x: {out[f'{s:g}x']['single']} sets {out[f'{s:g}x']['sets_of_10']}", flush=True)
    return out


# ------------------------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "detection_null.json")
    ap.add_argument("--cache", type=Path, default=ROOT / "build" / "detection_null")
    ap.add_argument("--messages", type=int, default=1000, help="random messages tested against every image")
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64],
                    help="bit lengths (32: everything; others: single held-out photos as given only); results of "
                         "other bit lengths already in --out are kept")
    ap.add_argument("--photo-sets", type=int, default=12)
    ap.add_argument("--render-sets", type=int, default=12, help="per held-out scene")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--limit-photos", type=int, default=None, help="smoke test: only the first N held-out photos")
    ap.add_argument("--no-power", action="store_true", help="skip the power measurement")
    ap.add_argument("--skip-calibrated", action="store_true",
                    help="leave out the calibrated (chosen-message) rows (unchanged rule, slow)")
    args = ap.parse_args()
    global SKIP_CALIBRATED
    SKIP_CALIBRATED = args.skip_calibrated
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    gen = np.random.default_rng(0)
    photos = holdout_photos(args.data)[: args.limit_photos]
    res: dict = json.loads(args.out.read_text()) if args.out.is_file() else {}
    res |= {"machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
                 "torch": torch.__version__, "python": platform.python_version(), "numpy": np.__version__,
                 "search_factors": [round(f, 4) for f in SEARCH_FACTORS], "messages_per_image": args.messages,
                 "holdout_photos": {kind: sum(k == kind for _, k, _ in photos) for kind in ("photo", "manga")}}
    for k in args.bits:
        t1 = time.perf_counter()
        decoder, null = load_decoder(k), load_null_model(k)
        msgs = gen.integers(0, 2, (args.messages, k)).astype(np.int8)
        # 32 bits: the full scale search; other lengths: the images as given (known size), to save CPU time
        pb = readings_of([im for _, _, im in photos], decoder, factors=SEARCH_FACTORS if k == 32 else (1.0,))
        kinds = [kd for _, kd, _ in photos]
        r = {"photos": singles(pb, msgs, null, k),
             "photos_aligned_messages": aligned_singles(pb, kinds, null, gen, k)}
        for kind in sorted(set(kinds)):
            stratum = next(s for s in null.strata if s.name == f"{kind}/down")
            r[f"bias_{kind}"] = bias_test(first_bits([rd for rd, kd in zip(pb, kinds) if kd == kind]), stratum)
        r["match_bias_photos"] = match_bias_test(pb, args.messages)
        if k == 32:
            rb = readings_of(holdout_renders(args.data), decoder)
            r["renders"] = singles(rb, msgs, null, k)
            r["renders_aligned_messages"] = aligned_singles(rb, ["render"] * len(rb), null, gen, k)["render"]
            r["bias_render"] = bias_test(first_bits(rb),
                                         next(s for s in null.strata if s.name == "render/down"))
            r["match_bias_renders"] = match_bias_test(rb, args.messages)
            rsets = [readings_of(fr, decoder, embed_size=(256, 256))
                     for fr in render_sets(args.data, args.render_sets, 40)]
            psets = [readings_of(fr, decoder) for fr in photo_sets(photos, args.photo_sets, 40)]
            for size in (10, 40):
                r[f"render_sets_{size}"] = set_results(rsets, msgs, null, k, size)
                r[f"photo_sets_{size}"] = set_results(psets, msgs, null, k, size)
            if not args.no_power:
                r["power"] = power(decoder, null, args.cache)
        r["seconds"] = round(time.perf_counter() - t1, 1)
        res[f"k{k}"] = r
        print(f"k={k} done in {r['seconds']} s", flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(args.out, "w") as f:
            f.write(json.dumps(res, indent=1) + "\n")
    res["seconds"] = round(time.perf_counter() - t0, 1)
    with atomic_write(args.out, "w") as f:
        f.write(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
