"""Trainer: a short run on the built-in scene, optimizer surgery, densification units, devices, CLI."""

from __future__ import annotations

import io
import json

import pytest
import torch

import gsw
from gsw.data.loaders import load_inria_model
from gsw.io.ply import load_ply
from gsw.render.rasterize import rasterize
from gsw.scenes import default_scene
from gsw.cli.main import build_parser, main
from gsw.cli.train import config_from_args
from gsw.train.optim import GaussianAdam
from gsw.progress import Progress
from gsw.train import TrainConfig, init_box, random_init, resolve_device, train
from gsw.train.densify import _State

SIZE = 48
HAS_CUDA = torch.cuda.is_available() and bool(gsw.build_info()["cuda"])
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device and a CUDA build of gsw")
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, needs_cuda])]


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny images gain nothing from threads, and OpenMP threads spin-waiting against other jobs on a 2-core machine
    make these runs ~40x slower; use one thread here and restore the setting afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene_views():
    scene = default_scene(width=SIZE, height=SIZE, n_cameras=8, detail=0.5, sh_degree=1)
    with torch.no_grad():
        images = torch.stack([rasterize(scene.gaussians, c, background=scene.background).image.clamp(0, 1)
                              for c in scene.cameras])
    return scene, images


def _small_config(**kw) -> TrainConfig:
    base = dict(iterations=120, sh_degree=1, init_points=2000, densify_from_iter=30, densify_until_iter=100,
                densification_interval=15, opacity_reset_interval=100, sh_increase_interval=50, log_interval=10,
                max_gaussians=20_000)
    base.update(kw)
    return TrainConfig(**base)


def _split_views(scene_views):
    """``(train views, test views)`` of the module scene: 6 training cameras, 2 held out (cameras 4 and 7)."""
    scene, images = scene_views
    train_idx, test_idx = [0, 1, 2, 3, 5, 6], [4, 7]
    cams = scene.cameras
    return ([cams[i] for i in train_idx], images[train_idx]), ([cams[i] for i in test_idx], images[test_idx])


def test_short_training_run(scene_views, tmp_path):
    scene, _ = scene_views
    cams = scene.cameras
    data, test = _split_views(scene_views)
    res = train(data, config=_small_config(), output_dir=tmp_path, progress=False, test_set=test,
                background=scene.background)
    first = sum(h["loss"] for h in res.history[:2]) / 2
    last = sum(h["loss"] for h in res.history[-3:]) / 3
    assert last < 0.6 * first, (first, last)
    assert res.test_metrics is not None and res.test_metrics["num_views"] == 2
    assert 10.0 < res.test_metrics["psnr"] < 60.0
    assert res.history[-1]["sh_degree"] == 1
    # a valid INRIA model folder
    ply = tmp_path / "point_cloud" / "iteration_120" / "point_cloud.ply"
    assert ply.is_file() and (tmp_path / "cameras.json").is_file() and (tmp_path / "cfg_args").is_file()
    model = load_inria_model(tmp_path)
    assert model.iteration == 120 and len(model.gaussians) == res.gaussians.num_gaussians
    assert torch.allclose(model.gaussians.means, res.gaussians.means)
    assert len(model.cameras) == 8  # train + test cameras, like INRIA
    assert torch.equal(model.cameras[0].viewmat, cams[0].viewmat)
    summary = json.loads((tmp_path / "train_result.json").read_text())
    assert summary["num_gaussians"] == res.gaussians.num_gaussians and summary["test"]["psnr"] == pytest.approx(res.test_metrics["psnr"])
    # the loaded model renders what was trained
    img = rasterize(load_ply(ply), cams[4], background=scene.background).image
    ref = rasterize(res.gaussians, cams[4], background=scene.background).image
    assert torch.allclose(img, ref, atol=1e-5)


def test_device_option_cpu(scene_views, tmp_path):
    """``device="cpu"`` is the default and is honoured: model, statistics, result and files on the CPU."""
    scene, _ = scene_views
    assert TrainConfig().device == "cpu" and TrainConfig(device=torch.device("cpu")).device == "cpu"
    data, test = _split_views(scene_views)
    cfg = _small_config(iterations=30, densify_from_iter=10, densify_until_iter=25, densification_interval=10,
                        init_points=1000, device="cpu")
    res = train(data, config=cfg, output_dir=tmp_path, progress=False, test_set=test, background=scene.background)
    assert res.device == torch.device("cpu") and res.iterations == 30
    assert res.gaussians.device.type == "cpu" and res.gaussians.dtype == torch.float32
    assert res.test_metrics is not None and res.test_metrics["num_views"] == 2
    summary = json.loads((tmp_path / "train_result.json").read_text())
    assert (summary["device"], summary["config"]["device"], summary["iterations"]) == ("cpu", "cpu", 30)
    assert "data_device='cpu'" in (tmp_path / "cfg_args").read_text()


