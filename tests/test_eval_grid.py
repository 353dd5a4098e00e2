"""The evaluation grid (gsw.grid) and `gsw eval-grid`: methods, spec checks, TPR@FPR, aggregation, resume."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import sys
from pathlib import Path

import pytest
import torch

import gsw.eval.grid.run as grid_run
import gsw.eval.grid.spec as grid_spec
import gsw.eval.grid as grid
from gsw.cli.main import main
from gsw.data import save_inria_model, write_image
from gsw.mark import EmbedConfig
from gsw.mark.loss import LossWeights
from gsw.eval.grid import (METHODS, GridMismatchError, GridSpec, aggregate, apply_overrides, decoder_fingerprint,
                      default_grid_scene, detection_rate, detection_rates, load_grid_scene, lpips_loss_overrides,
                      mean_std, method_config, run_grid)
from gsw.stats import binomial_p_value
from gsw.scenes import default_scene
from gsw.stats import false_positive_threshold

from gsw.mark.embed import paper_config  # noqa: E402

NO_LPIPS = lpips_loss_overrides(None)


def _flat(obj: object, prefix: str = "") -> dict[str, object]:
    if not isinstance(obj, dict):
        return {prefix: obj}
    return {k: v for key, value in obj.items() for k, v in _flat(value, f"{prefix}{key}.").items()}


def _differences(cfg: EmbedConfig) -> dict[str, object]:
    base, other = _flat(dataclasses.asdict(paper_config())), _flat(dataclasses.asdict(cfg))
    return {k.rstrip("."): v for k, v in other.items() if base[k] != v}


# ------------------------------------------------------------------------------------------ methods and spec


def test_methods_are_the_intended_embedder_configurations() -> None:
    expected = {
        "default": {"fgd": False, "freeze": ("f_rest",), "mask": "none", "novel_views": 1.0, "weights.l1": 0.0,
                    "weights.mse": 35.0},
        "3d-gsw": {},
        "paper": {},
        "freeze-rest": {"freeze": ("f_rest",), "mask": "none"},
        "freeze-rest+views": {"freeze": ("f_rest",), "mask": "none", "novel_views": 1.0},
        "wild": {"novel_views": 0.5, "render_scales": (0.5, 2.0), "attacks": 0.5, "attack_ranges": "matched",
                 "model_attacks": 0.5, "model_attack_kinds": ("noise", "sh0", "splat", "spz", "8bit")},
        "no-fgd": {"fgd": False},
        "no-mask": {"mask": "none"},
        "no-subband": {"weights.subband": 0.0},
        "stega-3dgs": {"fgd": False, "mask": "stega", "weights.subband": 0.0},
        "waterf-3dgs": {"fgd": False, "mask": "none", "weights.subband": 0.0},
        "3d-gsw+attacks": {"attacks": 0.5},
        "3d-gsw+all-attacks": {"attacks": 0.5, "model_attacks": 0.5},
    }
    assert {m: _differences(method_config(m)) for m in METHODS} == expected
    with pytest.raises(ValueError, match="unknown method"):
        method_config("3dgsw")


def test_cell_config_layers_grid_overrides_method_and_axes() -> None:
    spec = GridSpec(methods=("3d-gsw", "no-subband"), bits=(32,), seeds=(0,), epochs=3,
                    embed={"weights": {"subband": 0.5, "lpips": 0.0}, "lr_f_dc": 1e-3, "lpips_net": None})
    full, ablated = spec.config("3d-gsw", 7, (1, 1, 1)), spec.config("no-subband", 7, (1, 1, 1))
    assert full.weights.subband == 0.5 and ablated.weights.subband == 0.0  # the method wins
    assert full.weights.lpips == ablated.weights.lpips == 0.0
    assert ablated.weights.message == LossWeights().message  # untouched weights keep their defaults
    for cfg in (full, ablated):
        assert (cfg.epochs, cfg.seed, cfg.background, cfg.lr_f_dc, cfg.lpips_net) == (3, 7, (1.0, 1.0, 1.0), 1e-3, None)
    assert apply_overrides(EmbedConfig(), {"background": [1, 0, 0]}).background == (1, 0, 0)
    no_lpips, alex = (apply_overrides(EmbedConfig(), lpips_loss_overrides(n)) for n in (None, "alex"))
    assert (no_lpips.lpips_net, no_lpips.weights.lpips, alex.lpips_net, alex.weights.lpips) == (None, 0.0, "alex", 0.2)
    with pytest.raises(ValueError, match="unknown EmbedConfig fields"):
        apply_overrides(EmbedConfig(), {"epoch": 2})
    with pytest.raises(ValueError, match="unknown LossWeights fields"):
        apply_overrides(EmbedConfig(), {"weights": {"wavelet": 0.0}})


@pytest.mark.parametrize("kwargs, message", [
    (dict(methods=("3d-gsw", "gsw")), "unknown methods"),
    (dict(methods=()), "no methods"),
    (dict(bits=()), "no bit lengths"),
    (dict(seeds=()), "no seeds"),
    (dict(seeds=(0, 0)), "duplicate seeds"),
    (dict(image_attacks=("jpg",)), "unknown image attacks"),
    (dict(model_attacks=("prune",)), "unknown model attacks"),
    (dict(sweeps=("combined",)), "unknown sweeps"),
    (dict(bits=(32.0,)), "integers"),
    (dict(epochs=0), "positive"),
    (dict(fpr=0.0), "fpr"),
    (dict(lpips_net="squeeze"), "lpips_net"),
    (dict(embed={"epochs": 2}), "the grid sets them"),
    (dict(embed={"lpips_net": None}), "weights.lpips"),
    (dict(embed={"mask_kind": "exp"}), "unknown EmbedConfig fields"),
])
def test_spec_rejects_bad_selections(kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        GridSpec(**kwargs)


def test_spec_defaults_cells_and_settings() -> None:
    spec = GridSpec()
    assert spec.methods == tuple(METHODS) and spec.bits == (32, 48, 64) and spec.report_bits == 32
    assert len(spec.cells()) == len(METHODS) * 3 * 3
    small = GridSpec(methods=("no-fgd",), bits=(64, 48), seeds=(3,))
    assert [c.name for c in small.cells()] == ["no-fgd_64b_seed3", "no-fgd_48b_seed3"] and small.report_bits == 64
    # the selection is not a setting: a grid can grow in the same folder
    assert small.settings() == GridSpec().settings()
    assert "methods" not in small.settings() and small.settings()["model_attacks"] == [
        "parameter_noise", "remove", "clone", "reduce_sh", "export_splat", "export_spz", "quantize",
        "export_compressed_ply"]


# ------------------------------------------------------------------------------------------ detection, aggregation


def test_tpr_at_fpr_on_hand_made_p_values() -> None:
    assert detection_rate([1e-7, 1e-6, 2e-6, 0.5], 1e-6) == 0.5
    assert detection_rate([1e-7, 1e-6, 2e-6, 0.5], 1e-2) == 0.75
    assert detection_rate([], 1e-6) == 0.0
    # a view is detected exactly when its matching bits reach the false-positive threshold
    for k in (32, 48, 64):
        m0 = false_positive_threshold(k, 1e-6)
        ps = [binomial_p_value(m, k) for m in range(k + 1)]
        assert detection_rate(ps, 1e-6) == (k + 1 - m0) / (k + 1)
    report = {
        "clean": {"p_values": [1e-9, 1e-3]}, "unmarked": {"p_values": [0.2, 1e-7]},
        "image_attacks": {"jpeg": {"p_values": [1e-9, 1e-8, 0.3]}},
        "unmarked_image_attacks": {"jpeg": {"p_values": [0.5, 0.5, 0.5]}},
        "model_attacks": {"remove": {"p_values": [0.9, 0.9]}},
        "unmarked_model_attacks": {"remove": {"p_values": [1e-12, 1e-12]}},
    }
    assert detection_rates(report, 1e-6) == {"clean": {"tpr": 0.5, "fpr": 0.5},
                                             "image": {"jpeg": {"tpr": 2 / 3, "fpr": 0.0}},
                                             "model": {"remove": {"tpr": 0.0, "fpr": 1.0}}}


def test_mean_std_and_aggregation_on_known_numbers() -> None:
    s = mean_std([1.0, 2.0, 3.0, 4.0])
    assert s.mean == 2.5 and s.std == pytest.approx(math.sqrt(5 / 3)) and s.n == 4
    assert mean_std([7.0]) == grid.Stat(7.0, 0.0, 1)
    with pytest.raises(ValueError):
        mean_std([])
    groups = aggregate([("a", 32, {"x": 1.0, "y": 10.0}), ("a", 32, {"x": 3.0}), ("b", 32, {"x": 5.0}),
                        ("a", 48, {"x": 0.0})])
    assert list(groups) == [("a", 32), ("b", 32), ("a", 48)]
    assert groups["a", 32]["x"] == grid.Stat(2.0, pytest.approx(math.sqrt(2.0)), 2)
    assert groups["a", 32]["y"] == grid.Stat(10.0, 0.0, 1) and groups["b", 32]["x"].mean == 5.0


def test_summary_tables_from_known_numbers() -> None:
    spec = GridSpec(methods=("3d-gsw", "no-fgd"), bits=(32, 48), seeds=(0, 1), image_attacks=("jpeg",),
                    model_attacks=(), sweeps=())
    metrics = {"bit_acc": 0.9, "psnr": 30.0, "ssim": 0.95, "tpr": 0.5, "fpr": 0.0, "image:jpeg:bit_acc": 0.8,
               "image:jpeg:tpr": 0.25, "image:jpeg:fpr": 0.0}
    cells = [(m, b, {**metrics, "bit_acc": 0.9 + 0.02 * s}) for m in spec.methods for b in spec.bits for s in (0, 1)]
    summary = grid.GridSummary(spec, {"kind": "test"}, aggregate(cells))
    md = summary.to_markdown()
    assert "| method | 32 bits: bit acc (%) | PSNR | SSIM | LPIPS | 48 bits: bit acc (%) |" in md
    assert "| 3d-gsw | 91.00 ± 1.41 | 30.00 ± 0.00 | 0.9500 ± 0.0000 | - | 91.00 ± 1.41 |" in md
    assert "| no-fgd | 91.00 ± 1.41 | 80.00 ± 0.00 |" in md  # image attacks: clean, jpeg
    assert "| 3d-gsw | 50 / 0 | 25 / 0 |" in md  # detection: TPR / FPR
    assert "## Ablation" in md and "Robustness curves" not in md
    assert json.loads(json.dumps(summary.to_dict()))["groups"][0]["metrics"]["bit_acc"]["n"] == 2


# ------------------------------------------------------------------------------------------ scenes


def test_scenes(tmp_path) -> None:
    scene = default_grid_scene(size=32, views=4, eval_views=2, detail=0.2)
    assert len(scene.cameras) == 4 and len(scene.eval_cameras) == 2 and scene.background == (1.0, 1.0, 1.0)
    train_centres = torch.stack([c.center for c in scene.cameras])
    for cam in scene.eval_cameras:  # held-out views lie between the training views
        assert float((train_centres - cam.center).norm(dim=1).min()) > 0.5
    with pytest.raises(ValueError, match="eval_views"):
        default_grid_scene(size=32, views=4, eval_views=5)

    g = default_scene(width=16, height=16, n_cameras=10, detail=0.2)
    save_inria_model(tmp_path / "model", g.gaussians, g.cameras, iteration=3)
    s = load_grid_scene(tmp_path / "model", train_views=3)
    assert len(s.cameras) == 3 and len(s.eval_cameras) == 2 and s.images is None  # views 0, 8 held out
    assert s.key["kind"] == "inria" and s.key["data"] is None and s.background == (0.0, 0.0, 0.0)
    # with a dataset: its train split to embed (images for FGD), its hold-out split to evaluate
    c2w = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    (tmp_path / "data" / "train").mkdir(parents=True)
    for i in range(9):
        write_image(tmp_path / "data" / "train" / f"r_{i}.png", torch.full((3, 8, 8), i / 10))
    (tmp_path / "data" / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": f"./train/r_{i}", "transform_matrix": c2w}
                                           for i in range(9)]}))
    s = load_grid_scene(tmp_path / "model", tmp_path / "data", white=True, eval_views=1)
    assert len(s.cameras) == 7 and s.images.shape == (7, 3, 8, 8) and len(s.eval_cameras) == 1
    assert s.key["data"] == str((tmp_path / "data").resolve()) and s.background == (1.0, 1.0, 1.0)


# ------------------------------------------------------------------------------------------ the runner

TINY = dict(methods=("3d-gsw", "waterf-3dgs"), bits=(32,), seeds=(0, 1), epochs=1, image_attacks=("noise", "crop"),
            model_attacks=("remove",), sweeps=("jpeg",), embed=NO_LPIPS, lpips_net=None)


@pytest.fixture(scope="module")
def tiny_scene():
    return default_grid_scene(size=48, views=3, eval_views=2, detail=0.3)


@pytest.fixture(scope="module")
def tiny_grid(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("grid") / "g"
    return out, run_grid(GridSpec(**TINY), tiny_scene, out, progress=False)


def test_tiny_grid_writes_cells_and_tables(tiny_grid, tiny_scene) -> None:
    out, summary = tiny_grid
    names = ["3d-gsw_32b_seed0", "3d-gsw_32b_seed1", "waterf-3dgs_32b_seed0", "waterf-3dgs_32b_seed1"]
    assert sorted(p.name for p in (out / "cells").iterdir()) == sorted(n + s for n in names for s in (".json", ".png"))
    assert (summary.computed, summary.reused) == (4, 0)
    assert json.loads((out / "grid.json").read_text())["settings"] == GridSpec(**TINY).settings()
    cells = {n: json.loads((out / "cells" / f"{n}.json").read_text()) for n in names}
    a, b = cells["3d-gsw_32b_seed0"], cells["waterf-3dgs_32b_seed0"]
    assert a["message"] == b["message"] != cells["3d-gsw_32b_seed1"]["message"]  # the seed picks the message
    assert a["config"]["fgd"] and not b["config"]["fgd"] and b["config"]["weights"]["subband"] == 0.0
    assert a["config"]["background"] == [1.0, 1.0, 1.0] and a["config"]["epochs"] == 1
    report = a["report"]
    assert set(report["image_attacks"]) == {"noise", "crop"} == set(report["unmarked_image_attacks"])
    assert set(report["model_attacks"]) == {"remove"} and len(report["clean"]["p_values"]) == 2
    assert a["detection"] == detection_rates(report, 1e-6)
    assert a["sweeps"]["jpeg"]["values"] == [90, 70, 50, 30, 20, 10] and len(a["sweeps"]["jpeg"]["watermarked"]) == 6
    assert b["storage"]["original"] == b["storage"]["watermarked"]  # no FGD: same model size
    assert a["storage"]["watermarked"]["gaussians"] == len(tiny_scene.gaussians) - a["embedding"]["pruned"] \
        + a["embedding"]["split"]
    assert a["storage"]["original"]["ply_bytes"] > 62 * 4 * len(tiny_scene.gaussians)
    assert min(a["fps"].values()) > 0 and a["timings"]["evaluation"] > 0
    stat = summary.stat("3d-gsw", 32, "bit_acc")
    accs = [cells[n]["report"]["clean"]["bit_accuracy"] for n in names[:2]]
    assert stat.n == 2 and stat.mean == pytest.approx(sum(accs) / 2)
    md = (out / "summary.md").read_text()
    for heading in ("Capacity", "Image attacks", "Model attacks", "Detection at FPR 1e-06", "Time", "### jpeg"):
        assert heading in md
    assert "Ablation" not in md  # a single ablation row
    assert json.loads((out / "summary.json").read_text())["groups"][1]["method"] == "waterf-3dgs"


@pytest.fixture
def embed_calls(monkeypatch) -> list[int]:
    """The seeds of the cells that :func:`gsw.eval.grid.run_grid` embeds (i.e. recomputes), in order."""
    calls: list[int] = []
    real_embed = grid_run.embed

    def counting_embed(*args, **kwargs):
        calls.append(kwargs["config"].seed)
        return real_embed(*args, **kwargs)

    monkeypatch.setattr(grid_run, "embed", counting_embed)
    return calls


def test_rerun_skips_finished_cells_and_recomputes_corrupt_ones(tiny_grid, tiny_scene, tmp_path,
                                                                embed_calls) -> None:
    calls = embed_calls
    out = tmp_path / "g"
    shutil.copytree(tiny_grid[0], out)
    spec = GridSpec(**TINY)
    again = run_grid(spec, tiny_scene, out, progress=False)
    assert calls == [] and (again.computed, again.reused) == (0, 4)
    assert again.groups == tiny_grid[1].groups
    cell = out / "cells" / "waterf-3dgs_32b_seed1.json"
    cell.write_text(cell.read_text()[:100])  # a partial file
    with pytest.warns(RuntimeWarning, match="corrupt"):
        again = run_grid(spec, tiny_scene, out, progress=False)
    assert calls == [1] and (again.computed, again.reused) == (1, 3) and json.loads(cell.read_text())["seed"] == 1
    # more seeds are more cells of the same grid
    more = run_grid(dataclasses.replace(spec, methods=("3d-gsw",), seeds=(0, 1, 2)), tiny_scene, out, progress=False)
    assert calls == [1, 2] and (more.computed, more.reused) == (1, 2)
    # other settings are refused, unless forced (then the cells are recomputed)
    other = dataclasses.replace(spec, methods=("3d-gsw",), seeds=(0,), fps_repeats=2)
    with pytest.raises(GridMismatchError, match="fps_repeats"):
        run_grid(other, tiny_scene, out, progress=False)
    with pytest.raises(GridMismatchError, match="eval_views"):
        run_grid(spec, default_grid_scene(size=48, views=3, eval_views=1, detail=0.3), out, progress=False)
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "notes.txt").write_text("mine")
    with pytest.raises(GridMismatchError, match="not empty"):
        run_grid(spec, tiny_scene, tmp_path / "elsewhere", progress=False)
    with pytest.warns(RuntimeWarning, match="other settings"):
        forced = run_grid(other, tiny_scene, out, force=True, progress=False)
    assert calls == [1, 2, 0] and forced.computed == 1
    assert json.loads((out / "grid.json").read_text())["settings"]["fps_repeats"] == 2
    assert not [p for p in out.rglob(".*")]  # no temporary files left


def test_cells_recorded_with_the_legacy_decoder_fingerprint_are_reused(tiny_grid, tiny_scene, tmp_path,
                                                                     embed_calls) -> None:
    """The short fingerprint is the decoder sha256's prefix (gsw.decoder.null); a cell written before it was (its
    own hash) still counts as made with that decoder."""
    from gsw.decoder.null import decoder_fingerprint as decoder_sha256
    from gsw.decoder.zoo import load_decoder
    from gsw.eval.grid.store import legacy_decoder_fingerprint

    d = load_decoder(32)
    assert decoder_fingerprint(d) == decoder_sha256(d)[:16] != legacy_decoder_fingerprint(d)
    out = tmp_path / "g"
    shutil.copytree(tiny_grid[0], out)
    cell = out / "cells" / "waterf-3dgs_32b_seed0.json"
    data = json.loads(cell.read_text())
    assert data["decoder"] == decoder_fingerprint(d)
    data["decoder"] = legacy_decoder_fingerprint(d)
    cell.write_text(json.dumps(data))
    spec = dataclasses.replace(GridSpec(**TINY), methods=("waterf-3dgs",), seeds=(0,))
    again = run_grid(spec, tiny_scene, out, progress=False)
    assert embed_calls == [] and again.computed == 0


def test_rerun_recomputes_cells_of_another_decoder_or_changed_defaults(tiny_grid, tiny_scene, tmp_path,
                                                                      embed_calls, monkeypatch) -> None:
    calls = embed_calls
    out = tmp_path / "g"
    shutil.copytree(tiny_grid[0], out)
    spec = dataclasses.replace(GridSpec(**TINY), methods=("waterf-3dgs",), seeds=(0,))
    from gsw.decoder.zoo import load_decoder

    def other_decoder(bits: int):
        d = load_decoder(bits)
        d.whitening.bias.add_(0.5)  # a retrained / replaced decoder
        return d

    assert decoder_fingerprint(other_decoder(32)) != decoder_fingerprint(load_decoder(32))
    with pytest.warns(RuntimeWarning, match="another decoder"):
        again = run_grid(spec, tiny_scene, out, progress=False, decoder_for=other_decoder)
    assert calls == [0] and again.computed == 1
    # a library default that changes a cell's EmbedConfig (not the grid's settings) invalidates it too
    @dataclasses.dataclass
    class ChangedDefaults(EmbedConfig):
        lr_f_rest: float = 2 * EmbedConfig.lr_f_rest

    monkeypatch.setattr(grid_spec, "EmbedConfig", ChangedDefaults)
    with pytest.warns(RuntimeWarning, match="other settings"):
        again = run_grid(spec, tiny_scene, out, progress=False, decoder_for=other_decoder)
    assert calls == [0, 0] and again.computed == 1
    assert json.loads((out / "cells" / "waterf-3dgs_32b_seed0.json").read_text())["config"]["lr_f_rest"] == 2 * EmbedConfig.lr_f_rest


# ------------------------------------------------------------------------------------------ CLI


def _cli(out: Path, *extra: str) -> int:
    return main(["eval-grid", "default", "--output", str(out), "--size", "32", "--train-views", "2",
                 "--eval-views", "1", "--methods", "no-fgd", "--bits", "32", "--seeds", "0", "--epochs", "1",
                 "--lpips", "none", "--metric-lpips", "none", "--image-attacks", "jpeg", "--model-attacks",
                 "--sweeps", "--no-progress", *extra])


def test_cli_round_trip_and_errors(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "grid"
    assert _cli(out, "--json") == 0
    data = json.loads(capsys.readouterr().out)
    assert (data["computed"], data["methods"], data["bits"]) == (1, ["no-fgd"], [32])
    assert data["settings"]["embed"] == NO_LPIPS and data["scene"]["kind"] == "default"
    assert "image:jpeg:bit_acc" in data["groups"][0]["metrics"]
    assert _cli(out) == 0  # resumed: nothing to compute
    text = capsys.readouterr().out
    assert "| no-fgd | " in text and "0 cells computed, 1 reused" in text
    for extra, message in [
        (("--methods", "no-fgd", "wateRF"), "unknown methods"),
        (("--seeds",), "no seeds selected"),
        (("--image-attacks", "jpeg", "blurr"), "unknown image attacks"),
        (("--epochs", "2"), "other settings"),
        (("--data", str(tmp_path)), "INRIA model folder"),
        (("--device", "tpu"), "tpu"),
    ]:
        assert _cli(out, *extra) == 2, extra
        assert message in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    assert _cli(tmp_path / "never", "--plots") == 2
    assert "pip install matplotlib" in capsys.readouterr().err and not (tmp_path / "never").exists()
    assert _cli(out, "--epochs", "2", "--force", "--no-resume", "--json") == 0
    assert json.loads(capsys.readouterr().out)["computed"] == 1
    with pytest.raises(SystemExit):
        _cli(out, "--bits", "40")
