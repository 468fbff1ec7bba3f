"""An actor that sees its own motion history (actor_history > 0, the paper's pi(a | o, h)), and its
nearest partners' (actor_history_partners > 0): the window reaches the network, the partners' part
is what the logs say by hand, the rollout stores what the actor saw, and every consumer of a
checkpoint (evaluate's policy, the CCE-gap's warm-started best response) feeds it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tg_gpudrive.config import REPO_CONFIGS, ConfigError, EngineConfig, TrainConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.evaluation import exploitability as ex
from tg_gpudrive.evaluation.episodes import record_episodes
from tg_gpudrive.history import HIST_DIM, PARTNER_HIST_DIM, HistoryBuffer, hist_dim
from tg_gpudrive.scene import make_scene
from tg_gpudrive.agents.networks import Actor
from tg_gpudrive.learn.train import Trainer
from tg_gpudrive.agents.policy import load_actor, load_policy

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"


def tiny(tmp_path, **kw) -> TrainConfig:
    cfg = load_config(TrainConfig, SMALL)
    base = dict(num_worlds=2, num_scenes=4, rollout_steps=8, epochs=1, minibatches=2, hidden=32, quantiles=8,
                updates=2, checkpoint_every=2, actor_history=3, out_dir=str(tmp_path))
    base.update(kw)
    return dataclasses.replace(cfg, **base)


def test_the_window_changes_the_actors_output_and_is_required():
    torch.manual_seed(0)
    actor = Actor(2, 3, discrete=True, num_actions=5, hidden=16, history=4)
    obs = torch.randn(6, 10 + 2 * 10 + 3 * 7)
    hist = torch.randn(6, 4, HIST_DIM)
    a = actor(obs, None, hist)
    b = actor(obs, None, hist + 1.0)
    assert a.shape == (6, 5) and not torch.allclose(a, b)
    with pytest.raises(ValueError, match="motion history"):
        actor(obs)
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 7\)"):
        actor(obs, None, hist[:, :2])
    assert Actor(2, 3, discrete=True, num_actions=5, hidden=16)(obs).shape == (6, 5)  # no history: as before


def test_a_plain_actor_grows_per_slot_heads_and_a_window_that_act_as_it_did():
    """grown_actor_state: each per-slot head a copy of the shared one (the same output exactly, on every slot), and
    a fresh window of the agent and two partners whose encoder starts near zero: the output moves by a small
    fraction of a fresh window's effect, the window's last layer still gets gradients, and every other weight is
    the plain actor's."""
    from tg_gpudrive.agents.networks import grown_actor_state

    torch.manual_seed(0)
    plain = Actor(2, 3, discrete=True, num_actions=5, hidden=16)
    obs, slot = torch.randn(6, 10 + 2 * 10 + 3 * 7), torch.arange(6)
    heads = Actor(2, 3, discrete=True, num_actions=5, hidden=16, heads=3)
    heads.load_state_dict(grown_actor_state(plain.state_dict(), heads))
    assert torch.equal(heads(obs, slot), plain(obs))
    both = Actor(2, 3, discrete=True, num_actions=5, hidden=16, heads=3, history=4, history_partners=2)
    fresh = both(obs, slot, torch.randn(6, 4, hist_dim(2)))  # a fresh window's effect, before growing
    both.load_state_dict(grown_actor_state(plain.state_dict(), both))
    hist = torch.randn(6, 4, hist_dim(2), requires_grad=False)
    out = both(obs, slot, hist)
    moved, fresh_moved = (out - plain(obs)).abs().max(), (fresh - plain(obs)).abs().max()
    assert 0 < moved < 0.05 * fresh_moved
    out.sum().backward()
    assert both.hist_encoder[-2].weight.grad.abs().sum() > 0
    kept = {k: v for k, v in plain.state_dict().items() if not k.startswith("head_")}
    assert all(torch.equal(both.state_dict()[k], v) for k, v in kept.items())


def test_rollout_stores_the_window_the_actor_saw(tmp_path, device):
    """At the first step of a rollout the newest window entry is the agent's present state: its
    position and heading in its own frame are 0 and its speed is the observation's ego speed."""
    tr = Trainer(tiny(tmp_path, device=device), tmp_path, progress=False)
    buf, _ = tr.collect()
    live = buf["mask"][0]
    h = buf["hist"][0][live].cpu()  # (n, H, HIST_DIM)
    assert h.shape[1:] == (3, HIST_DIM) and len(h) > 0
    newest = h[:, -1]
    np.testing.assert_allclose(newest[:, :3].numpy(), 0.0, atol=1e-4)  # dx, dy, dyaw
    obs = buf["obs"][0][live].cpu()  # bf16 on a GPU (the trainer stores what autocast would round to)
    np.testing.assert_allclose(newest[:, 3].to(obs.dtype).float().numpy(), obs[:, 0].float().numpy(), atol=1e-5)  # speed
    assert (newest[:, 6] == 1).all()  # valid