def test_time_budget_stops_early(scene_views, tmp_path):
    """``max_train_time_s``: the loop stops, and the iteration reached is logged, saved and evaluated."""
    scene, _ = scene_views
    data, test = _split_views(scene_views)
    res = train(data, config=_small_config(iterations=50, max_train_time_s=1e-9), output_dir=tmp_path,
                progress=False, test_set=test, background=scene.background)
    assert res.iterations == 1 and [h["iteration"] for h in res.history] == [1]
    assert res.test_metrics is not None
    assert load_inria_model(tmp_path).iteration == 1
    assert json.loads((tmp_path / "train_result.json").read_text())["iterations"] == 1
    with pytest.raises(ValueError, match="max_train_time_s"):
        TrainConfig(max_train_time_s=0)


def test_resolve_device(monkeypatch):
    import gsw.device

    assert resolve_device is gsw.device.resolve_device  # one device rule (training, embedding, the CLI)
    assert resolve_device("cpu") == resolve_device(torch.device("cpu")) == torch.device("cpu")
    expected = torch.device("cuda", torch.cuda.current_device()) if HAS_CUDA else torch.device("cpu")
    assert resolve_device("auto") == resolve_device() == expected
    for bad in ("tpu", "mps", "cuda:x", ""):
        with pytest.raises(ValueError, match="device must be"):
            resolve_device(bad)
    with pytest.raises(ValueError, match="device must be"):
        TrainConfig(device="bogus")
    assert TrainConfig(device="cuda:1").device == "cuda:1"  # checked for usability by train(), not here
    monkeypatch.setattr(gsw, "build_info", lambda: {"cuda": False, "cuda_available": False})
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(RuntimeError, match="built without CUDA"):
        resolve_device("cuda:0")
    monkeypatch.setattr(gsw, "build_info", lambda: {"cuda": True, "cuda_available": False})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(RuntimeError, match=r"torch.cuda.is_available\(\) is False"):
        resolve_device("cuda")


