"""Same-process A/B of CPU builds: the whole forward+backward of one scene, the builds called alternately.

Separate processes running the same code differ by up to ~15 % on a shared 2-core VM (BENCHMARKS.md 1), more
than most kernel changes are worth. Here every build is loaded into one process as its own module and the
repetitions alternate between them, so they share the machine's state; the result per build is the minimum
and median wall / process-CPU time, and per build after the first the median over the repetitions of its time
divided by the first build's time in the same repetition.

Each build is an extension module file (``_C*.so``) built aside, e.g. for a source tree SRC::

    pip install --no-build-isolation --no-deps --target /tmp/gsw_NAME SRC \\
        -Ccmake.define.CMAKE_MODULE_LINKER_FLAGS=-Wl,-Bsymbolic -Cbuild-dir=/tmp/gsw_NAME_build

The module's own functions are hidden symbols (pybind11's default visibility), so each build calls its own
code; ``-Bsymbolic`` binds the few it exports (inline c10 functions) to itself too.

Usage:
    python benchmarks/bench_cpu_ab.py base=/tmp/gsw_base/gsw/_C.cpython-311-x86_64-linux-gnu.so \\
        new=/tmp/gsw_new/gsw/_C...so [--family frustum|heavy] [--threads 2] [--repeats 20] [--json OUT]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import time
from types import ModuleType

from bench_cpu import add_scene_args, family_scene, forward_backward_fn


def load_build(name: str, path: str) -> ModuleType:
    """Loads the extension file ``path`` as the module ``gsw_<name>._C`` (not ``gsw._C``: one name loads once)."""
    spec = importlib.util.spec_from_file_location(f"gsw_{name}._C", path)
    if spec is None:
        raise SystemExit(f"{path}: not an extension module")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("builds", nargs="+", help="NAME=PATH of each build's extension module; the first is the base")
    add_scene_args(parser, family="frustum", threads=2, repeats=20)
    parser.add_argument("--json", help="append the result as one JSON line to this file")
    args = parser.parse_args()
    builds = {}
    for item in args.builds:
        name, sep, path = item.partition("=")
        if not sep or not name or not os.path.isfile(path):
            raise SystemExit(f"expected NAME=PATH of an existing extension module file, got {item!r}")
        builds[name] = path
    if len(builds) < 2:
        raise SystemExit("give at least two builds")

    import torch

    import gsw._ext

    torch.set_num_threads(args.threads)
    modules = {name: load_build(name, path) for name, path in builds.items()}
    installed = gsw._ext._C
    # gsw's modules bind `_C` by name at import: each call swaps every such binding to the build under test.
    holders = [m for m in list(sys.modules.values()) if m is not None and getattr(m, "_C", None) is installed]

    def use(name: str) -> None:
        for holder in holders:
            holder._C = modules[name]

    g, cam = family_scene(args.family, args.n, args.size, args.size, args.sh_degree)
    whole = forward_backward_fn(g, cam)

    wall: dict[str, list[float]] = {name: [] for name in builds}
    cpu: dict[str, list[float]] = {name: [] for name in builds}
    try:
        for name in builds:  # warm-up
            use(name)
            whole()
        for _ in range(args.repeats):
            for name in builds:
                use(name)
                start, start_cpu = time.perf_counter(), time.process_time()
                whole()
                wall[name].append(1e3 * (time.perf_counter() - start))
                cpu[name].append(1e3 * (time.process_time() - start_cpu))
    finally:
        for holder in holders:
            holder._C = installed
    base = next(iter(builds))
    result = dict(family=args.family, n=args.n, size=args.size, sh_degree=args.sh_degree, threads=args.threads,
                  repeats=args.repeats, load=os.getloadavg()[0], time=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                  torch=torch.__version__, builds={})
    print(f"{args.family} {args.n:,} {args.size}x{args.size} SH {args.sh_degree}, {args.threads} threads, "
          f"{args.repeats} alternating repetitions, load {result['load']:.2f}, {result['time']}")
    for name in builds:
        row = dict(path=builds[name], wall_min_ms=min(wall[name]), wall_median_ms=statistics.median(wall[name]),
                   cpu_min_ms=min(cpu[name]), cpu_median_ms=statistics.median(cpu[name]))
        line = (f"{name:>10}: wall min {row['wall_min_ms']:7.1f} median {row['wall_median_ms']:7.1f} ms | "
                f"cpu min {row['cpu_min_ms']:7.1f} median {row['cpu_median_ms']:7.1f} ms")
        if name != base:
            ratios = sorted(a / b for a, b in zip(wall[name], wall[base]))
            row["wall_ratio_median"] = statistics.median(ratios)
            row["wall_ratio_q25_q75"] = [ratios[len(ratios) // 4], ratios[(3 * len(ratios)) // 4]]
            line += (f" | / {base}: {row['wall_ratio_median']:.3f} "
                     f"(q25 {row['wall_ratio_q25_q75'][0]:.3f}, q75 {row['wall_ratio_q25_q75'][1]:.3f})")
        result["builds"][name] = row
        print(line, flush=True)
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
