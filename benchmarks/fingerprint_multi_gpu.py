"""`gsw fingerprint` on 1, 2, 4 GPUs of one host through Ray (#27): recipients per hour, scaling, identical copies.

Three steps, each one command (so that each fits one device call; ``--workdir`` carries the state):

1. ``prepare``: trains lego for ``--train-seconds`` (the INRIA recipe cut by time, every 8th view held out,
   as ``fingerprint_throughput.py``), saves it as an INRIA model folder ``WORKDIR/model`` (the embedding
   views' cameras), the held-out cameras ``WORKDIR/held_out.json`` and ``WORKDIR/recipients.csv``: ``--recipients``
   recipients whose 32-bit messages are drawn from ``--seed`` (given in the file, so that every run embeds
   the same messages; the job itself never writes them outside its registry); lego's photos stay (as PNG)
   for FGD.
2. ``run --gpus G``: the ``gsw fingerprint`` command a user runs, in a subprocess, with
   ``CUDA_VISIBLE_DEVICES`` set to the first G GPUs: a local Ray cluster (one task per ``--task-size``
   recipients, ``num_gpus=1`` each, so one worker per GPU), a pool of ``--batch`` slots per task, the early-
   stopping rule ``--early-stop``, lego's photos as ``--images`` (unless ``--no-photos``); output ``WORKDIR/out_G``, registry ``WORKDIR/marks_G.sqlite``. Timed from
   the command's start to its exit (Ray's start, the set-up and every write included) and, apart, its own
   "finetune" time (after the once-per-scene set-up). Recipients per hour = 3600 x recipients / wall time.
   ``--local`` runs ``gsw fingerprint --local`` (one process, no Ray), ``--limit N`` only the first N
   recipients, ``--first-gpu K`` on GPUs K.. (for a run beside another); the run is named by its GPU count,
   ``local``, ``cluster`` and ``xN`` (or ``--tag``). ``--cluster`` starts a Ray cluster first (a process that
   holds one, untimed) and joins it (``--address auto``), as on a host that keeps Ray running: the job then
   pays neither the cluster's start nor its shutdown.
3. ``compare --runs NAME...``: every run's copies against the first run's (normally 1 GPU): bitwise equal
   parameters or the largest difference; then each copy of each run on the held-out views (never used by
   the job): bit accuracy of each view's render with its registered message, PSNR against the original
   model's render (and, from the job's report, the copy's PSNR on its embedding views); scaling efficiency =
   (rate at G GPUs) / (G x rate at 1 GPU), recipients per hour from start to exit: with the same recipients,
   strong scaling; a run of G x as many recipients (``--limit``) gives weak scaling. A larger run's copies are
   compared bitwise where the first run has them.

Results: ``WORKDIR/run_G.json`` and ``--out`` (the summary JSON; a table on stdout).

Usage on a 2-GPU machine (lego photos in DIR; Ray with its data extra importable):
    python benchmarks/fingerprint_multi_gpu.py prepare --data DIR --workdir /tmp/fp27
    python benchmarks/fingerprint_multi_gpu.py run --gpus 1 --workdir /tmp/fp27
    python benchmarks/fingerprint_multi_gpu.py run --gpus 2 --workdir /tmp/fp27
    python benchmarks/fingerprint_multi_gpu.py compare --runs 1 2 --workdir /tmp/fp27 --out fp_multi_gpu.json
CPU smoke test (built-in scene, 2 Ray CPU workers):
    python benchmarks/fingerprint_multi_gpu.py prepare --scene builtin --size 64 --recipients 4 --device cpu --workdir /tmp/fp27
    python benchmarks/fingerprint_multi_gpu.py run --gpus 0 --workers 1 --batch 2 --task-size 2 --epochs 1 \\
        --device cpu --workdir /tmp/fp27
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: ``run --cluster``: a process holding a local Ray cluster with argv[1] GPUs until its stdin closes.
HOLD_CLUSTER = ("import ray, sys; ray.init(num_gpus=int(sys.argv[1]), include_dashboard=False, log_to_driver=False); "
                "print('up', flush=True); sys.stdin.read(); ray.shutdown()")
#: The early-stopping rule of the runs (a preset of gsw.fingerprint.stopping.PRESETS; the seventh round used it).
EARLY_STOP = "quality"


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, indent=1) + "\n")
    tmp.replace(path)


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def _quartiles(values: list[float]) -> list[float] | None:
    v = sorted(values)
    return [round(v[round(q * (len(v) - 1))], 2) for q in (0.0, 0.25, 0.5, 0.75, 1.0)] if v else None


def _machine() -> dict:
    import torch

    import gsw

    gpus = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []
    try:
        import ray

        ray_version = ray.__version__
    except ImportError:
        ray_version = None
    return dict(gpus=gpus, cpus=os.cpu_count(), torch=torch.__version__, python=platform.python_version(),
                gsw=gsw.__version__, ray=ray_version, date=time.strftime("%Y-%m-%d %H:%M:%S %Z"))


def prepare(args) -> None:
    from gsw.camera_io import save_inria_cameras
    from gsw.data import save_inria_model
    from gsw.device import resolve_device

    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    dev = resolve_device(args.device)
    if args.scene == "lego":
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from fingerprint_throughput import _train_lego
        from power_lego import png_dataset  # a WebP copy of the photos (power_lego.py --pack-webp) back to PNG

        data = png_dataset(Path(args.data), work / "lego_png")
        photos = str(data)
        ns = argparse.Namespace(data=str(data), size=args.size, train_seconds=args.train_seconds,
                                train_seed=args.train_seed)
        g, train_set, test_set, info = _train_lego(ns, dev)
        cams, held = train_set.cameras, test_set.cameras
    else:
        from gsw.scenes import default_cameras, default_scene

        sc = default_scene(width=args.size, height=args.size, n_cameras=args.views, device=dev)
        g, cams, info, photos = sc.gaussians, sc.cameras, None, None
        held = default_cameras(args.held_out, args.size, args.size, azimuth_offset_deg=180.0 / args.views)
    save_inria_model(work / "model", g.to("cpu"), cams, iteration=0)
    save_inria_cameras(held, work / "held_out.json")
    rng = random.Random(args.seed)
    rows = ["recipient,message"] + [f"r{i:03d},{rng.getrandbits(args.bits):0{args.bits // 4}x}"
                                    for i in range(args.recipients)]
    (work / "recipients.csv").write_text("\n".join(rows) + "\n")
    _write_json(work / "prepare.json", dict(scene=args.scene, photos=photos, training=info, gaussians=len(g), views=len(cams),
                                           held_out_views=len(held), size=f"{cams[0].width}x{cams[0].height}",
                                           recipients=args.recipients, machine=_machine()))
    print(f"prepared {work}: {len(g)} Gaussians, {len(cams)} embedding / {len(held)} held-out views", flush=True)


def run_tag(args) -> str:
    """The run's name: its GPU count, ``local`` for ``--local``, ``xN`` for ``--limit N``, or ``--tag``."""
    if args.tag:
        return args.tag
    return (f"{args.gpus[0]}" + ("local" if args.local else "") + ("cluster" if args.cluster else "")
            + ("nophotos" if args.no_photos else "") + (f"x{args.limit}" if args.limit else ""))


