"""gsw.fingerprint.batched: recipients fine-tuned together in a pool of slots get what each would get alone."""

from __future__ import annotations

import dataclasses
import sys

import pytest
import torch

from gsw.decoder.zoo import load_decoder
from gsw.fingerprint.batched import SlotParams, batched_loss, check_pool_config, finetune_batch, pool_config
from gsw.fingerprint.shared import prepare_scene, worker_scene
from gsw.fingerprint.stopping import PRESETS, EarlyStop
from gsw.mark.embed import EmbedConfig, embed
from gsw.mark.loss import LossWeights, WatermarkLoss
from gsw.mark.message import as_message
from gsw.scenes import default_scene
from helpers import ReadsOnes


@pytest.mark.parametrize("lpips_net", [None, "alex"])  # with alex: LPIPS per sample in one batch
def test_batched_loss_is_the_sum_of_the_single_losses(lpips_net) -> None:
    torch.manual_seed(0)
    weights = LossWeights(lpips=0.0) if lpips_net is None else LossWeights(mse=5.0)  # with and without MSE
    loss = WatermarkLoss(load_decoder(32), weights, lpips_net)
    renders = torch.rand(3, 3, 64, 64, requires_grad=True)
    original = torch.rand(3, 64, 64)
    messages = torch.randint(0, 2, (3, 32)).float()
    total, logits = batched_loss(loss, renders, original, messages)
    total.backward()
    single = renders.detach().clone().requires_grad_()
    parts = [loss(single[j], original, messages[j]) for j in range(3)]
    sum(p[0] for p in parts).backward()
    assert torch.allclose(total, sum(p[0] for p in parts).detach(), rtol=1e-5)
    assert torch.allclose(logits, torch.stack([p[2] for p in parts]), rtol=1e-4, atol=1e-3)  # batched convs
    assert torch.allclose(renders.grad, single.grad, rtol=1e-3, atol=1e-6)
    # with the references made once (one wavelet transform of the renders, the references' LPIPS features)
    from gsw.decoder.dwt import dwt2
    from gsw.fingerprint.batched import References

    originals = original[None].expand(3, -1, -1, -1)
    refs = References(dwt2(originals)[1], None if loss.lpips is None else loss.lpips.references(originals))
    again = renders.detach().clone().requires_grad_()
    total_refs, logits_refs = batched_loss(loss, again, original, messages, references=refs)
    total_refs.backward()
    torch.testing.assert_close(total_refs, total.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(logits_refs, logits, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(again.grad, renders.grad, rtol=1e-3, atol=1e-6)  # L1 signs at ~0 may differ


def test_stacked_parameters_start_from_the_model() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    assert not SlotParams(scene.gaussians, 1, pool_config(lpips_net=None)).rest.requires_grad  # the default
    params = SlotParams(scene.gaussians, 3, pool_config(lpips_net=None, freeze=(), mask="exp"))  # the paper's
    assert params.dc.shape == (3, len(scene.gaussians), 1, 3)
    for j in range(3):
        g = params.gaussians(j)
        assert torch.equal(g.sh, scene.gaussians.sh) and torch.equal(g.quats, scene.gaussians.quats)
    assert not params.means.requires_grad  # positions are shared and frozen by default
    assert all(mask.shape == p.shape[1:] for p, _, mask in params.groups)  # one recipient's mask, broadcast
    # a slot that is not stepped keeps its parameters; a reset slot starts over
    (params.dc.sum() + params.rest.sum() + params.logits.sum()).backward()
    params.step([0])
    assert not torch.equal(params.dc[0], params.dc[1]) and torch.equal(params.dc[1], params.dc[2])
    assert params.steps == [1, 0, 0]
    params.reset(0)
    assert torch.equal(params.dc[0], params.dc[1]) and params.steps == [0, 0, 0]
    assert all(float(m[0].abs().sum()) == 0 for m in params.exp_avg)


def _cpu_scene(epochs: int = 1, decoder: torch.nn.Module | None = None,
               weights: LossWeights = LossWeights(lpips=0.0, message=1.0)):
    """The 64x64 built-in scene with 3 views, a pool config of ``epochs`` passes without LPIPS, and its worker scene
    on the CPU with ``decoder`` (default: the shipped one): (scene, config, worker scene)."""
    scene = default_scene(width=64, height=64, n_cameras=3, detail=0.3)
    bg = tuple(float(v) for v in scene.background)
    cfg = pool_config(epochs=epochs, lpips_net=None, weights=weights, background=bg)
    return scene, cfg, worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg, decoder=decoder), "cpu")


