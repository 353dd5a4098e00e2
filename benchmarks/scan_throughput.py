"""`gsw scan` throughput (#26, #27): images per second, per-source vs batched, in one process and on Ray.

1. A crawl of ``--images`` N files in ``--workdir`` (kept between runs: a rerun with the same settings reuses
   it): ``--views`` distinct renders of the built-in scene at ``--size`` (or of the INRIA model folder
   ``--model``, e.g. a trained lego, at its cameras' size) written as PNG, then replicas of them with light
   re-encoding (JPEG, quality 85-95) up to N, written by a pool of threads.
2. A registry of ``--marks`` M random 32-bit marks (``--chosen`` of them of origin "chosen", the others
   "random"); the first ``--carriers`` are the messages the decoder reads from the first renders (factor 1),
   (the bits of the reading the exact test picks), so those renders (and their replicas, while the
   re-encoding keeps the bits) carry a registered mark without an embedding: the decoder's work per image
   is the same as on a marked render.
3. Each ``--modes`` entry times :func:`gsw.fingerprint.scan.scan` end to end over the N files (reading, decoding,
   testing; the registry already open; Ray's start excluded, its workers' start and decoder loading
   included):

   * ``per-source``: the path ``gsw scan`` took before the batched pipeline (up to commit 823c404): one
     :func:`gsw.mark.identify.identify` per source (the decoders given; each call checks them and resolves
     their null models again), the next source read ahead on one thread;
   * ``batched``: ``scan(use_ray=False, batch_size=--batch-size, readers=--readers)`` on ``--device``
     (one GPU);
   * ``batched-f32``: the same with the readers before commit 61f9121 (images decoded to contiguous float32 on
     the reader threads instead of kept as views of their uint8 samples), for an A/B in one run;
   * ``host-only``: ``batched`` with the decoder replaced by random logits (the readings of the scale search,
     nothing decoded): the rate one worker's host side (reading, the pipeline, the tests) sustains;
   * ``ray``: ``scan(use_ray=True, workers=--workers)`` on a local Ray cluster started here with ``--gpus``
     GPUs (``CUDA_VISIBLE_DEVICES`` restricted to the first ``--gpus`` when it is not set) or, on the CPU,
     ``--workers`` CPUs: one Ray Data worker per GPU (per CPU), each running the batched pipeline. Ray Data
     starts its workers for every scan; after the timed scan, the same scan over one file per worker is
     timed (``startup_s``: worker start, imports, decoder loading), and ``images_per_s_after_startup``
     divides by the difference (an estimate of the steady rate).

   The modes run in turn ``--repeats`` times (interleaved, so that a change of the machine's load hits them
   alike); the summary gives each mode's median. Every run's rows are compared with the first run's
   (identified labels and best p-values).
4. A JSON (``--out``) with the machine, versions, load averages before/after every mode, the settings and the
   results (with each pipeline's stage times, :class:`gsw.fingerprint.scan.StageTimes`, and their sums per worker
   process), and a summary table on stdout.

CPU (this 2-core machine; BENCHMARKS.md "Per-recipient fingerprints", `gsw scan`; add ``--batch-size 64`` for
scan_cpu_batch64.json):
    python benchmarks/scan_throughput.py --images 48 --size 256 --marks 14 --modes per-source,batched,ray \
        --workers 2 --repeats 2 --threads 1 --workdir /tmp/scan48 --out benchmarks/results/scan_cpu.json

GPU, 10,000 images at 800x800 against 64 marks on 1 and 2 GPUs of one host (#27; Ray with its data extra must
be importable; the crawl, ~1-2 GB of JPEG and PNG, is written once into --workdir and reused by the second
command; ``--per-source-images 500`` times the old path on the first 500 files only):
    python benchmarks/scan_throughput.py --images 10000 --size 800 --marks 64 --device cuda --gpus 1 \
        --readers 8 --modes per-source,batched,ray --per-source-images 500 --workdir /tmp/scan10k \
        --out benchmarks/results/scan_cuda_1gpu.json
    python benchmarks/scan_throughput.py --images 10000 --size 800 --marks 64 --device cuda --gpus 2 \
        --readers 8 --modes ray --workdir /tmp/scan10k --out benchmarks/results/scan_cuda_2gpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from unittest import mock

ROOT = Path(__file__).resolve().parents[1]
MODES = ("per-source", "batched", "batched-f32", "host-only", "ray")
#: The :class:`gsw.fingerprint.scan.StageTimes` fields summed per worker process.
STAGES = ("wall", "read_wait", "decode_wait", "test", "decode", "sources")


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=64, help="files in the crawl (N)")
    ap.add_argument("--views", type=int, default=16, help="distinct renders (the rest are re-encoded replicas)")
    ap.add_argument("--size", type=int, default=256, help="built-in scene: render width = height")
    ap.add_argument("--model", help="an INRIA model folder to render instead of the built-in scene")
    ap.add_argument("--marks", type=int, default=14, help="registered marks (M)")
    ap.add_argument("--chosen", type=int, default=0, help="of which of origin 'chosen'")
    ap.add_argument("--carriers", type=int, default=4, help="marks whose message a render carries")
    ap.add_argument("--modes", default="per-source,batched", help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--per-source-images", type=int, default=0,
                    help="time the per-source mode on the first this many files only (0: all)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--gpus", type=int, default=0, help="GPUs of the local Ray cluster (and CUDA_VISIBLE_DEVICES)")
    ap.add_argument("--workers", type=int, default=None, help="Ray workers (default: --gpus, or the CPU count)")
    ap.add_argument("--batch-size", type=int, default=None, help="default: gsw's for the device (64 CUDA, 4 CPU)")
    ap.add_argument("--readers", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=1, help="runs of every mode, interleaved")
    ap.add_argument("--threads", type=int, default=0, help="torch threads of this process (0: torch's default)")
    ap.add_argument("--shard", default=None, metavar="I/N",
                    help="scan only files I, I+N, I+2N, ... of the crawl (several processes side by side, one per "
                         "GPU: whether the host limits them without Ray)")
    ap.add_argument("--sources-per-call", type=int, default=None,
                    help="Ray Data calls of at most this many x batch sources (gsw's RAY_SOURCES_PER_CALL)")
    ap.add_argument("--workdir", default=None, help="crawl folder (default: a new temporary one)")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/scan_<device>.json)")
    args = ap.parse_args()
    bad = [m for m in args.modes.split(",") if m not in MODES]
    if bad or args.images < 1 or not 1 <= args.views <= args.images or args.marks < max(1, args.carriers, args.chosen):
        ap.error(f"bad --modes {bad}" if bad else "need --images >= --views >= 1 and --marks >= --carriers, --chosen")
    if args.gpus and args.device != "cuda":
        ap.error("--gpus needs --device cuda")
    if args.shard is not None:
        try:
            i, n = map(int, args.shard.split("/"))
        except ValueError:
            ap.error(f"--shard takes I/N, got {args.shard!r}")
        if not 0 <= i < n:
            ap.error(f"--shard I/N needs 0 <= I < N, got {args.shard}")
        args.shard = (i, n)
    return args


def _renders(args: argparse.Namespace, device: str) -> list:
    """``--views`` [3, H, W] renders in [0, 1] (CPU)."""
    import torch

    from gsw.render.rasterize import rasterize

    if args.model:
        from gsw.data import load_inria_model

        model = load_inria_model(args.model)
        gaussians, background = model.gaussians, torch.ones(3)
        cams = [model.cameras[i * len(model.cameras) // args.views] for i in range(args.views)]
    else:
        from gsw.scenes import default_scene

        scene = default_scene(width=args.size, height=args.size, n_cameras=args.views)
        gaussians, cams, background = scene.gaussians, scene.cameras, scene.background
    gaussians, background = gaussians.to(device), background.to(device)
    with torch.no_grad():
        return [rasterize(gaussians, cam, background=background).image.clamp(0, 1).cpu() for cam in cams]


def _crawl(args: argparse.Namespace, workdir: Path, device: str) -> list[Path]:
    """The N files (written unless ``workdir`` already holds this crawl)."""
    from gsw.data.images import read_image, write_image

    stamp = workdir / "crawl.json"
    key = dict(images=args.images, views=args.views, size=args.size, model=args.model)
    names = [f"v{i:05d}.png" if i < args.views else f"r{i:05d}.jpg" for i in range(args.images)]
    if stamp.is_file() and json.loads(stamp.read_text()) == key:
        return [workdir / "crawl" / n for n in names]
    (workdir / "crawl").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    renders = _renders(args, device)
    for i, img in enumerate(renders):
        write_image(workdir / "crawl" / names[i], img)
    base = [read_image(workdir / "crawl" / names[i]) for i in range(len(renders))]  # what the replicas re-encode

    def replica(i: int) -> None:
        write_image(workdir / "crawl" / names[i], base[i % len(base)], quality=85 + (i // len(base)) % 11)

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(replica, range(len(renders), args.images)))
    stamp.write_text(json.dumps(key))
    print(f"wrote {args.images} files in {time.perf_counter() - t0:.1f} s", flush=True)
    return [workdir / "crawl" / n for n in names]


def _registry(args: argparse.Namespace, workdir: Path, paths: list[Path]) -> list:
    """The M marks (a new registry file each run)."""
    import torch

    from gsw.io.video import load_images_or_video
    from gsw.mark.detect import load_decoder_for
    from gsw.mark.message import message_to_hex, random_message
    from gsw.mark.randomization import choose_reading
    from gsw.mark.scales import read_images
    from gsw.registry import open_registry, shipped_decoder_sha256

    decoder = load_decoder_for(32, None, torch.device("cpu"))
    carried = []
    for p in paths[:min(args.carriers, args.views, len(paths))]:  # the reading the exact test picks
        reading = read_images(load_images_or_video([p]), decoder)[0]
        carried.append(message_to_hex(reading.bits[choose_reading(reading.confidence)]))
    messages = carried + [message_to_hex(random_message(32, seed=10_000 + i)) for i in range(args.marks - len(carried))]
    origins = ["random"] * (args.marks - args.chosen) + ["chosen"] * args.chosen
    path = workdir / f"marks-{os.getpid()}.sqlite"
    with open_registry(path) as reg:
        reg.add_many([dict(label=f"m{i}", message=m, origin=o, decoder_sha256=shipped_decoder_sha256(32))
                      for i, (m, o) in enumerate(zip(messages, origins))])
        marks = reg.list()
    path.unlink()
    return marks


def _per_source(paths: list[Path], marks: list, device: str | None) -> list:
    """The scan path before the batched pipeline: one identify per source, one reader thread ahead."""
    from gsw.decoder.zoo import load_decoder
    from gsw.fingerprint.scan import ScanRow
    from gsw.io.video import load_images_or_video
    from gsw.mark.identify import identify
    from gsw.registry import shipped_decoder_sha256

    decoders = {shipped_decoder_sha256(k): load_decoder(k).to(device or "cpu") for k in {m.num_bits for m in marks}}
    rows = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        for path, images in zip(paths, pool.map(lambda p: load_images_or_video([p], 16), paths)):
            res = identify(images, marks, decoders=decoders, device=device)
            best = res.results[0]
            rows.append(ScanRow(str(path), len(images), ";".join(res.recipients), best.mark.label,
                                best.adjusted_p_value, best.p_value, best.best_bit_accuracy))
    return rows


def _batched_f32(paths: list[Path], marks: list, device, args: argparse.Namespace, times: list) -> list:
    """``batched`` with the readers of commit 51831ad and before: every image decoded to contiguous float32 on
    its reader thread (4x the bytes to move, and a torch copy per image there)."""
    import gsw.fingerprint.scan as scan_module
    from gsw.io.video import load_images_or_video

    def old_load(path: Path, frames: int) -> tuple[list, str]:
        return load_images_or_video([path], frames), ""

    with mock.patch.object(scan_module, "_load", old_load):
        return _batched(paths, marks, device, args, times)


def _host_only(paths: list[Path], marks: list, device, args: argparse.Namespace, times: list) -> list:
    """``batched`` with the decoder replaced by random logits (one reading per scale of the search): what one
    worker's host side (reading files, the pipeline, the tests) sustains when the decoder costs nothing."""
    import torch

    import gsw.mark.identify as identify_module
    from gsw.mark.scales import Reading, read_plan

    gen = torch.Generator().manual_seed(0)

    def random_readings(images, decoder, *, embed_size=None, batch_size=16, **_):
        plans = [read_plan(int(im.shape[1]), int(im.shape[2]), embed_size=embed_size) for im in images]
        return [Reading([f for f, _ in p], [sz for _, sz in p], torch.randn(len(p), decoder.num_bits, generator=gen))
                for p in plans]

    with mock.patch.object(identify_module, "read_images", random_readings):
        return _batched(paths, marks, device, args, times)


