"""gsw.fingerprint.shared: the scene hash, the per-worker scene cache and the warm-up."""

from __future__ import annotations

import torch

from gsw.fingerprint.batched import pool_config
import gsw.fingerprint.shared as shared_module
from gsw.fingerprint.shared import prepare_scene, scene_hash, warm_worker, worker_scene
from gsw.render.rasterize import rasterize
from gsw.scenes import default_scene


def _scene():
    sc = default_scene(width=32, height=32, n_cameras=2, detail=0.2, seed=0)
    cfg = pool_config(epochs=1, lpips_net=None, weights={"lpips": 0.0}, fgd=True,  # FGD: the pool's option, off by
                      background=tuple(float(v) for v in sc.background))  # default; these tests are about its scene
    return sc, cfg


def test_scene_hash_sees_the_images() -> None:
    sc, cfg = _scene()
    photos = [rasterize(sc.gaussians, c, background=sc.background).image for c in sc.cameras]
    dimmer = [0.5 * im for im in photos]
    plain = scene_hash(sc.gaussians, sc.cameras, 32, cfg)
    assert plain == scene_hash(sc.gaussians, sc.cameras, 32, cfg, None)
    assert len({plain, scene_hash(sc.gaussians, sc.cameras, 32, cfg, photos),
                scene_hash(sc.gaussians, sc.cameras, 32, cfg, dimmer)}) == 3
    assert scene_hash(sc.gaussians, sc.cameras, 32, cfg, photos) == scene_hash(sc.gaussians, sc.cameras, 32, cfg,
                                                                               [im.clone() for im in photos])


def test_a_worker_reuses_its_scene_only_for_the_same_job() -> None:
    """Two jobs of one model whose FGD differs (here: with and without images) each get their own worker scene
    in one process; the batches of one job share theirs."""
    sc, cfg = _scene()
    black = [torch.zeros(3, c.height, c.width) for c in sc.cameras]  # photos that make FGD prune differently
    a = prepare_scene(sc.gaussians, sc.cameras, config=cfg)
    b = prepare_scene(sc.gaussians, sc.cameras, config=cfg, images=black)
    assert a.stats["pruned"] != b.stats["pruned"]
    wa = worker_scene(a, "cpu")
    assert worker_scene(a, "cpu") is wa
    wb = worker_scene(b, "cpu")
    assert wb is not wa and len(wb.model) == len(b.model) != len(a.model)


def test_a_warmed_worker_uses_its_parts_for_that_job_only() -> None:
    """What :func:`warm_worker` prepared before the scene existed is what the job's worker scene uses, and
    equals what the worker would have built; another job's token builds its own."""
    sc, cfg = _scene()
    warm_worker("job-1", sc.gaussians, sc.cameras, cfg, 32, None, "cpu")
    warmed = dict(shared_module._WARM)
    shared = prepare_scene(sc.gaussians, sc.cameras, config=cfg, token="job-1")
    ws = worker_scene(shared, "cpu")
    (originals, loss, seconds), = warmed.values()
    assert ws.loss is loss and all(a is b for a, b in zip(ws.originals, originals)) and ws.warm_s == seconds > 0
    cold = prepare_scene(sc.gaussians, sc.cameras, config=cfg)  # a new token: built in the worker
    warm_worker("job-2", sc.gaussians, sc.cameras, cfg, 32, None, "cpu")
    wc = worker_scene(cold, "cpu")
    assert wc.loss is not loss and wc.warm_s == 0 and not shared_module._WARM  # job-2's parts dropped: one job a worker
    assert all(torch.equal(a, b) for a, b in zip(wc.originals, originals))


def test_references_are_made_once_per_view(monkeypatch) -> None:
    """The pool's references are the wavelet details and LPIPS features of each view's original render, made once
    per view while they fit the budget, and made again per call beyond it."""
    from gsw.decoder.dwt import dwt2

    sc = default_scene(width=32, height=32, n_cameras=3, detail=0.2, seed=0)
    cfg = pool_config(epochs=1, background=tuple(float(v) for v in sc.background))
    ws = worker_scene(prepare_scene(sc.gaussians, sc.cameras, config=cfg), "cpu")
    lp = ws.loss.lpips
    calls = []
    monkeypatch.setattr(lp, "references", lambda y: calls.append(1) or type(lp).references(lp, y))
    refs = ws.references([2, 0, 2])
    stacked = torch.stack([ws.originals[v] for v in (2, 0, 2)])
    for got, want in zip(refs.lpips, lp.references(stacked)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
    for got, want in zip(refs.highs, dwt2(stacked)[1]):
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    ws.references([0, 1])
    assert len(calls) == 1 + 2 + 1  # the check above, views 2 and 0, then view 1 only
    monkeypatch.setattr(shared_module, "REFERENCE_BYTES", 0)
    ws._references.clear()
    calls.clear()
    ws.references([1])
    ws.references([1])
    assert len(calls) == 2 and not ws._references