def _pool_scene(epochs: int, decoder: torch.nn.Module | None = None):
    """:func:`_cpu_scene` with the default message weight and ``decoder`` (default :class:`ReadsOnes`, which reads
    every bit as 1): (config, worker scene)."""
    _, cfg, ws = _cpu_scene(epochs, decoder or ReadsOnes(), LossWeights(lpips=0.0))
    return cfg, ws


def test_batch_matches_one_at_a_time() -> None:
    _, _, ws = _cpu_scene()
    messages = torch.stack([as_message("c0ffee42", 32), as_message("12345678", 32)])
    steps = []
    both = finetune_batch(ws, ["a", "b"], messages, on_step=steps.append)
    alone = finetune_batch(ws, ["b"], messages[1:])[0]
    assert steps == [2, 2, 2]
    assert [r.name for r in both] == ["a", "b"]
    # the same optimisation up to float summation order (Adam with eps 1e-15 amplifies tiny differences)
    assert abs(both[1].psnr - alone.psnr) < 0.2
    assert abs(both[1].bit_accuracy - alone.bit_accuracy) <= 2 / 32
    assert (both[1].gaussians.sh - alone.gaussians.sh).abs().mean() < 1e-3
    # while the two recipients' copies differ (in the SH DC: the rest is frozen by default)
    assert (both[0].gaussians.sh[:, 0] - both[1].gaussians.sh[:, 0]).abs().mean() > 1e-3
    assert all(0 <= r.min_bit_accuracy <= r.bit_accuracy <= 1 and r.min_psnr <= r.psnr for r in both)


def test_a_refilled_slot_is_gsw_embed() -> None:
    scene, cfg, ws = _cpu_scene()
    messages = torch.stack([as_message(h, 32) for h in ("c0ffee42", "12345678", "abcdef01")])
    finished = []
    copies = finetune_batch(ws, ["a", "b", "c"], messages, slots=2, on_copy=lambda c: finished.append(c.name))
    assert [c.name for c in copies] == ["a", "b", "c"] and finished == ["a", "b", "c"]
    assert all(c.steps == 3 and not c.stopped_early for c in copies)
    # "c" ran in "a"'s slot after it: fresh parameters and Adam state, its own view order = gsw.embed's
    alone = embed(scene.gaussians, scene.cameras, message=messages[2], config=cfg, progress=False)
    # the same steps up to float summation order (Adam with eps 1e-15 amplifies it in a few elements)
    assert (copies[2].gaussians.sh - alone.gaussians.sh).abs().max() < 1e-3
    d = (copies[2].gaussians.opacity_logits - alone.gaussians.opacity_logits).abs()
    assert d.mean() < 1e-5 and d.max() < 5e-3
    assert abs(copies[2].psnr - sum(alone.psnr) / len(alone.psnr)) < 0.05


def test_early_stopping_finishes_and_refills() -> None:
    cfg, ws = _pool_scene(4)
    ones, zeros = torch.ones(32), torch.zeros(32)
    progress = []
    rule = EarlyStop(min_steps=4, window=3, margin=1.0, check_every=2)
    copies = finetune_batch(ws, ["yes", "no", "yes2"], torch.stack([ones, zeros, ones]), progress.append, slots=2,
                            stop=rule)
    assert [(c.steps, c.stopped_early) for c in copies] == [(4, True), (12, False), (4, True)]
    assert sum(progress) == 3 * 12  # skipped steps are reported when a recipient leaves
    assert copies[0].bit_accuracy == 1.0 and copies[1].bit_accuracy == 0.0
    # a margin above the decoder's confidence never passes
    strict = finetune_batch(ws, ["yes"], ones[None], stop=EarlyStop(min_steps=2, window=1, margin=6.0, check_every=1))
    assert strict[0].steps == 12 and not strict[0].stopped_early