def _batched(paths: list[Path], marks: list, device, args: argparse.Namespace, times: list) -> list:
    """The ``batched`` scan (in this process), for the modes that patch part of it; ``times`` gets its stages."""
    from gsw.fingerprint.scan import scan

    return scan(paths, marks, device=device, use_ray=False, batch_size=args.batch_size, readers=args.readers,
                times=times)


def _machine(args: argparse.Namespace) -> dict:
    import torch

    import gsw

    try:
        import ray

        ray_version = ray.__version__
    except ImportError:
        ray_version = None
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").is_file() else ""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    gpus = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if args.device == "cuda" else []
    return dict(cpu=cpu, cores=os.cpu_count(), torch_threads=torch.get_num_threads(), gpus=gpus,
                cuda_visible_devices=os.environ.get("CUDA_VISIBLE_DEVICES"), python=platform.python_version(),
                torch=torch.__version__, ray=ray_version, gsw=gsw.__version__, commit=commit,
                date=time.strftime("%Y-%m-%d %H:%M:%S %Z"))


def _time_mode(mode: str, args: argparse.Namespace, paths: list[Path], marks: list) -> tuple[dict, list]:
    import torch

    from gsw.fingerprint.scan import scan

    device = None if args.device == "cpu" else torch.device(args.device)
    load_before = os.getloadavg()
    times: list = []
    t0, epoch = time.perf_counter(), time.time()
    if mode == "per-source":
        rows = _per_source(paths, marks, device)
    elif mode == "batched-f32":
        rows = _batched_f32(paths, marks, device, args, times)
    elif mode == "host-only":
        rows = _host_only(paths, marks, device, args, times)
    else:
        rows = scan(paths, marks, device=device, use_ray=mode == "ray", workers=args.workers,
                    batch_size=args.batch_size, readers=args.readers, times=times)
    if device is not None:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    res = dict(mode=mode, images=len(paths), seconds=seconds, images_per_s=len(paths) / seconds,
               identified=sum(bool(r.identified) for r in rows), errors=sum(bool(r.error) for r in rows),
               load_before=load_before, load_after=os.getloadavg(), stages=[asdict(t) for t in times])
    if times:  # per worker process: when it ran its calls, and its pipelines' stage seconds summed
        res["timeline"] = tl = _timeline(times, epoch, len(paths))
        res["stages_by_worker"] = [w["stages"] for w in tl["workers"]]
        print(f"{mode} timeline: calls from {tl['first_call']:.2f} to {tl['last_end']:.2f} s, "
              f"{tl['scanning_rate']:.1f} images/s between; per worker (ready s, calls, busy s, images/s busy): "
              + "; ".join(f"{w['ready']}, {len(w['calls'])}, {w['busy_s']:.2f}, {w['busy_rate']:.1f}"
                          for w in tl["workers"]), flush=True)
        print(f"{mode} stages per worker (s): " + "; ".join(
            ", ".join(f"{k} {v:.1f}" if k != "sources" else f"{v} sources" for k, v in w.items())
            for w in res["stages_by_worker"]), flush=True)
    if mode == "ray":
        import ray

        res["workers"] = workers = args.workers or int(ray.cluster_resources().get("GPU" if device else "CPU", 1))
        t0 = time.perf_counter()  # the same scan over one file per worker: the workers' start, decoders' loading
        scan(paths[:workers], marks, device=device, use_ray=True, workers=workers, batch_size=args.batch_size,
             readers=args.readers)
        res["startup_s"] = time.perf_counter() - t0
        res["images_per_s_after_startup"] = len(paths) / max(seconds - res["startup_s"], 1e-9)
    return res, rows


