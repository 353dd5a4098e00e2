"""The pool's loss pass (#26), A/B in one process: what the references made once per view buy.

Times forward + backward of :func:`gsw.fingerprint.batched.batched_loss` (wavelets, decoder, LPIPS, message BCE)
for K renders of H x W that require grad, the rasteriser left out, under these rules:

* ``joint``: LPIPS on one batch of renders and references with the backward through both halves (the pool up to
  commit a0e4a46: ``torch.cat([x, y])`` put the references into the graph);
* ``split``: the references' LPIPS features without gradient, recomputed per call (``LPIPS.forward`` now);
* ``cached``: :class:`gsw.fingerprint.batched.References` made once: the references' LPIPS features and wavelet
  details, so one transform of the renders serves the decoder and the subband term;
* ``cached+fold``: the same with the decoder's BatchNorms folded into its convolutions (the pool now);
* ``cached+fold+bf16`` (CUDA only, not used by gsw): the decoder and LPIPS under bfloat16 autocast, the wavelet and
  pixel terms in float32: what mixed precision would buy, and how far its gradient moves;
* ``cached+fold+klein`` (with ``--klein``): ``cached+fold`` with the folded decoder read through
  :class:`gsw.decoder.KleinReadout` (four decoder passes per render; #22): what that readout would cost the pool
  (its loss and gradient differ from ``joint``'s by design).

(The first GPU run, ``pool_loss_ab_h200.json``, had ``cached`` with the LPIPS features only and a channels-last
rule, since dropped.) Each rule: ``--warmup`` passes, then the median of ``--repeats`` timed passes (CUDA events
around each pass), and the largest difference of its loss / render gradient from ``joint``'s.

    python benchmarks/pool_loss_ab.py --device cuda --k 16 --size 800 --out benchmarks/results/pool_loss_ab_h200.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch


class _Fn(torch.nn.Module):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def forward(self, *a):
        return self.fn(*a)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--k", type=int, default=16)
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--lpips", default="alex")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--klein", action="store_true", help="also the cached+fold+klein rule")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    from gsw.decoder.zoo import load_decoder
    from gsw.decoder.dwt import dwt2
    from gsw.decoder.hidden import fold_batchnorm
    from gsw.fingerprint.batched import References, batched_loss
    from gsw.mark.loss import LossWeights, WatermarkLoss, lpips_weights

    dev = torch.device(args.device)
    gen = torch.Generator().manual_seed(0)
    k, s = args.k, args.size
    originals = torch.rand(k, 3, s, s, generator=gen).to(dev)
    renders0 = (originals + 0.02 * torch.randn(k, 3, s, s, generator=gen).to(dev)).clamp(0, 1)
    messages = torch.randint(0, 2, (k, args.bits), generator=gen).float().to(dev)
    weights = torch.full((k,), 0.15, device=dev)

    class Autocast(torch.nn.Module):
        """``module`` under bfloat16 autocast, its output back in float32."""

        def __init__(self, module):
            super().__init__()
            self.module = module

        def forward(self, *a):
            with torch.autocast(dev.type, dtype=torch.bfloat16):
                return self.module(*a).float()

        def __getattr__(self, name):
            try:
                return super().__getattr__(name)
            except AttributeError:
                return getattr(self.module, name)

    def make_loss(fold=False, bf16=False, klein=False):
        from gsw.decoder import KleinReadout

        decoder = load_decoder(args.bits).eval()
        decoder = fold_batchnorm(decoder) if fold else decoder
        decoder = KleinReadout(decoder) if klein else decoder
        loss = WatermarkLoss(decoder, lpips_weights(args.lpips, LossWeights()), args.lpips).to(dev)
        if bf16:
            loss.decoder = Autocast(loss.decoder)
            lp = loss.lpips
            lp.distance = lambda x, refs, f=lp.distance: Autocast(_Fn(f))(x, refs)
        return loss

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    rules = {}
    variants = ["joint", "split", "cached", "cached+fold"] + (["cached+fold+bf16"] if dev.type == "cuda" else []) + (
        ["cached+fold+klein"] if args.klein else [])
    for name in variants:
        loss = make_loss(fold="fold" in name, bf16=name.endswith("bf16"), klein=name.endswith("klein"))
        refs = None
        if name.startswith("cached"):
            with torch.no_grad():
                refs = References(dwt2(originals)[1], loss.lpips.references(originals))

        def one_pass():
            r = renders0.clone().requires_grad_(True)
            t = originals.clone().requires_grad_(name == "joint")
            total, _ = batched_loss(loss, r, t, messages, None, weights, refs)
            total.backward()
            return total.detach(), r.grad

        times = []
        for i in range(args.warmup + args.repeats):
            if dev.type == "cuda":
                a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                a.record()
                value, grad = one_pass()
                b.record()
                sync()
                ms = a.elapsed_time(b)
            else:
                t0 = time.perf_counter()
                value, grad = one_pass()
                ms = 1e3 * (time.perf_counter() - t0)
            if i >= args.warmup:
                times.append(ms)
        rules[name] = dict(ms=statistics.median(times), ms_min=min(times), value=float(value), grad=grad)
        del loss, refs
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    base = rules["joint"]
    rows = []
    for name, r in rules.items():
        rows.append(dict(rule=name, ms_median=r["ms"], ms_min=r["ms_min"], ms_per_render=r["ms"] / k,
                         speedup_vs_joint=base["ms"] / r["ms"], loss=r["value"],
                         loss_rel_diff=abs(r["value"] - base["value"]) / abs(base["value"]),
                         grad_max_abs_diff=float((r["grad"] - base["grad"]).abs().max()),
                         grad_max_abs=float(base["grad"].abs().max())))
        print(json.dumps(rows[-1]), flush=True)
    machine = dict(device=str(dev), gpu=torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                   cpu=platform.processor() or platform.machine(), torch=torch.__version__,
                   python=platform.python_version(), date=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()))
    out = dict(k=k, size=s, bits=args.bits, lpips=args.lpips, warmup=args.warmup, repeats=args.repeats,
               machine=machine, rows=rows)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