class _RightInBatches(ReadsOnes):
    """Reads bit 0 as 0 (logit -4) when it decodes a single image: the training steps of two slots pass,
    the score of a finished copy (one view at a time) has 31 of 32 bits of a message of ones."""

    def __init__(self) -> None:
        super().__init__()
        self.bias.data.fill_(4.0)  # other weights than ReadsOnes': another decoder for the worker-scene cache

    def forward(self, ll: torch.Tensor) -> torch.Tensor:
        out = super().forward(ll)
        return out if ll.shape[0] > 1 else torch.cat([-out[:, :1], out[:, 1:]], dim=1)


def test_confirmation_on_the_embedding_views(monkeypatch) -> None:
    # the score decodes one view at a time (see _RightInBatches); gsw.mark.embed the module, not the function
    monkeypatch.setattr(sys.modules["gsw.mark.embed"], "SCORE_CHUNK", 1)
    cfg, ws = _pool_scene(4, _RightInBatches())
    ones = torch.ones(2, 32)
    strict = EarlyStop(min_steps=4, window=2, check_every=2, confirm=1.0)
    refused = finetune_batch(ws, ["a", "b"], ones, stop=strict)
    assert [(c.steps, c.stopped_early) for c in refused] == [(12, False)] * 2
    assert all(c.refusals == 2 for c in refused)  # attempts at 4 and 8 steps (the window doubles), all refused
    lenient = EarlyStop(min_steps=4, window=2, check_every=2, confirm=0.95)
    copies = finetune_batch(ws, ["a", "b"], ones, stop=lenient)
    assert [(c.steps, c.stopped_early, c.bit_accuracy) for c in copies] == [(4, True, 31 / 32)] * 2
    assert strict.confirmed(1.0, 20.0) and not strict.confirmed(0.99, 50.0)
    assert not EarlyStop(psnr_target=37.0).confirmed(1.0, 36.9)


def test_a_copy_failing_the_confirmation_at_the_cap_goes_on_once() -> None:
    cfg, ws = _pool_scene(4)
    progress = []
    # min_steps above the cap: no early stop; "good" reads every bit (confirmed at the cap), "bad" none
    rule = EarlyStop(min_steps=100, window=1, check_every=2, confirm=0.9, extend=0.5)
    good, bad = finetune_batch(ws, ["good", "bad"], torch.stack([torch.ones(32), torch.zeros(32)]), progress.append,
                               stop=rule)
    assert (good.steps, good.bit_accuracy) == (12, 1.0)
    assert (bad.steps, bad.stopped_early, bad.bit_accuracy) == (18, False, 0.0)  # 12 + 0.5 x 12, then as it is
    assert sum(progress) == 2 * 12  # the extension's steps are not counted: the bar's total stays R x cap
    assert rule.extension(12) == 6 and EarlyStop().extension(12) == 0


@pytest.mark.parametrize("focus", [0.0, 1.0])
def test_a_failed_confirmation_focuses_the_steps_on_the_views_read_wrong(monkeypatch, focus) -> None:
    from gsw.fingerprint import batched

    cfg, ws = _pool_scene(4)  # 3 views, cap 12; ReadsOnes passes every training step of a message of ones
    views: list[int] = []
    real_view = batched._Pool._view
    monkeypatch.setattr(batched._Pool, "_view", lambda self, slot: views.append(int((r := real_view(self, slot))[1]))
                        or r)
    # the score reads one bit wrong on view 1 only: every early stop is refused (confirm=1)
    monkeypatch.setattr(batched, "final_scores", lambda *a: (torch.tensor([1.0, 31 / 32, 1.0]), torch.full((3,), 50.0)))
    rule = EarlyStop(min_steps=4, window=1, check_every=2, confirm=1.0, focus=focus)
    copy = finetune_batch(ws, ["a"], torch.ones(1, 32), stop=rule)[0]
    assert (copy.steps, copy.stopped_early) == (12, False) and copy.refusals >= 1
    assert sorted(views[:3]) == [0, 1, 2]  # the first epoch: the shuffled order
    if focus:
        assert views[4:] == [1] * 8  # refused at step 4: from then on only the view read wrong
    else:
        assert sorted(views) == [0] * 4 + [1] * 4 + [2] * 4  # no focus: the shuffled epochs, as without a rule


