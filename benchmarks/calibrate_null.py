"""Calibrates the shipped decoders' null models: ``gsw/decoder/weights/null_k{32,48,64}.json`` (CPU).

What each decoder reads on unmarked content (:mod:`gsw.decoder.null`), measured on the CALIBRATION
split only (the HOLD-OUT split, :func:`gsw.decoder.null.is_holdout`, is left for
``benchmarks/detection_null.py``):

* photos: ``unmarked/{sun80,urban100,manga109}`` images not held out, and all of ``bsds500/{train,val}``;
* renders of unmarked scenes: the built-in scene (:func:`gsw.scenes.default_scene`, seed 0, SH 3) and the
  PLY fixture ``ply/sh3_fixture`` from orbit cameras (:func:`calibration_renders`) at 128, 256 and
  512 px.

Every image is read as the detector reads it (:func:`gsw.mark.scales.read_plan`): photos at factor 1
and at one more factor of their search plan (chosen by a hash of the name, so every factor is covered),
renders at every factor of their plan.  Strata (:func:`gsw.decoder.null.fit_null_model`): content kind
(``photo`` = sun80 + urban100, ``manga``, ``bsds`` -- the decoder's own training and whitening photos,
kept apart because the decoder is centred on them -- and ``render``) x reading direction (``down``:
factor <= 1, ``up``: enlarged).  All readings of one image count as one calibration image for the
estimate's uncertainty.  Deterministic: same data + same code -> same JSON (decoded bits are cached in
``--cache``, keyed by the decoder's sha256 and the reading list; ``--from-cache`` refits from them).

    PYTHONPATH=. python benchmarks/calibrate_null.py --data ../shared/data       # all three bit lengths
    PYTHONPATH=. python benchmarks/calibrate_null.py --bits 32 --from-cache      # refit only
    PYTHONPATH=. python benchmarks/calibrate_null.py --readout klein             # through KleinReadout:
                                                                                 # null_k{bits}_klein.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import time
from collections.abc import Iterator
from pathlib import Path

import torch

from gsw.decoder import KleinReadout
from gsw.decoder.null import fit_null_model, is_holdout, null_path
from gsw.decoder.zoo import load_decoder, sha256_file, weights_path
from gsw.mark.scales import SEARCH_FACTORS, read_images, read_plan

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
PHOTO_SETS = (("unmarked/sun80", "photo"), ("unmarked/urban100", "photo"), ("unmarked/manga109", "manga"))
BSDS_SETS = ("bsds500/train", "bsds500/val")
RENDER_SIZES = (128, 256, 512)


def photo_files(data: Path, holdout: bool) -> list[tuple[str, str]]:
    """(name relative to ``data``, kind) of the unmarked photos of one split, sorted; bsds500 belongs to the
    calibration split only."""
    out = [(f"{folder}/{p.name}", kind) for folder, kind in PHOTO_SETS
           for p in sorted((data / folder).glob("*.jpg")) if is_holdout(f"{folder}/{p.name}") == holdout]
    if not holdout:
        out += [(f"{folder}/{p.name}", "photo") for folder in BSDS_SETS for p in sorted((data / folder).glob("*.jpg"))]
    if not out:
        raise FileNotFoundError(f"no unmarked photos under {data} (expected {[f for f, _ in PHOTO_SETS]})")
    return out


def fixture_orbit(data: Path, n: int, size: int, *, up=(0.0, 0.0, 1.0), radius_scale: float = 1.0,
                  elevation: float = 20.0, offset: float = 0.0):
    """The PLY fixture and ``n`` orbit cameras around its content (its centre is the median of the means;
    radius 900 world units frames the ~400-unit object)."""
    from gsw.camera import orbit_cameras
    from gsw.io.ply import load_ply

    g = load_ply(data / "ply" / "sh3_fixture" / "point_cloud.ply")
    center = g.means.median(0).values.double().tolist()
    cams = orbit_cameras(center, 900.0 * radius_scale, n, width=size, height=size, up=up,
                         elevation_deg=elevation, azimuth_offset_deg=offset)
    return g, cams


def render_all(g, cams, background) -> list[torch.Tensor]:
    from gsw.render.rasterize import rasterize

    with torch.no_grad():
        return [rasterize(g, c, background=background).image.clamp(0, 1) for c in cams]


def calibration_renders(data: Path) -> Iterator[tuple[str, str, torch.Tensor]]:
    """(name, "render", image) of the unmarked calibration renders: 8 orbit views (elevation 30 deg) of the
    built-in scene (seed 0) and 8 of the PLY fixture (up +z, elevation 20 deg), at each of
    :data:`RENDER_SIZES`."""
    from gsw.scenes import default_cameras, default_scene

    scene = default_scene(seed=0)
    for size in RENDER_SIZES:
        cams = default_cameras(8, size, size)
        for i, img in enumerate(render_all(scene.gaussians, cams, scene.background)):
            yield f"render/default_seed0/view{i}_{size}", "render", img
        g, cams = fixture_orbit(data, 8, size)
        for i, img in enumerate(render_all(g, cams, (0.0, 0.0, 0.0))):
            yield f"render/sh3_fixture/view{i}_{size}", "render", img


def _hash_index(name: str, n: int) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "big") % n


def calibration_factors(name: str, kind: str, height: int, width: int) -> list[float]:
    """The reading factors of one calibration image: all of its plan for renders; factor 1 and one other
    factor of the plan (hash of the name) for photos."""
    plan = [f for f, _ in read_plan(height, width)]
    if kind == "render" or len(plan) == 1:
        return plan
    return [plan[0], plan[1 + _hash_index(name, len(plan) - 1)]]


def decode_calibration(decoder, items: list[tuple[str, str, torch.Tensor]]) -> list[dict]:
    """Reads every image at its calibration factors: one record (name, kind, factor, size, bits) per reading."""
    records = []
    by_factors: dict[tuple[float, ...], list[int]] = {}
    for i, (name, kind, img) in enumerate(items):
        by_factors.setdefault(tuple(calibration_factors(name, kind, *img.shape[-2:])), []).append(i)
    for factors, idx in sorted(by_factors.items()):
        readings = read_images([items[i][2] for i in idx], decoder, factors=factors)
        for i, r in zip(idx, readings):
            for f, size, b in zip(r.factors, r.sizes, r.bits.to(torch.uint8).tolist()):
                records.append({"name": items[i][0], "kind": items[i][1], "factor": f, "size": list(size), "bits": b})
    records.sort(key=lambda r: (r["name"], r["factor"]))
    return records


def load_items(data: Path) -> list[tuple[str, str, torch.Tensor]]:
    from gsw.data.images import read_image

    items = [(name, kind, (read_image(data / name)[:3] * 255).round().to(torch.uint8))
             for name, kind in photo_files(data, holdout=False)]
    return items + list(calibration_renders(data))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bits", type=int, nargs="+", default=[32, 48, 64])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--output", type=Path, default=None, help="folder of the JSON files (default: beside the weights)")
    ap.add_argument("--cache", type=Path, default=ROOT / "build" / "null_calibration")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--readout", choices=("direct", "klein"), default="direct",
                    help="calibrate the decoder read directly or through gsw.decoder.KleinReadout")
    ap.add_argument("--from-cache", action="store_true",
                    help="refit from the decoded bits in --cache without loading the images")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    items = [] if args.from_cache else load_items(args.data)
    print(f"{len(items)} calibration images loaded in {time.perf_counter() - t0:.1f} s", flush=True)
    key_src = json.dumps([(n, k, list(im.shape)) for n, k, im in items]).encode()
    for k in args.bits:
        t1 = time.perf_counter()
        wfile = weights_path(k)
        sha = sha256_file(wfile)
        tag = f"k{k}_{sha[:12]}" + ("" if args.readout == "direct" else f"_{args.readout}")
        cache = args.cache / f"{tag}_{hashlib.sha256(key_src).hexdigest()[:12]}.json"
        if args.from_cache:
            found = sorted(args.cache.glob(f"{tag}_[0-9a-f]*.json"))
            if len(found) != 1:
                raise SystemExit(f"--from-cache: expected one cache file {tag}_*.json in {args.cache}, "
                                 f"found {len(found)}")
            cache = found[0]
        decoder = load_decoder(k) if args.readout == "direct" else KleinReadout(load_decoder(k)).eval()
        if cache.is_file():
            records = json.loads(cache.read_text())
        else:
            records = decode_calibration(decoder, items)
            cache.parent.mkdir(parents=True, exist_ok=True)
            cache.write_text(json.dumps(records))
        provenance = {
            "script": "benchmarks/calibrate_null.py", "torch": torch.__version__, "python": platform.python_version(),
            "readout": args.readout,
            "search_factors": [round(f, 6) for f in SEARCH_FACTORS], "render_sizes": list(RENDER_SIZES),
            "split": "unmarked/{sun80,urban100,manga109}: calibration = not gsw.decoder.null.is_holdout(name); "
                     "bsds500/{train,val}: calibration only; renders: built-in scene seed 0 (8 orbit views, "
                     "elevation 30) + ply/sh3_fixture (8 orbit views, up +z, elevation 20)",
        }
        for r in records:  # bsds500 trained the decoder and centred its whitening: a stratum of its own
            r["kind"] = "bsds" if r["name"].startswith("bsds500/") else r["kind"]
        model = fit_null_model(records, k, decoder=decoder, decoder_sha256=sha, provenance=provenance)
        out = null_path(k, args.output, args.readout)
        model.save(out)
        print(f"k={k}: {len(records)} readings of {model.calibration['images']} images -> {out} "
              f"({time.perf_counter() - t1:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
