"""False identifications of `gsw identify` on unmarked HOLD-OUT images against a registry of 1,000 marks.

Every image is one source: :func:`gsw.mark.identify.identify` tests it against all 1,000 registered marks
(calibrated null model, scale search or the registered embedding size, Holm over the marks). An image is a
false identification at level ``a`` when its smallest Holm-adjusted p-value is at or below ``a``.

Unmarked images, none used by ``benchmarks/calibrate_null.py``:

* photos: the held-out half of ``unmarked/{sun80,manga109}`` (:func:`gsw.decoder.null.is_holdout`), each
  as given, at half size and as four 256x256 crops (corners of the central area) -- 6 images per photo;
* renders: the built-in scene with another seed (1) and the PLY fixture seen with another up axis (-y), at
  160 and 256 px, from orbits at 3 elevations (the calibration used seed 0 / up +z, other orbits);
* NeRF-synthetic lego ground-truth views (all 100, white background, 400 px): a scene the calibration
  never saw.

Registry: 1,000 marks with random 32-bit messages (seeded here), the shipped decoder, embedding sizes
alternating between none (scale search) and 256x256 (every image resized to it), written through
:func:`gsw.registry.open_registry` into a temporary SQLite file.

``--origin random`` (default since the exact randomization test): the marks are registered as random
messages (they are: drawn here), so each is tested with :mod:`gsw.mark.randomization`'s exact test, whose
adjusted p-values are exact at every level (1e-2 reported too). ``--origin chosen`` reproduces the calibrated
run: identification runs at ``fpr = 1e-3`` with ``exact=0``: every mark whose fair-coin lower bound is at or
below 1e-3 gets its calibrated p-value, so every Holm-adjusted p-value at or below 1e-3 is exact and the
decisions at 1e-3 and 1e-6 are read off the same run (1e-2 would need ~10x more calibrated tail tables,
too slow for the shared 2-core machine).

    PYTHONPATH=. python benchmarks/identify_null.py --data ../shared/data
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from calibrate_null import DATA, ROOT, fixture_orbit, render_all
from detection_null import holdout_photos
from gsw._atomic import atomic_write
from gsw.stats import clopper_pearson

LEVELS = (1e-3, 1e-6)
SIZES = (None, (256, 256))  # (width, height) of the registered embeddings: none (scale search) or 256x256


def photo_variants(photos) -> list[tuple[str, torch.Tensor]]:
    from gsw.data.images import resize_image

    out = []
    for name, _, img in photos:
        x = img.float() / 255
        h, w = x.shape[-2:]
        out += [(name, x), (f"{name}@0.5", resize_image(x[None], h // 2, w // 2)[0])]
        for dy in (0, 1):
            for dx in (0, 1):
                y0 = max(0, h // 2 - 256 + dy * 256) if h >= 512 else dy * max(0, h - 256)
                x0 = max(0, w // 2 - 256 + dx * 256) if w >= 512 else dx * max(0, w - 256)
                crop = x[:, y0 : y0 + 256, x0 : x0 + 256]
                if min(crop.shape[-2:]) >= 64:
                    out.append((f"{name}#crop{dy}{dx}", crop))
    return out


def renders(data: Path, per_ring: int) -> list[tuple[str, torch.Tensor]]:
    from gsw.scenes import default_cameras, default_scene

    out = []
    scene = default_scene(seed=1)
    for size in (160, 256):
        for e in (-10.0, 15.0, 45.0):
            cams = default_cameras(per_ring, size, size, elevation_deg=e, azimuth_offset_deg=3.7 + e)
            out += [(f"default_seed1/{size}/e{e:g}/{i}", im) for i, im in
                    enumerate(render_all(scene.gaussians, cams, scene.background))]
            g, fcams = fixture_orbit(data, per_ring, size, up=(0.0, -1.0, 0.0), radius_scale=0.9, elevation=e,
                                     offset=5.3 + e)
            out += [(f"fixture_up-y/{size}/e{e:g}/{i}", im) for i, im in enumerate(render_all(g, fcams, (0.0,) * 3))]
    return out


def lego_views(data: Path) -> list[tuple[str, torch.Tensor]]:
    from gsw.data.loaders import load_nerf_synthetic

    ds = load_nerf_synthetic(data / "lego", "train", downscale=2, holdout_every=0)
    return [(f"lego/{c.name}", im) for c, im in zip(ds.cameras, ds.images)]


def registry_marks(path: Path, n: int, seed: int, origin: str = "random"):
    from gsw.registry import open_registry, shipped_decoder_sha256

    gen = np.random.default_rng(seed)
    sha = shipped_decoder_sha256(32)
    rows = []
    for i in range(n):
        size = SIZES[i % len(SIZES)]
        rows.append(dict(label=f"recipient-{i:04d}", message=gen.integers(0, 2, 32).tolist(), decoder_sha256=sha,
                         width=None if size is None else size[0], height=None if size is None else size[1],
                         origin=origin))
    with open_registry(path) as reg:
        reg.add_many(rows)
        return reg.list()


def summary(min_adjusted: list[float], levels: tuple[float, ...] = LEVELS) -> dict:
    p = np.asarray(min_adjusted)
    out = {"images": int(p.size)}
    for lv in levels:
        c = int((p <= lv).sum())
        lo, hi = clopper_pearson(c, p.size)
        out[f"{lv:g}"] = {"false_identifications": c, "rate": c / p.size, "ci95": [lo, hi]}
    out["smallest_adjusted_p"] = float(p.min())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "identify_null.json")
    ap.add_argument("--marks", type=int, default=1000)
    ap.add_argument("--per-ring", type=int, default=30, help="orbit views per elevation, size and scene")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--limit", type=int, default=None, help="smoke test: only the first N images of each source")
    ap.add_argument("--origin", choices=["random", "chosen"], default="random",
                    help="the registered marks' origin: the exact test (random) or the calibrated one (chosen)")
    args = ap.parse_args()
    levels = (1e-2,) + LEVELS if args.origin == "random" else LEVELS
    torch.set_num_threads(args.threads)
    from gsw.mark.identify import identify

    t0 = time.perf_counter()
    sources = {"renders": renders(args.data, args.per_ring), "lego": lego_views(args.data),
               "photos": photo_variants(holdout_photos(args.data))}
    with tempfile.TemporaryDirectory() as tmp:
        marks = registry_marks(Path(tmp) / "marks.sqlite", args.marks, seed=22, origin=args.origin)
    res: dict = {"machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
                 "torch": torch.__version__, "python": platform.python_version(), "marks": len(marks),
                 "bits": 32, "sizes": [None if s is None else list(s) for s in SIZES], "run_fpr": LEVELS[0],
                 "origin": args.origin}
    everything = []
    for kind, items in sources.items():
        items = items[: args.limit]
        t1 = time.perf_counter()
        best = []
        for _, img in items:
            found = identify(img, marks, fpr=LEVELS[0], exact=0)
            best.append(min(r.adjusted_p_value for r in found.results))
            if len(best) % 50 == 0:
                print(f"{kind}: {len(best)} of {len(items)}, min adjusted p {min(best):.3g}", flush=True)
        res[kind] = summary(best, levels) | {"seconds": round(time.perf_counter() - t1, 1)}
        everything += best
        res["all"] = summary(everything, levels)  # written after every source: a cut run keeps what it measured
        res["seconds"] = round(time.perf_counter() - t0, 1)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(args.out, "w") as f:
            f.write(json.dumps(res, indent=1) + "\n")
        print(kind, json.dumps(res[kind]), flush=True)
    print(json.dumps(res["all"], indent=1))


if __name__ == "__main__":
    main()