def test_probes_between_the_views_gate_the_confirmation_and_take_the_focused_steps(monkeypatch) -> None:
    from gsw.fingerprint import batched

    cfg, ws = _pool_scene(4)  # 3 views, cap 12; ReadsOnes passes every training step of a message of ones
    views: list[int] = []
    real_view = batched._Pool._view
    monkeypatch.setattr(batched._Pool, "_view", lambda self, slot: views.append(int((r := real_view(self, slot))[1]))
                        or r)

    def scores(copy, cams, originals, dec, target, bg):  # every embedding view reads all bits, every probe 90 %
        between = torch.tensor([c.name == "sampled_between" for c in cams])
        return torch.where(between, 0.9, 1.0), torch.full((len(cams),), 50.0)

    monkeypatch.setattr(batched, "final_scores", scores)
    rule = EarlyStop(min_steps=4, window=1, check_every=2, confirm=1.0, focus=1.0, probes=2)
    copy = finetune_batch(ws, ["a"], torch.ones(1, 32), stop=rule)[0]
    assert (copy.steps, copy.stopped_early, copy.bit_accuracy) == (12, False, 1.0) and copy.refusals >= 1
    assert copy.probe_bit_accuracy == pytest.approx(0.9)
    assert ws.probe_views(2) == [3, 4] and [ws.camera(v).name for v in (3, 4)] == ["sampled_between"] * 2
    assert set(views[4:]) == {3, 4}  # refused at step 4: from then on only the probes, read wrong
    from gsw.render.rasterize import rasterize
    assert torch.equal(ws.original(3), rasterize(ws.bank.original, ws.camera(3), background=cfg.background).image)
    assert finetune_batch(ws, ["b"], torch.ones(1, 32), stop=dataclasses.replace(rule, probe_bits=0.85))[0].steps == 4
    plain = finetune_batch(ws, ["c"], torch.ones(1, 32), stop=dataclasses.replace(rule, probes=0))[0]
    assert (plain.steps, plain.probe_bit_accuracy) == (4, None)  # no probes: nothing scored between the views
    assert rule.confirmed(1.0, 50.0, 0.99) and not rule.confirmed(1.0, 50.0, 0.98) and rule.confirmed(1.0, 50.0)
    redrawing = dataclasses.replace(rule, redraw=1)
    assert redrawing.redraws(1.0, 0, 0.9) and not redrawing.redraws(1.0, 0, 0.995) and not redrawing.redraws(1.0, 1, 0.9)


def test_a_copy_below_redraw_bits_at_its_last_cap_gets_a_new_message() -> None:
    from gsw.mark.message import redrawn_message

    cfg, ws = _pool_scene(4)
    ones, zeros = torch.ones(32), torch.zeros(32)
    progress = []
    # ReadsOnes reads every bit as 1: a message of zeros reads 0 %, a redrawn one about half its bits, never all
    rule = EarlyStop(min_steps=100, window=1, check_every=2, confirm=0.9, redraw=2, redraw_bits=0.9)
    good, drawn, given = finetune_batch(ws, ["good", "drawn", "given"], torch.stack([ones, zeros, zeros]),
                                        progress.append, slots=2, stop=rule, redrawable=[True, True, False])
    assert (good.redraws, good.message, good.bit_accuracy) == (0, None, 1.0)  # never below redraw_bits
    assert (given.redraws, given.message, given.steps) == (0, None, 12)  # a given message is kept as it is
    assert (drawn.redraws, drawn.steps, drawn.redrawn_steps) == (2, 12, 24)  # two attempts discarded
    expected = redrawn_message(redrawn_message(zeros, 1), 2)
    assert torch.equal(drawn.message, expected) and 0 < drawn.bit_accuracy < 0.9
    assert drawn.bit_accuracy == pytest.approx(float(expected.mean()))
    assert sum(progress) == 3 * 12  # a redrawn recipient's later attempts are not counted
    # its copy is what a recipient with the last message gets from scratch (fresh parameters and Adam state)
    alone = finetune_batch(ws, ["alone"], expected[None], stop=EarlyStop(min_steps=100, window=1, check_every=2))[0]
    assert torch.equal(alone.gaussians.sh, drawn.gaussians.sh)
    assert not rule.redraws(0.5, 2) and rule.redraws(0.5, 1) and not rule.redraws(0.95, 0)
    # replacements are derived, different per attempt and message, uniform-looking bits
    assert not torch.equal(redrawn_message(zeros, 1), redrawn_message(zeros, 2))
    assert not torch.equal(redrawn_message(zeros, 1), redrawn_message(ones, 1))