def test_a_history_checkpoint_evaluates_and_warm_starts_the_best_response(tmp_path, device):
    Trainer(tiny(tmp_path, device=device), tmp_path, progress=False).train()
    cfg = tiny(tmp_path)
    src = resolve_scenes(cfg.scenes, n=2, seed=123)
    sim = Simulator([src.get(i) for i in range(2)], cfg.env, device)
    tr = record_episodes(sim, load_policy(tmp_path, sim), label="history")
    assert tr.valid[tr.policy].any()
    actor = load_actor(tmp_path, sim)[0]
    assert actor.history == 3
    res = ex.cce_gap(lambda s: ex.SimGame(sim, actor=actor), seeds=(0,), max_iters=1,
                     min_iters=1, window=1, patience=1, eval_rounds=1)
    assert np.isfinite(res["mean_gap"])



def test_the_partners_window_is_their_logged_motion_in_the_agents_frame():
    """Car 0 drives along x at 1 m per step; car 1 runs 3 m to its left at 2 m per step, heading 0.1 rad;
    car 2 is far beyond the partner radius. Right after a reset the window is the log's last three
    warm-up steps: car 0's first partner block is car 1 there, in car 0's present frame, and its second
    block (no second partner) is zero."""
    T, H = 12, 3
    pos = np.zeros((3, T, 2))
    pos[0, :, 0] = np.arange(T) * 1.0
    pos[1, :, 0] = 10.0 + np.arange(T) * 2.0
    pos[1, :, 1] = 3.0
    pos[2] = 500.0
    yaw = np.zeros((3, T))
    yaw[1] = 0.1
    vel = np.zeros((3, T, 2))
    vel[0, :, 0], vel[1, :, 0], vel[1, :, 1] = 10.0, 20.0 * np.cos(0.1), 20.0 * np.sin(0.1)
    sc = make_scene(pos, yaw, log_vel=vel, goal=np.array([[300.0, 0.0], [300.0, 3.0], [600.0, 600.0]]))
    sim = Simulator([sc], EngineConfig(replay_infeasible=False, max_agents=4, init_steps=4, partner_k=2, road_k=4,
                                       partner_radius=30.0, control="all_agents"), "cpu")
    sim.reset()
    buf = HistoryBuffer(H)
    buf.sync(sim)
    f = buf.features(sim, partners=2)
    assert f.shape == (1, 4, H, hist_dim(2)) == (1, 4, H, HIST_DIM + 2 * PARTNER_HIST_DIM)
    torch.testing.assert_close(f[..., :HIST_DIM], buf.features(sim))  # the agent's own part, as before
    now = int(sim.world_step[0])
    steps = np.arange(now - H + 1, now + 1)
    x0 = pos[0, now, 0]
    want = np.stack([pos[1, steps, 0] - x0, np.full(H, 3.0), np.full(H, 0.1), np.full(H, 20.0), np.ones(H)], -1)
    np.testing.assert_allclose(f[0, 0, :, HIST_DIM:HIST_DIM + PARTNER_HIST_DIM].numpy(), want, atol=1e-4)
    assert (f[0, 0, :, HIST_DIM + PARTNER_HIST_DIM:] == 0).all()  # no second partner
    assert (f[0, 2, :, HIST_DIM:] == 0).all()  # car 2 has no partner within 30 m
    with pytest.raises(ValueError, match="partner_k >= 3"):
        buf.features(sim, partners=3)


def test_an_actor_that_sees_its_partners_windows_trains_and_evaluates(tmp_path, device):
    cfg = tiny(tmp_path, device=device, actor_history_partners=2)
    tr = Trainer(cfg, tmp_path, progress=False)
    buf, _ = tr.collect()
    assert buf["hist"].shape[-2:] == (3, hist_dim(2))
    tr.train()
    src = resolve_scenes(cfg.scenes, n=2, seed=123)
    sim = Simulator([src.get(i) for i in range(2)], cfg.env, device)
    actor = load_actor(tmp_path, sim)[0]
    assert (actor.history, actor.history_partners) == (3, 2)
    tr = record_episodes(sim, load_policy(tmp_path, sim), label="partners")
    assert tr.valid[tr.policy].any()
    with pytest.raises(ConfigError, match="actor_history_partners: needs actor_history"):
        tiny(tmp_path, actor_history=0, actor_history_partners=2)
    with pytest.raises(ConfigError, match=r"at most env.partner_k \(6\)"):
        tiny(tmp_path, actor_history_partners=9)