def run(args) -> None:
    work = Path(args.workdir)
    g, tag = args.gpus[0], run_tag(args)
    out, reg = work / f"out_{tag}", work / f"marks_{tag}.sqlite"
    if out.exists() or reg.exists():
        raise SystemExit(f"{out} or {reg} exists: a run is timed from scratch; remove them first")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if g > 0:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(str(args.first_gpu + i) for i in range(g))
    recipients = work / "recipients.csv"
    if args.limit:
        recipients = work / f"recipients_{tag}.csv"
        recipients.write_text("".join((work / "recipients.csv").read_text().splitlines(keepends=True)[:args.limit + 1]))
    cmd = [sys.executable, "-m", "gsw", "fingerprint", str(work / "model"), "--recipients", str(recipients),
           "--output", str(out), "--registry", str(reg), "--batch", str(args.batch), "--task-size", str(args.task_size),
           "--epochs", str(args.epochs), "--device", args.device, "--no-progress", "--json"]
    cmd += ["--white"]  # lego's and the built-in scene's background
    if args.local:
        cmd += ["--local"]
    prep = json.loads((work / "prepare.json").read_text())
    if prep.get("photos") and not args.no_photos:  # the training photos, for FGD (as a user with them runs it)
        cmd += ["--images", prep["photos"]]
    cmd += ["--early-stop", args.early_stop]  # "none": every recipient runs --epochs passes
    head = None
    if args.cluster:  # a Ray cluster already running on this host (started untimed below), joined by address
        cmd += ["--address", "auto"]
        # a process that starts a local cluster and holds it until its stdin closes (the stripped Ray bundle of
        # the GPU machines has no `ray start`)
        head = subprocess.Popen([sys.executable, "-c", HOLD_CLUSTER, str(g)], env=env, stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)
        if head.stdout.readline().strip() != "up":
            head.kill()
            raise SystemExit("the Ray cluster of --cluster did not start")
    if args.workers:  # CPU: Ray's CPUs (a test of the path, not a measurement)
        cmd = [sys.executable, "-c", "import ray,runpy,sys; ray.init(num_cpus=%d, include_dashboard=False, "
               "log_to_driver=False); sys.argv=sys.argv[1:]; runpy.run_module('gsw', run_name='__main__')"
               % args.workers, "gsw"] + cmd[3:]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    finally:
        wall = time.perf_counter() - t0
        if head is not None:
            head.stdin.close()
            head.wait(timeout=120)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-4000:])
        raise SystemExit(f"gsw fingerprint exited {proc.returncode}")
    report = json.loads(proc.stdout[proc.stdout.index("{"):])
    n = sum(r["status"] == "embedded" for r in report["recipients"])
    first = json.loads((Path(report["recipients"][0]["folder"]) / "watermark.json").read_text())
    scene = {k: first.get(k) for k in ("gaussians_in", "gaussians_out", "pruned", "split", "setup_timings")}
    res = dict(tag=tag, gpus=g, local=args.local, command=" ".join(cmd), wall_s=wall, recipients=n, runner=report["runner"],
               timings=report["timings"], recipients_per_hour=3600 * n / wall,
               recipients_per_hour_finetune=3600 * n / report["timings"]["finetune"],
               recipients_per_gpu_hour=3600 * n / wall / max(g, 1), scene=scene, report=report, machine=_machine(),
               stderr_tail=proc.stderr[-2000:])
    _write_json(work / f"run_{tag}.json", res)
    print(json.dumps({k: v for k, v in res.items() if k not in ("report", "stderr_tail", "command")}), flush=True)