def test_psnr_target_holds_back_and_steers_the_message_weight() -> None:
    cfg, ws = _pool_scene(2)
    rule = EarlyStop(min_steps=1, window=1, check_every=1, psnr_target=200.0, adapt=2.0, max_factor=4.0)
    copy = finetune_batch(ws, ["x"], torch.ones(1, 32), stop=rule)[0]
    assert copy.steps == 6 and not copy.stopped_early  # the PSNR target is out of reach
    assert copy.message_weight == pytest.approx(cfg.weights.message / 4)  # lowered down to its bound
    # PSNR above the target but bits that never pass: the weight goes back up, never above the configured one
    easy = EarlyStop(min_steps=1, window=1, check_every=1, psnr_target=-100.0, adapt=2.0)
    stuck = finetune_batch(ws, ["y"], torch.zeros(1, 32), stop=easy)[0]
    assert stuck.steps == 6 and stuck.message_weight == pytest.approx(cfg.weights.message)


def test_early_stop_settings() -> None:
    rule = EarlyStop.parse("min_steps=50, window=8,margin=1.5,psnr_target=37,adapt=1.2")
    assert (rule.min_steps, rule.window, rule.margin, rule.psnr_target, rule.adapt) == (50, 8, 1.5, 37.0, 1.2)
    assert EarlyStop.parse("psnr_target=none").psnr_target is None
    assert EarlyStop.parse("confirm=0.998").confirm == 0.998
    assert EarlyStop.parse("extend=0.5").extend == 0.5
    assert EarlyStop.parse("confirm=0.99,accuracy_window=32").accuracy_window == 32
    quality = EarlyStop.parse("quality")
    assert (quality.psnr_target, quality.confirm, quality.extend, quality.window) == (37.4, 0.995, 0.5, 16)
    assert EarlyStop.parse("quality, extend=1") == dataclasses.replace(quality, extend=1.0)  # later keys override
    careful = EarlyStop.parse("careful")
    assert (careful.min_steps, careful.confirm, careful.accuracy_window, careful.extend) == (384, 0.998, 32, 0.5)
    assert careful == EarlyStop.parse("quality,confirm=0.998,accuracy_window=32,min_steps=384")
    assert (EarlyStop.parse("careful,redraw=2").redraw, EarlyStop().redraw_bits) == (2, 0.995)
    assert (EarlyStop.parse("careful,focus=0.5").focus, EarlyStop().focus) == (0.5, 0.0)
    assert EarlyStop.parse("focused") == dataclasses.replace(careful, focus=1.0)
    assert EarlyStop.parse("assured") == dataclasses.replace(careful, focus=1.0, redraw=2)
    assert EarlyStop.parse("probed") == dataclasses.replace(careful, focus=1.0, redraw=2, probes=16)
    assert (EarlyStop.parse("assured,probes=8").probes, EarlyStop().probes, EarlyStop().probe_bits) == (8, 0, 0.99)
    for bad in ("probes=-1", "probe_bits=2", "probes=0.5"):
        with pytest.raises(ValueError, match="probe"):
            EarlyStop.parse(bad)
    for bad in ("redraw=-1", "redraw_bits=1.5", "redraw=0.5"):
        with pytest.raises(ValueError, match="redraw"):
            EarlyStop.parse(bad)
    assert EarlyStop.parse("throughput,extend=0.25") == EarlyStop.parse(PRESETS["throughput"] + ",extend=0.25")
    for bad, match in [("windw=3", "key=value"), ("margin=x", "not a number"), ("window=0", "window"),
                       ("adapt=1.5", "psnr_target"), ("confirm=99", "confirm"), ("extend=-1", "extend"),
                       ("accuracy_window=8", "confirmation"), ("focus=1.5", "focus"),
                       ("accuracy_window=1.5", "not a number"),
                       ("fastest", "not a preset"), ("quality,bogus=1", "key=value")]:
        with pytest.raises(ValueError, match=match):
            EarlyStop.parse(bad)