@pytest.mark.skipif(HAS_CUDA, reason="CUDA is usable here")
def test_unavailable_cuda_device_is_a_clear_error(scene_views, tmp_path, capsys):
    scene, images = scene_views
    with pytest.raises(RuntimeError, match="device 'cuda' requested"):
        train((scene.cameras[:2], images[:2]), config=_small_config(iterations=1, device="cuda"),
              output_dir=tmp_path / "lib", progress=False)
    assert not (tmp_path / "lib").exists()  # refused before anything was written
    assert main(["train", "default", "-o", str(tmp_path / "cli"), "--device", "cuda", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw train: error: device 'cuda' requested") and err.count("\n") == 1
    assert not (tmp_path / "cli").exists()


@pytest.mark.cuda
@needs_cuda
def test_training_on_cuda_matches_cpu(scene_views, tmp_path):
    """The same run on CUDA and on the CPU: the loss falls on CUDA, and held-out PSNR and model size agree
    (the backends round differently, so the runs are not identical; on the CPU, seeds 0-4 differ by 0.13 dB and
    3% in model size here)."""
    scene, _ = scene_views
    data, test = _split_views(scene_views)
    gpu, cpu = (train(data, config=_small_config(device=dev), output_dir=tmp_path / dev, progress=False,
                      test_set=test, background=scene.background) for dev in ("cuda", "cpu"))
    assert gpu.device.type == "cuda" and gpu.gaussians.device.type == "cuda" and gpu.iterations == 120
    first = sum(h["loss"] for h in gpu.history[:2]) / 2
    last = sum(h["loss"] for h in gpu.history[-3:]) / 3
    assert last < 0.6 * first, (first, last)
    assert abs(gpu.test_metrics["psnr"] - cpu.test_metrics["psnr"]) < 1.0, (gpu.test_metrics, cpu.test_metrics)
    assert abs(gpu.gaussians.num_gaussians - cpu.gaussians.num_gaussians) < 0.15 * cpu.gaussians.num_gaussians
    model = load_inria_model(tmp_path / "cuda")  # written from CPU float32 copies
    assert model.iteration == 120 and torch.allclose(model.gaussians.means, gpu.gaussians.means.cpu())
    assert "data_device='cuda'" in (tmp_path / "cuda" / "cfg_args").read_text()
    with pytest.raises(RuntimeError, match="CUDA device"):
        resolve_device(f"cuda:{torch.cuda.device_count()}")


def test_training_is_deterministic(scene_views):
    scene, images = scene_views
    cfg = _small_config(iterations=40, densify_from_iter=10, densify_until_iter=35, densification_interval=10,
                        init_points=1000)
    a = train((scene.cameras[:4], images[:4]), config=cfg, progress=False, background=scene.background)
    b = train((scene.cameras[:4], images[:4]), config=cfg, progress=False, background=scene.background)
    assert a.gaussians.num_gaussians == b.gaussians.num_gaussians
    assert torch.equal(a.gaussians.means, b.gaussians.means)


def test_scaled_config():
    cfg = TrainConfig.scaled(3000)
    assert (cfg.densify_from_iter, cfg.densify_until_iter, cfg.densification_interval) == (50, 1500, 20)
    assert (cfg.opacity_reset_interval, cfg.sh_increase_interval) == (1000, 100)
    assert TrainConfig.scaled(15000).densification_interval == 50
    assert TrainConfig.scaled(3000, densification_interval=25).densification_interval == 25
    d = TrainConfig()
    assert (d.iterations, d.position_lr_init, d.densify_grad_threshold, d.lambda_dssim) == (30000, 1.6e-4, 2e-4, 0.2)
    with pytest.raises(ValueError):
        TrainConfig(iterations=0)
    with pytest.raises(ValueError):
        TrainConfig(sh_degree=4)


@pytest.mark.parametrize("device", DEVICES)
def test_adam_surgery(device):
    params = {"a": torch.arange(8.0, device=device).reshape(4, 2), "b": torch.arange(4.0, device=device)}
    opt = GaussianAdam(params, {"a": 0.1, "b": 0.1})
    (opt.params["a"].sum() * 2 + opt.params["b"].pow(2).sum()).backward()
    opt.step()
    st_a = opt.optimizer.state[opt.params["a"]]
    m_before = st_a["exp_avg"].clone()
    opt.prune(torch.tensor([True, False, True, True], device=device))
    assert opt.params["a"].shape == (3, 2) and opt.params["a"].requires_grad and opt.params["a"].is_leaf
    assert torch.equal(opt.optimizer.state[opt.params["a"]]["exp_avg"], m_before[[0, 2, 3]])
    opt.append({"a": torch.ones(2, 2), "b": torch.ones(2)})  # rows follow the parameters' device
    st = opt.optimizer.state[opt.params["a"]]
    assert opt.params["a"].shape == (5, 2) and st["exp_avg"].shape == (5, 2)
    assert opt.params["a"].device.type == st["exp_avg"].device.type == device
    assert torch.equal(st["exp_avg"][3:], torch.zeros(2, 2, device=device))
    assert torch.equal(st["exp_avg"][:3], m_before[[0, 2, 3]])
    assert len(opt.optimizer.state) == 2  # no stale entries for replaced tensors
    opt.replace("b", torch.zeros(5, device=device))
    assert torch.equal(opt.optimizer.state[opt.params["b"]]["exp_avg_sq"], torch.zeros(5, device=device))
    opt.zero_grad()
    (opt.params["a"].sum() + opt.params["b"].sum()).backward()
    opt.step()  # still a working optimiser
    opt.set_lr("a", 0.5)
    assert opt.lr("a") == 0.5


@pytest.mark.parametrize("device", DEVICES)
def test_densification_gradient_units(device):
    """Accumulated statistic = |pixel gradient * (W/2, H/2)| (INRIA's NDC gradient), on the training device."""
    g = random_init(3, torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64), sh_degree=0,
                    device=device)
    st = _State(g, TrainConfig(sh_degree=0), 1.0, device)
    assert {t.device.type for t in (st.grad_accum, st.denom, st.max_radii, *st.opt.params.values())} == {device}
    m2d = torch.zeros(3, 2, device=device, requires_grad=True)
    m2d.grad = torch.tensor([[1e-6, 0.0], [0.0, 2e-6], [5.0, 5.0]], device=device)
    st.accumulate(m2d, torch.tensor([3, 4, 0], dtype=torch.int32, device=device), width=200, height=100)
    assert st.grad_accum.tolist() == pytest.approx([1e-4, 1e-4, 0.0])
    assert st.denom.tolist() == [1.0, 1.0, 0.0] and st.max_radii.tolist() == [3.0, 4.0, 0.0]


@pytest.mark.parametrize("device", DEVICES)
def test_densify_clone_split_prune(device):
    lo, hi = torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    g = random_init(4, lo, hi, sh_degree=0, opacity=0.5, device=device)
    g.log_scales[:] = torch.log(torch.tensor(0.001))
    g.log_scales[1] = torch.log(torch.tensor(0.05))  # large -> split
    g.opacity_logits[3] = -10.0  # transparent -> pruned
    st = _State(g, TrainConfig(sh_degree=0, percent_dense=0.01), 1.0, device)
    st.grad_accum = torch.tensor([1.0, 1.0, 0.0, 0.0], device=device)
    st.denom = torch.ones(4, device=device)
    info = st.densify_and_prune(torch.Generator().manual_seed(0), prune_big=False)
    assert info == {"cloned": 1, "split": 1, "pruned": 1}
    # kept: 0, 2 (original), clone of 0, two children of 1
    assert st.n == 5 and st.opt.params["means"].device.type == st.grad_accum.device.type == device
    scales = st.opt.params["log_scales"].detach().exp()
    assert torch.allclose(scales[-2:], torch.full((2, 3), 0.05 / 1.6, device=device))
    assert torch.equal(st.opt.params["means"][2], st.opt.params["means"][0])
    st.max_radii = torch.tensor([0.0, 30.0, 0.0, 0.0, 0.0], device=device)  # over 20 px on screen -> pruned
    assert st.densify_and_prune(torch.Generator(), prune_big=True) == {"cloned": 0, "split": 0, "pruned": 1}
    assert st.n == 4


def test_init_box_contains_look_target(scene_views):
    scene, _ = scene_views
    lo, hi = init_box(scene.cameras)
    centre = (lo + hi) / 2
    assert torch.allclose(centre, torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64), atol=1e-6)
    assert float((hi - lo)[0]) == pytest.approx(2 * 0.33 * 4.0, rel=1e-6)


