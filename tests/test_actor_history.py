"""An actor that sees its own motion history (actor_history > 0, the paper's pi(a | o, h)): the
window reaches the network, the rollout stores what the actor saw, and every consumer of a
checkpoint (evaluate's policy, the CCE-gap's warm-started best response) feeds it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tg_gpudrive.config import REPO_CONFIGS, TrainConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.evaluation import exploitability as ex
from tg_gpudrive.evaluation.episodes import record_episodes
from tg_gpudrive.history import HIST_DIM
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