def test_a_running_accuracy_finishes_a_recipient_without_a_perfect_streak() -> None:
    """Slot 0 misses one bit of 32 on every 4th step (no streak of 8 perfect steps ever), slot 1 on every other
    step: with ``accuracy_window`` slot 0's running accuracy (~0.992) reaches confirm 0.99 after the window and
    it finishes; slot 1 (~0.984) does not; without the window neither does; a refusal doubles the steps needed."""
    from gsw.fingerprint.stopping import SlotMonitor

    msgs = torch.ones(2, 32)
    img = torch.zeros(2, 3, 8, 8)

    def run(rule, steps, monitor=None):
        monitor = monitor or SlotMonitor(2, 0.15, rule, torch.device("cpu"))
        for t in range(steps):
            logits = torch.full((2, 32), 3.0)
            logits[0, 5] = -3.0 if t % 4 == 0 else 3.0
            logits[1, 7] = -3.0 if t % 2 == 0 else 3.0
            monitor.observe(torch.tensor([0, 1]), logits, msgs, img, img)
        return monitor, monitor.decide([steps, steps], [True, True], [10_000, 10_000])

    with_window = EarlyStop(min_steps=8, window=8, confirm=0.99, accuracy_window=16)
    monitor, done = run(with_window, 40)
    assert done == [0]
    assert run(EarlyStop(min_steps=8, window=8, confirm=0.99), 40)[1] == []
    assert run(with_window, 10)[1] == []  # fewer steps than the window: no decision from the running accuracy
    monitor.refuse(0)
    assert run(with_window, 20, monitor)[1] == []  # 20 < 2 x 16 steps since the refusal
    assert run(with_window, 12, monitor)[1] == [0]


def test_train_time_image_attacks_per_slot() -> None:
    scene = default_scene(width=64, height=64, n_cameras=2, detail=0.3)
    bg = tuple(float(v) for v in scene.background)
    cfg = pool_config(epochs=2, lpips_net=None, weights={"lpips": 0.0}, background=bg, attacks=1.0)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    messages = torch.stack([as_message(h, 32) for h in ("c0ffee42", "12345678", "abcdef01")])
    copies = finetune_batch(ws, ["a", "b", "c"], messages, slots=2)  # attacks of different output sizes
    alone = embed(scene.gaussians, scene.cameras, message=messages[2], config=cfg, progress=False)
    # the same attacks as gsw.embed (Adam with eps 1e-15 amplifies float-order differences in a few elements)
    assert (copies[2].gaussians.sh - alone.gaussians.sh).abs().mean() < 1e-4


@pytest.mark.parametrize("bank", [0, 4])
def test_sampled_viewpoints_per_slot_are_gsw_embeds(bank) -> None:
    """With EmbedConfig.novel_views a recipient's steps render sampled viewpoints (targets: the input model's renders
    there), drawn from its own random state, fresh or from the job's bank (EmbedConfig.view_bank): a copy that ran in
    a refilled slot is gsw.embed's with that config."""
    scene = default_scene(width=64, height=64, n_cameras=3, detail=0.3)
    bg = tuple(float(v) for v in scene.background)
    cfg = pool_config(epochs=2, lpips_net=None, weights={"lpips": 0.0}, background=bg, novel_views=0.5,
                      view_bank=bank)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    messages = torch.stack([as_message(h, 32) for h in ("c0ffee42", "12345678", "abcdef01")])
    copies = finetune_batch(ws, ["a", "b", "c"], messages, slots=2)
    alone = embed(scene.gaussians, scene.cameras, message=messages[2], config=cfg, progress=False)
    # the same steps as gsw.embed (Adam with eps 1e-15 amplifies float-order differences in a few elements)
    assert (copies[2].gaussians.sh - alone.gaussians.sh).abs().mean() < 1e-4
    assert abs(copies[2].psnr - sum(alone.psnr) / len(alone.psnr)) < 0.05
    without = dataclasses.replace(cfg, novel_views=0.0)
    ws0 = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=without), "cpu")
    other = finetune_batch(ws0, ["c"], messages[2:])[0]
    # the sampled views changed the copy (its SH DC: the rest is frozen by default)
    assert (other.gaussians.sh[:, 0] - copies[2].gaussians.sh[:, 0]).abs().mean() > 1e-3
    assert len(ws.bank) == bank