def test_progress_bar():
    buf = io.StringIO()
    with Progress(4, "t", stream=buf, min_interval=0.0) as bar:
        for _ in range(4):
            bar.update(loss=0.5, n=7)
    text = buf.getvalue()
    assert "4/4" in text and "loss=0.5" in text and "n=7" in text
    silent = io.StringIO()
    with Progress(4, stream=silent, enabled=False) as bar:
        bar.update()
    assert silent.getvalue() == ""


def test_bad_inputs(scene_views):
    scene, images = scene_views
    with pytest.raises(TypeError, match="Dataset"):
        train("nope", config=_small_config(iterations=1), progress=False)
    with pytest.raises(ValueError, match="images must be"):
        train((scene.cameras[:2], images[:3]), config=_small_config(iterations=1), progress=False)
    with pytest.raises(ValueError, match="init"):
        train((scene.cameras[:2], images[:2]), config=_small_config(iterations=1), init="bogus", progress=False)
    with pytest.raises(ValueError, match="point cloud"):
        train((scene.cameras[:2], images[:2]), config=_small_config(iterations=1), init="points", progress=False)


def _cli(argv):
    return build_parser().parse_args(argv)


def test_cli_default_scene(tmp_path, capsys):
    out = tmp_path / "model"
    args = _cli(["train", "default", "-o", str(out), "--iterations", "40", "--scene-size", "48", "--sh-degree", "0",
                 "--init-points", "1500", "--no-progress"])
    cfg = config_from_args(args)
    assert cfg.densify_until_iter == 20 and cfg.max_train_time_s is None
    assert cfg.device == str(resolve_device("auto"))  # --device auto, resolved
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["num_gaussians"] > 0 and "test_psnr" in summary
    assert summary["device"] == cfg.device and summary["iterations"] == 40
    assert load_inria_model(out).iteration == 40


def test_cli_bad_data(tmp_path, capsys):
    assert main(["train", str(tmp_path / "missing"), "-o", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gsw train: error: ") and "not found" in err and not (tmp_path / "o").exists()
    args = _cli(["train", "x", "-o", "y", "--black", "--device", "cpu", "--time-budget-s", "30"])
    assert args.background == "black"
    cfg = config_from_args(args)
    assert (cfg.device, cfg.max_train_time_s) == ("cpu", 30.0)