def _timeline(times: list, epoch: float, images: int) -> dict:
    """Per worker process: when it was ready and ran its calls (seconds from the scan's start), its rate while
    busy and its pipelines' stage seconds summed; and the scanning phase (first call's start to last call's end)."""
    workers: dict = {}
    for t in sorted(times, key=lambda t: t.started):
        w = workers.setdefault(t.pid, dict(ready=round(t.worker_ready - epoch, 3) if t.worker_ready else None,
                                           init_s=round(t.worker_init, 3), calls=[], busy_s=0.0, sources=0,
                                           stages=dict.fromkeys(STAGES, 0)))
        w["calls"].append([round(t.started - epoch, 3), round(t.ended - epoch, 3), t.sources])
        w["busy_s"] += t.ended - t.started
        w["sources"] += t.sources
        for k in STAGES:
            w["stages"][k] += getattr(t, k)
    for w in workers.values():
        w["busy_rate"] = w["sources"] / max(w["busy_s"], 1e-9)
    first = min(t.started for t in times) - epoch
    last = max(t.ended for t in times) - epoch
    return dict(first_call=first, last_end=last, scanning_rate=images / max(last - first, 1e-9),
                workers=list(workers.values()))


def main() -> int:
    args = _parse_args()
    if args.gpus and "CUDA_VISIBLE_DEVICES" not in os.environ:
        os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, range(args.gpus)))
    import tempfile

    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="scan_throughput_"))
    modes = args.modes.split(",")
    paths = _crawl(args, workdir, args.device)
    marks = _registry(args, workdir, paths)
    if args.shard is not None:
        paths = paths[args.shard[0]::args.shard[1]]
    if args.sources_per_call is not None:
        import gsw.fingerprint.scan as scan_module

        scan_module.RAY_SOURCES_PER_CALL = args.sources_per_call  # read on this process (the driver)
    if "ray" in modes:
        import ray

        ray.init(num_cpus=None if args.gpus else (args.workers or os.cpu_count()), num_gpus=args.gpus or None,
                 include_dashboard=False, log_to_driver=False)
    results, first = [], None
    for _ in range(args.repeats):
        for mode in modes:
            subset = paths[:args.per_source_images] if mode == "per-source" and args.per_source_images else paths
            res, rows = _time_mode(mode, args, subset, marks)
            if first is None and mode != "host-only":  # random logits: nothing to agree with
                first = {r.source: r for r in rows}
            same = [r for r in rows if r.source in first] if first is not None and mode != "host-only" else []
            res["agree_with_first"] = sum((r.identified, r.best_p) == (first[r.source].identified,
                                                                       first[r.source].best_p) for r in same)
            res["compared"] = len(same)
            results.append(res)
            print(json.dumps(res), flush=True)
    from PIL import Image

    with Image.open(paths[0]) as first_image:
        image_size = list(first_image.size)
    summary = []
    for mode in modes:
        runs = [r for r in results if r["mode"] == mode]
        summary.append(dict(mode=mode, workers=runs[0].get("workers", 1), images=runs[0]["images"],
                            images_per_s=statistics.median(r["images_per_s"] for r in runs),
                            runs=[round(r["images_per_s"], 3) for r in runs], identified=runs[0]["identified"],
                            after_startup=statistics.median(r.get("images_per_s_after_startup", r["images_per_s"])
                                                            for r in runs),
                            errors=runs[0]["errors"], agree=sum(r["agree_with_first"] for r in runs),
                            compared=sum(r["compared"] for r in runs)))
    machine = _machine(args)
    out = dict(settings=vars(args), machine=machine, image_size=image_size, marks=len(marks),
               summary=summary, results=results)
    dest = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"scan_{args.device}.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.tmp")
    tmp.write_text(json.dumps(out, indent=1) + "\n")
    tmp.replace(dest)
    print(f"\n{image_size[0]}x{image_size[1]}, {len(marks)} marks, batch {args.batch_size or 'default'}, "
          f"{args.readers} readers, "
          f"torch threads {machine['torch_threads']}, load {os.getloadavg()[0]:.1f}")
    print(f"{'mode':<11} {'workers':>7} {'images':>7} {'images/s (median)':>18} {'after startup':>13} {'runs':<24} "
          f"{'identified':>10} {'errors':>6} {'agree':>11}")
    for r in summary:
        print(f"{r['mode']:<11} {r['workers']:>7} {r['images']:>7} {r['images_per_s']:>18.2f} "
              f"{r['after_startup']:>13.2f} "
              f"{','.join(map(str, r['runs'])):<24} {r['identified']:>10} {r['errors']:>6} "
              f"{r['agree']:>5}/{r['compared']:<5}")
    print(f"written {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