def test_a_view_bank_renders_and_keeps_each_viewpoint_once(monkeypatch) -> None:
    """The bank's viewpoints are the sampler's first draws; each one's original render and references are made on
    first use and kept (within the reference budget), so the pool's sampled steps cost what an embedding view's do."""
    import gsw.fingerprint.shared as shared
    from gsw.mark.embed import ViewBank, embedding_view_sampler

    scene = default_scene(width=48, height=48, n_cameras=2, detail=0.2)
    cfg = pool_config(epochs=1, lpips_net=None, weights={"lpips": 0.0}, novel_views=1.0, view_bank=3)
    ws = worker_scene(prepare_scene(scene.gaussians, scene.cameras, config=cfg), "cpu")
    fresh = embedding_view_sampler(scene.gaussians, scene.cameras, cfg).sample_many(3)
    assert [torch.equal(a.viewmat, b.viewmat) for a, b in zip(ws.bank.cameras, fresh)] == [True] * 3
    renders = []
    real = ViewBank.render_camera
    monkeypatch.setattr(ViewBank, "render_camera", lambda self, cam: renders.append(cam) or real(self, cam))
    v = len(scene.cameras) + 1
    first = ws.references([v, v]).highs[0][0]
    again = ws.references([v]).highs[0][0]
    assert len(renders) == 1 and ws.camera(v) is ws.bank.cameras[1] and torch.equal(first[1:], again)
    monkeypatch.setattr(shared, "REFERENCE_BYTES", 0)  # over budget: made per call, never kept
    ws.references([v + 1])
    ws.references([v + 1])
    assert v + 1 not in ws._references and len(renders) == 2  # the render is kept; the references are not


@pytest.mark.parametrize("setting", [{"model_attacks": 0.5}, {"render_scales": (0.5, 2.0)}, {"psnr_target": 37.0}])
def test_settings_the_pool_does_not_implement_are_refused(setting) -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    with pytest.raises(ValueError, match=f"does not support EmbedConfig.{next(iter(setting))}"):
        prepare_scene(scene.gaussians, scene.cameras, config=pool_config(epochs=1, lpips_net=None,
                                                                         weights=LossWeights(lpips=0.0), **setting))


def test_the_library_default_is_poolable() -> None:
    check_pool_config(EmbedConfig())  # sampled viewpoints and a frozen SH rest: both implemented by the pool


def test_frozen_groups_stay_in_the_pool() -> None:
    scene = default_scene(width=32, height=32, n_cameras=2, detail=0.2)
    params = SlotParams(scene.gaussians, 2, pool_config(lpips_net=None, freeze=("f_rest", "scaling"), mask="none"))
    assert not params.rest.requires_grad and not params.log_scales.requires_grad
    assert {id(p) for p, _, _ in params.groups} == {id(params.dc), id(params.logits), id(params.quats)}


def test_pool_default_is_the_measured_setting() -> None:
    """The pool's defaults: gsw embed's default recipe on the given cameras with the AlexNet LPIPS term (BENCHMARKS.md,
    #26; the copies survive SH-0 / .splat / .spz exports); the CLI agrees."""
    import argparse

    from gsw.cli.fingerprint import register
    from gsw.cli.mark import embed_config
    from gsw.fingerprint.batched import POOL_LPIPS

    cfg = pool_config()
    assert cfg.lpips_net == POOL_LPIPS == "alex" and cfg.weights.lpips > 0
    # gsw embed's default recipe (SH rest frozen, no mask, the squared-error term, no FGD) on the given cameras only
    assert cfg == dataclasses.replace(EmbedConfig(), lpips_net=POOL_LPIPS, novel_views=0.0)
    assert cfg.freeze == ("f_rest",) and cfg.mask == "none" and cfg.weights == LossWeights() and not cfg.fgd
    assert pool_config(weights={"message": 0.3}).weights == dataclasses.replace(LossWeights(), message=0.3)
    assert pool_config(lpips_net="vgg").lpips_net == "vgg"
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["fingerprint", "m", "--recipients", "r.csv", "--output", "o"]
    args = parser.parse_args(base)
    assert args.lpips == POOL_LPIPS and embed_config(args, pool_config()) == pool_config(
        epochs=args.epochs, lpips_net=POOL_LPIPS, seed=0, background=(0.0, 0.0, 0.0))
    paper = embed_config(parser.parse_args(base + ["--freeze", "none", "--mask", "exp"]), pool_config())
    assert (paper.freeze, paper.mask) == ((), "exp")
    two = embed_config(parser.parse_args(base + ["--freeze", "f_rest,scaling"]), pool_config())
    assert (two.freeze, two.mask) == (("f_rest", "scaling"), "none")
    with pytest.raises(SystemExit):
        parser.parse_args(base + ["--freeze", "colour"])