def compare(args) -> None:
    import torch

    from gsw.camera_io import load_inria_cameras
    from gsw.data import load_inria_model
    from gsw.decoder.zoo import load_decoder
    from gsw.device import resolve_device
    from gsw.registry import open_registry
    from gsw.render.rasterize import rasterize

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from fingerprint_throughput import held_out_scores

    work = Path(args.workdir)
    dev = resolve_device(args.device)
    prep = json.loads((work / "prepare.json").read_text())
    bg = (1.0, 1.0, 1.0)
    held = load_inria_cameras(work / "held_out.json")
    orig = load_inria_model(work / "model").gaussians.to(dev)
    dec = load_decoder(args.bits).to(dev)
    with torch.no_grad():
        originals = [rasterize(orig, c, background=bg).image.clamp(0, 1) for c in held]
    runs = {t: json.loads((work / f"run_{t}.json").read_text()) for t in args.runs}
    base = args.runs[0]
    in_base = {r["name"] for r in runs[base]["report"]["recipients"]}
    per_run = {}
    for g in args.runs:
        with open_registry(work / f"marks_{g}.sqlite", create=False) as reg:
            messages = {m.label: m.message.float() for m in reg.list()}
        rows = []
        for r in sorted(runs[g]["report"]["recipients"], key=lambda r: r["name"]):
            copy = load_inria_model(Path(r["folder"])).gaussians.to(dev)
            row = dict(name=r["name"], steps=r["steps"], stopped_early=r["stopped_early"], train_bits=r.get("bit_accuracy"),
                       train_psnr=r.get("psnr"))
            if g != base and r["name"] in in_base:  # a larger job's extra recipients have no 1-GPU copy
                ref = load_inria_model(work / f"out_{base}" / r["name"]).gaussians.to(dev)
                pa, pb = copy.parameters(), ref.parameters()
                diffs = [float((pa[k] - pb[k]).abs().max()) for k in pa] if len(copy) == len(ref) else [float("inf")]
                row["max_abs_diff_vs_base"] = max(diffs)
                with open_registry(work / f"marks_{base}.sqlite", create=False) as reg:
                    row["same_message"] = bool(torch.equal(reg.get(r["name"]).message.float(), messages[r["name"]]))
            accs, ps = held_out_scores(copy, originals, held, bg, messages[r["name"]], dec)
            row.update(held_out_bits=sum(accs) / len(accs), held_out_min_bits=min(accs), held_out_psnr=sum(ps) / len(ps))
            rows.append(row)
        per_run[g] = rows
    summary = []
    rate1 = runs[base]["recipients_per_hour"] / max(runs[base]["gpus"], 1)
    for g in args.runs:
        rows = per_run[g]
        s = dict(run=g, gpus=runs[g]["gpus"], recipients=len(rows), wall_s=runs[g]["wall_s"], finetune_s=runs[g]["timings"]["finetune"],
                 recipients_per_hour=runs[g]["recipients_per_hour"],
                 recipients_per_gpu_hour=runs[g]["recipients_per_gpu_hour"],
                 scaling_efficiency=runs[g]["recipients_per_hour"] / (max(runs[g]["gpus"], 1) * rate1),
                 mean_train_psnr=_mean(r["train_psnr"] for r in rows),
                 mean_bits=sum(r["held_out_bits"] for r in rows) / len(rows),
                 worst_recipient_bits=min(r["held_out_bits"] for r in rows),
                 mean_psnr=sum(r["held_out_psnr"] for r in rows) / len(rows),
                 worst_recipient_psnr=min(r["held_out_psnr"] for r in rows),
                 meeting_99_and_37=sum(r["held_out_bits"] >= 0.99 and r["held_out_psnr"] >= 37 for r in rows),
                 timings=runs[g]["timings"])
        recs = runs[g]["report"]["recipients"]  # where the fine-tune time went: workers' set-up, copies' arrival
        s.update(worker_setup_s=sorted({round(r["worker_setup_s"], 2) for r in recs if r.get("worker_setup_s")}),
                 worker_warm_s=sorted({round(r["worker_warm_s"], 2) for r in recs if r.get("worker_warm_s")}),
                 copies_arrived_s=_quartiles([r["finished_s"] for r in recs if r.get("finished_s") is not None]))
        if g != base:
            same = {r["name"]: r for r in per_run[base]}
            common = [r for r in rows if r["name"] in same]
            s.update(compared=len(common), bitwise_identical=sum(r["max_abs_diff_vs_base"] == 0 for r in common),
                     max_abs_diff=max(r["max_abs_diff_vs_base"] for r in common),
                     same_message=sum(r["same_message"] for r in common),
                     same_held_out_bits=sum(r["held_out_bits"] == same[r["name"]]["held_out_bits"] for r in common),
                     same_steps=sum(r["steps"] == same[r["name"]]["steps"] for r in common))
        summary.append(s)
    res = dict(prepare=prep, runs={g: {k: v for k, v in runs[g].items() if k != "report"} for g in args.runs},
               summary=summary, rows=per_run, machine=_machine())
    _write_json(Path(args.out) if args.out else work / "compare.json", res)
    print("| run | GPUs | recipients | wall s | recipients/h | per GPU-h | scaling | held-out bits mean / worst | PSNR mean / "
          "worst | train PSNR | meets | identical to 1 GPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in summary:
        ident = ("-" if s["run"] == base
                 else f"{s['bitwise_identical']} of {s['compared']} (max diff {s['max_abs_diff']:.2g})")
        print(f"| {s['run']} | {s['gpus']} | {s['recipients']} | {s['wall_s']:.1f} | {s['recipients_per_hour']:.0f} | "
              f"{s['recipients_per_gpu_hour']:.0f} | {s['scaling_efficiency']:.3f} | {100 * s['mean_bits']:.2f} / "
              f"{100 * s['worst_recipient_bits']:.2f} % | {s['mean_psnr']:.2f} / {s['worst_recipient_psnr']:.2f} dB | "
              f"{'-' if s['mean_train_psnr'] is None else format(s['mean_train_psnr'], '.2f')} | "
              f"{s['meeting_99_and_37']} | {ident} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("step", choices=["prepare", "run", "compare"])
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--scene", choices=["lego", "builtin"], default="lego")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego"))
    ap.add_argument("--train-seconds", type=float, default=60.0)
    ap.add_argument("--train-seed", type=int, default=0, help="prepare: lego's training seed")
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--views", type=int, default=24, help="builtin: embedding views")
    ap.add_argument("--held-out", type=int, default=8, help="builtin: held-out views")
    ap.add_argument("--recipients", type=int, default=64)
    ap.add_argument("--bits", type=int, default=32)
    ap.add_argument("--seed", type=int, default=27, help="messages of the recipients file")
    ap.add_argument("--gpus", type=int, nargs=1, default=[1], help="run: GPUs (0: CPU)")
    ap.add_argument("--first-gpu", type=int, default=0, help="run: the first GPU's index (the run takes --gpus from it)")
    ap.add_argument("--local", action="store_true", help="run: gsw fingerprint --local (one process, no Ray)")
    ap.add_argument("--cluster", action="store_true",
                    help="run: start a Ray cluster on this host first (untimed; with the run's GPUs) and join it "
                         "(gsw fingerprint --address auto), as a host that keeps Ray running does")
    ap.add_argument("--no-photos", action="store_true",
                    help="run: without --images (FGD without the photos; lego's photos are used by default)")
    ap.add_argument("--limit", type=int, default=0, help="run: only the first N recipients")
    ap.add_argument("--tag", default=None, help="run: the run's name (default: GPUs, 'local', 'xN')")
    ap.add_argument("--runs", nargs="+", default=["1"], help="compare: the runs' names, the base first")
    ap.add_argument("--workers", type=int, default=0, help="run on the CPU: Ray CPUs")
    ap.add_argument("--batch", type=int, default=16, help="pool slots per task")
    ap.add_argument("--task-size", type=int, default=16, help="recipients handed to a Ray worker at a time")
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--early-stop", default=EARLY_STOP, help="gsw fingerprint --early-stop, or 'none'")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    {"prepare": prepare, "run": run, "compare": compare}[args.step](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
