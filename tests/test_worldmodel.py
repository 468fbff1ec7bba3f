"""The learned world model: it can learn, the shipped one beats simple baselines on held-out
procedural scenes, it drives background traffic about as safely as the expert replay, and
CCE-MAPPO's magnet KL reads its distribution.

Held-out scenes use seeds from 10,000 on; the shipped model saw procedural:all seeds 0..107.
The figures each test measures are printed (pytest -s shows them)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, TrainConfig, load_config
from tg_gpudrive.data.procedural import SCENARIO_TYPES, generate_scene
from tg_gpudrive.learn.losses import categorical_kl
from tg_gpudrive.rollout import constant_policy, expert_policy
from tg_gpudrive.worldmodel import WorldModel, WorldModelDriver, WorldModelPrior, load_world_model
from tg_gpudrive.worldmodel.prior import SHIPPED
from tg_gpudrive.worldmodel.train import (WorldModelConfig, background_rates, baseline_nlls, build_model, collect,
                                          dataset_nll, fit, model_policy_factory, sampled_displacement)

WM_CONFIG = REPO_CONFIGS / "worldmodel" / "small_cpu.yaml"


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # the small attention batches run several times slower when two threads contend for two cores
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def wm_cfg() -> WorldModelConfig:
    return load_config(WorldModelConfig, WM_CONFIG)


@pytest.fixture(scope="module")
def heldout():
    return [generate_scene(t, 10_000 + i) for i, t in enumerate(SCENARIO_TYPES)]


@pytest.fixture(scope="module")
def shipped() -> WorldModel:
    assert SHIPPED.exists(), "tg_gpudrive/worldmodel/shipped.pt is missing"
    assert SHIPPED.stat().st_size < 10 * 2**20
    return load_world_model(SHIPPED)


def _collect(scenes, cfg: WorldModelConfig):
    return collect(scenes, cfg.env, history=cfg.history, max_partners=cfg.max_partners, max_roads=cfg.max_roads)


def test_memorises_a_tiny_dataset(wm_cfg):
    torch.manual_seed(0)
    data = _collect([generate_scene("merge", 3), generate_scene("t_junction", 4)], wm_cfg)
    keep = torch.randperm(data["target"].shape[0], generator=torch.Generator().manual_seed(0))[:256]
    data = {k: (v[keep] if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    model = WorldModel(hidden=32, heads=4, partner_k=data["layout"][0], road_k=data["layout"][1])
    before = dataset_nll(model, data)["nll"]
    fit(model, data, steps=300, batch_size=256, lr=5e-3, gen=torch.Generator().manual_seed(0))
    after = dataset_nll(model, data)
    # a model that ignores its inputs can do no better than the action frequencies (about 1.6 nats here)
    floor = baseline_nlls(data, wm_cfg.env, data)["marginal"]
    print(f"\ntiny set: nll {before:.3f} -> {after['nll']:.3f} (accuracy {after['accuracy']:.2f}); "
          f"input-blind floor {floor:.3f}")
    assert after["nll"] < 0.25 * floor
    assert after["accuracy"] > 0.9


def test_shipped_model_beats_baselines_on_heldout_nll(shipped, heldout, wm_cfg):
    data = _collect(heldout, wm_cfg)
    got = dataset_nll(shipped, data)
    base = baseline_nlls(data, wm_cfg.env, data)  # marginal fitted on the held-out set itself: generous
    print(f"\nheld-out NLL (nats, {data['target'].shape[0]} agent-steps): world model {got['nll']:.3f} "
          f"(top-1 {got['accuracy']:.2f}); " + ", ".join(f"{k} {v:.3f}" for k, v in base.items()))
    assert got["nll"] < base["constant_velocity"] - 0.3
    assert got["nll"] < base["marginal"] - 0.2
    assert got["nll"] < base["uniform"]
    # ExpertPrior is centred on the true logged action: an oracle bound no model reaches
    assert base["expert_oracle"] < got["nll"]


def test_sampled_rollouts_beat_constant_velocity(shipped, heldout, wm_cfg):
    scenes = heldout[:3]
    wm = sampled_displacement(model_policy_factory(shipped), scenes, wm_cfg.env, samples=6, horizon=60)
    cv = sampled_displacement(lambda: constant_policy, scenes, wm_cfg.env, samples=1, horizon=60)
    ex = sampled_displacement(lambda: expert_policy, scenes, wm_cfg.env, samples=1, horizon=60)
    print(f"\n6 s horizon, {wm['agents']} vehicles: world model (6 samples) minADE {wm['minADE']:.2f} m "
          f"minFDE {wm['minFDE']:.2f} m; constant velocity ADE {cv['minADE']:.2f} FDE {cv['minFDE']:.2f}; "
          f"expert replay ADE {ex['minADE']:.2f} FDE {ex['minFDE']:.2f}")
    assert wm["minADE"] < cv["minADE"]
    assert wm["minFDE"] < cv["minFDE"]


def _background(shipped, scenes, env, steps):
    wm = background_rates(WorldModelDriver(shipped, rows="background", seed=0), scenes, env, steps=steps)
    ex = background_rates(None, scenes, env, steps=steps)
    print(f"\nbackground vehicles ({wm['vehicles']}), {steps or 'one episode of'} steps closed loop: world model "
          f"collision {wm['collision_rate']:.3f} off-road {wm['offroad_rate']:.3f}; expert replay collision "
          f"{ex['collision_rate']:.3f} off-road {ex['offroad_rate']:.3f}")
    assert wm["vehicles"] == ex["vehicles"] > 20
    return wm, ex


def test_background_traffic_close_to_expert_replay_over_4s(shipped, heldout, wm_cfg):
    wm, ex = _background(shipped, heldout, wm_cfg.env, 40)
    # tolerance 0.10 absolute per rate (about 7 of the ~75 vehicles): every background vehicle is
    # model-driven and reacts to other model-driven vehicles, while the expert tracks its log
    assert abs(wm["collision_rate"] - ex["collision_rate"]) <= 0.10
    assert abs(wm["offroad_rate"] - ex["offroad_rate"]) <= 0.10


def test_background_traffic_full_episode_gap_stays_bounded(shipped, heldout, wm_cfg):
    """Over a full 8 s episode the teacher-forced model drifts more (closed-loop fine-tuning is
    not implemented): measured collision 0.027 and off-road 0.107 against the expert's 0 and 0.
    The bound below holds that known gap where it is, so a regression (or a broken model, which
    leaves the road most of the time) fails."""
    wm, ex = _background(shipped, heldout, wm_cfg.env, None)
    assert abs(wm["collision_rate"] - ex["collision_rate"]) <= 0.10
    assert abs(wm["offroad_rate"] - ex["offroad_rate"]) <= 0.15


def test_driver_writes_only_its_rows(shipped, heldout, wm_cfg):
    from tg_gpudrive.control import control_masks
    from tg_gpudrive.simulator import Simulator

    scenes = heldout[:2]
    veh = control_masks(scenes, wm_cfg.env, "vehicles")
    ctrl = [m & (np.cumsum(m) <= 2) for m in veh]
    sim = Simulator(scenes, wm_cfg.env, "cpu", controlled=ctrl, background=[v & ~c for v, c in zip(veh, ctrl)])
    sim.reset()
    sim.actions_index.fill_(-7)
    WorldModelDriver(shipped)(sim)
    bg = (sim.background != 0) & (sim.present != 0)
    assert bool((sim.actions_index[bg] >= 0).all())
    assert bool((sim.actions_index[~bg] == -7).all())


def test_continuous_configs_are_refused(shipped, heldout):
    from tg_gpudrive.simulator import Simulator

    sim = Simulator(heldout[:1], EngineConfig(max_agents=32, action_space="continuous"), "cpu")
    with pytest.raises(NotImplementedError, match="discrete"):
        WorldModelPrior(shipped, sim)


def test_magnet_kl_uses_the_world_model(shipped, tmp_path):
    from tg_gpudrive.learn.train import Trainer

    cfg = dataclasses.replace(load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml"), num_worlds=2,
                              num_scenes=2, rollout_steps=4, updates=1, epochs=1, minibatches=1, hidden=32,
                              quantiles=8, out_dir=str(tmp_path))
    tr = Trainer(cfg, progress=False)
    start = (tr.sim.snapshot(), copy.deepcopy(tr.actor.state_dict()), copy.deepcopy(tr.critic.state_dict()),
             copy.deepcopy(tr.opt.state_dict()), copy.deepcopy(tr.lagrange.state_dict()), tr.gen.get_state())
    buf, _ = tr.rollout()  # with the ExpertPrior
    prior = WorldModelPrior(shipped, tr.sim)
    # the world-model context of the same rollout: replay its actions from the same engine state
    # (works whatever width the trainer's prior buffer has)
    T, W, C = buf["reward"].shape
    tr.sim.restore(start[0])
    ctx = torch.zeros(T, W, C, prior.context_dim)
    for t in range(T):
        assert torch.equal(tr.sim.obs[:, :C], buf["obs"][t])
        ctx[t] = prior.context(tr.sim, C)
        tr.sim.actions_index[:, :C] = buf["act"][t].to(torch.int32)
        tr.sim.step()

    def learn(b):
        tr.actor.load_state_dict(start[1]), tr.critic.load_state_dict(start[2])
        tr.opt.load_state_dict(start[3]), tr.lagrange.load_state_dict(start[4]), tr.gen.set_state(start[5])
        return tr.learn(b)

    kl_expert = learn(buf)["kl/prior"]
    tr.prior = prior
    kl_wm = learn(dict(buf, prior=ctx))["kl/prior"]
    # one epoch, one minibatch: the reported KL is KL(pi_init || prior) over the live rows
    tr.actor.load_state_dict(start[1])
    m = buf["mask"]
    with torch.no_grad():
        logits = tr.actor(buf["obs"][m], m.nonzero()[:, 2])
        want = categorical_kl(logits, shipped(buf["obs"][m], ctx[m].view(-1, shipped.history, 7))).mean()
    print(f"\nmagnet KL: ExpertPrior {kl_expert:.3f}, world model {kl_wm:.3f} (recomputed {float(want):.3f})")
    assert np.isfinite(kl_wm) and abs(kl_wm - kl_expert) > 0.1
    assert kl_wm == pytest.approx(float(want), rel=1e-3, abs=1e-4)
