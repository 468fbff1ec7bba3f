"""The learned world model: it can learn (discrete grid and continuous Laplace-mixture heads),
the shipped one beats simple baselines on held-out procedural scenes, it drives background
traffic about as safely as the expert replay, CCE-MAPPO's magnet KL reads its distribution,
and closed-loop (DAgger) fine-tuning labels drifted states with actions back to the log.

Held-out scenes use seeds from 10,000 on; the shipped model saw procedural:all seeds 0..107.
The figures each test measures are printed (pytest -s shows them)."""

from __future__ import annotations

import copy
import math
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, TrainConfig, load_config
from tg_gpudrive.data.procedural import SCENARIO_TYPES, generate_scene
from tg_gpudrive.agents.policy import categorical_kl
from tg_gpudrive.agents.builtin import constant_policy, expert_policy
from tg_gpudrive.worldmodel import WorldModel, WorldModelDriver, WorldModelPrior, load_world_model
from tg_gpudrive.worldmodel.closed_loop import corrective_from_log, corrective_target
from tg_gpudrive.worldmodel.mixture import LaplaceMixture
from tg_gpudrive.worldmodel.prior import SHIPPED, save_world_model
from tg_gpudrive.worldmodel.data import collect
from tg_gpudrive.worldmodel.metrics import (background_rates, baseline_nlls, dataset_nll, model_policy_factory,
                                            sampled_displacement)
from tg_gpudrive.worldmodel.train import WorldModelConfig, build_model, fit, train_world_model

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


@pytest.mark.slow
def _reference_forward(model: WorldModel, obs: torch.Tensor, hist: torch.Tensor) -> torch.Tensor:
    """The world model's forward through PyTorch's own attention modules (the weights it holds)."""
    from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM

    def cross(ca, q, keys, mask):
        keys = torch.cat([ca.null.expand(len(keys), 1, -1), keys], dim=1)
        pad = torch.cat([mask.new_zeros(len(mask), 1), ~mask], dim=1)
        out, _ = ca.attn(q[:, None], keys, keys, key_padding_mask=pad, need_weights=False)
        return ca.norm(out[:, 0])

    k, kr = model.partner_k, model.road_k
    part = obs[:, EGO_DIM:EGO_DIM + k * PARTNER_DIM].reshape(-1, k, PARTNER_DIM)[:, :model.max_partners]
    road = obs[:, EGO_DIM + k * PARTNER_DIM:].reshape(-1, kr, ROAD_DIM)[:, :model.max_roads]
    q = model.ego(obs[:, :EGO_DIM] / model.ego_scale)
    t = cross(model.ca_time, q, model._hist_tokens(hist), hist[..., -1] > 0.5)
    m = cross(model.ca_map, q + t, model.road_in(road / model.road_scale), road[..., 0] > 0.5)
    n = cross(model.ca_agent, q + t + m, model.partner_in(part / model.partner_scale), part[..., 0] > 0.5)
    z = model.self_attn(torch.stack([q, t, m, n], dim=1))
    return model.head(z.reshape(len(z), -1))


@pytest.mark.parametrize("train", [False, True])
def test_attention_matches_pytorchs_modules(train):
    """The world model runs its attention written out (a few queries per row); on the same weights
    it gives PyTorch's nn.MultiheadAttention / TransformerEncoderLayer outputs and gradients,
    including rows whose partner, road or history sets are empty (only the null key is left)."""
    torch.manual_seed(0)
    from tg_gpudrive.history import HIST_DIM
    from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
    model = WorldModel(partner_k=4, road_k=6, max_partners=3, max_roads=5, history=5).double().train(train)
    for p in model.parameters():  # the null keys and biases start at 0: make every weight count
        p.data.add_(0.1 * torch.randn_like(p))
    n = 40
    obs = torch.randn(n, EGO_DIM + 4 * PARTNER_DIM + 6 * ROAD_DIM, dtype=torch.float64)
    lay = obs[:, EGO_DIM:].clone()
    lay[:, :4 * PARTNER_DIM].view(n, 4, PARTNER_DIM)[..., 0] = (torch.rand(n, 4) < 0.6).float()
    lay[:, 4 * PARTNER_DIM:].view(n, 6, ROAD_DIM)[..., 0] = (torch.rand(n, 6) < 0.6).float()
    lay[:3, :4 * PARTNER_DIM].view(3, 4, PARTNER_DIM)[..., 0] = 0.0  # no partner
    lay[3:6, 4 * PARTNER_DIM:].view(3, 6, ROAD_DIM)[..., 0] = 0.0  # no road point
    obs[:, EGO_DIM:] = lay
    hist = torch.randn(n, 5, HIST_DIM, dtype=torch.float64)
    hist[..., -1] = (torch.rand(n, 5) < 0.7).float()
    hist[6:9, :, -1] = 0.0  # no history
    obs.requires_grad_(True)
    got = model(obs, hist)
    g_got = torch.autograd.grad(got.square().sum(), [obs, *model.parameters()])
    want = _reference_forward(model, obs, hist)
    g_want = torch.autograd.grad(want.square().sum(), [obs, *model.parameters()])
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    for a, b in zip(g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)


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


def test_background_traffic_full_episode_within_issue_12s_bar(shipped, heldout, wm_cfg):
    """Over a full 8 s episode every vehicle of six held-out scenes (75) driven by the shipped model
    (GPU-trained, closed-loop fine-tuned): measured collision 0.000 and off-road 0.013 against the
    expert's 0 and 0 (seed 0; 512 held-out scenes on a GPU: 0.003 / 0.006). Issue 12's bar is 0.02;
    on 75 vehicles off-road gets 0.03 (two vehicles). The CPU model this one replaced, also packaged
    (`small_cpu`), misses it (0.027 / 0.107), so the bound tells the two apart."""
    wm, ex = _background(shipped, heldout, wm_cfg.env, None)
    assert wm["collision_rate"] - ex["collision_rate"] <= 0.02
    assert wm["offroad_rate"] - ex["offroad_rate"] <= 0.03
    old, _ = _background(load_world_model("small_cpu"), heldout, wm_cfg.env, None)
    assert old["offroad_rate"] - ex["offroad_rate"] > 0.03
    assert load_world_model("small_cpu").hparams["hidden"] == 64 and shipped.hparams["hidden"] == 128


def test_driver_writes_only_its_rows(shipped, heldout, wm_cfg):
    from tg_gpudrive.engine.control import control_masks
    from tg_gpudrive.engine.simulator import Simulator

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


def test_a_guarded_driver_leaves_no_action_its_guard_would_refuse(shipped, heldout, wm_cfg):
    """Behind guard_s, every background action is safe by the guard's own test wherever a safe one exists,
    over an episode of the two real scenes of tests/data, every vehicle driven by the world model."""
    from tg_gpudrive.data.sources import resolve_scenes
    from tg_gpudrive.engine.control import control_masks
    from tg_gpudrive.engine.model import sized_for
    from tg_gpudrive.engine.simulator import Simulator

    src = resolve_scenes(str(Path(__file__).parent / "data"))
    scenes = [src[i] for i in range(len(src))]
    env = sized_for(wm_cfg.env, scenes)
    veh = control_masks(scenes, env, "vehicles")
    sim = Simulator(scenes, env, "cpu", controlled=[m & False for m in veh], background=veh)
    sim.reset()
    drv = WorldModelDriver(shipped, seed=0, guard_s=1.0)
    for _ in range(sim.episode_length):
        drv(sim)
        rows = (sim.background != 0) & (sim.present != 0)
        obs, act = sim.obs[rows], sim.actions_index[rows].long()
        chosen = drv.guard.unsafe(obs, drv.guard.grid[act][:, None])[:, 0]
        none_safe = drv.guard.unsafe(obs, drv.guard.grid.expand(len(obs), -1, -1)).all(-1)
        assert not bool((chosen & ~none_safe).any())
        sim.step()
    assert drv.guard.replaced > 0  # the world model does drive into others, and the guard redraws those actions
    with pytest.raises(ValueError, match="needs the discrete world model"):
        WorldModelDriver(build_model(dataclasses.replace(_cont_cfg(wm_cfg), hidden=16)), guard_s=1.0)


def test_action_space_mismatch_is_refused(shipped, heldout, wm_cfg):
    from tg_gpudrive.config import ConfigError
    from tg_gpudrive.engine.simulator import Simulator

    sim = Simulator(heldout[:1], EngineConfig(max_agents=32, action_space="continuous"), "cpu")
    with pytest.raises(ValueError, match="discrete actions but the simulator's action_space is continuous"):
        WorldModelPrior(shipped, sim)
    with pytest.raises(ValueError, match="action_space"):
        load_world_model(SHIPPED, sim)
    with pytest.raises(ConfigError, match="bicycle"):
        dataclasses.replace(wm_cfg, env=EngineConfig(dynamics="delta_local", action_space="continuous"))


def test_magnet_kl_uses_the_world_model(shipped, tmp_path):
    from tg_gpudrive.learn.train import Trainer

    cfg = dataclasses.replace(load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml"), num_worlds=2,
                              num_scenes=2, rollout_steps=4, updates=1, epochs=1, minibatches=1, hidden=32,
                              quantiles=8, out_dir=str(tmp_path), prior="expert")
    tr = Trainer(cfg, progress=False)
    start = (tr.sim.snapshot(), copy.deepcopy(tr.actor.state_dict()), copy.deepcopy(tr.critic.state_dict()),
             copy.deepcopy(tr.opt.state_dict()), copy.deepcopy(tr.lagrange.state_dict()), tr.gen.get_state())
    buf, _ = tr.collect()  # with the ExpertPrior
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
    # the discrete magnet is stored as logits per live row and step, as the rollout does
    m = buf["mask"]
    wm_logits = torch.zeros(T, W, C, tr.sim.num_actions)
    wm_logits[m] = prior.distribution(ctx[m], buf["obs"][m])
    kl_wm = learn(dict(buf, prior=wm_logits))["kl/prior"]
    # one epoch, one minibatch: the reported KL is KL(pi_init || prior) over the live rows
    tr.actor.load_state_dict(start[1])
    m = buf["mask"]
    with torch.no_grad():
        logits = tr.actor(buf["obs"][m], m.nonzero()[:, 2])
        want = categorical_kl(logits, shipped(buf["obs"][m], ctx[m].view(-1, shipped.history, 7))).mean()
    print(f"\nmagnet KL: ExpertPrior {kl_expert:.3f}, world model {kl_wm:.3f} (recomputed {float(want):.3f})")
    assert np.isfinite(kl_wm) and abs(kl_wm - kl_expert) > 0.1
    assert kl_wm == pytest.approx(float(want), rel=1e-3, abs=1e-4)


def test_magnet_kl_of_the_trainer_matches_a_hand_computed_case(tmp_path):
    """A world model whose head ignores its inputs and puts probability 1/2 on the no-op bin and
    1/180 on each of the other 90, against a uniform policy over the 91 bins:

        KL(pi || p) = sum_k (1/91) (log(1/91) - log p_k)
                    = -log 91 - (log 0.5 + 90 log(1/180)) / 91   (~= 0.6326)

    which the trainer must report as kl/prior (one epoch, one minibatch: computed before the step)."""
    from tg_gpudrive.learn.train import Trainer

    cfg = dataclasses.replace(load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml"), num_worlds=2,
                              num_scenes=2, rollout_steps=4, updates=1, epochs=1, minibatches=1, hidden=32,
                              quantiles=8, out_dir=str(tmp_path), prior="world_model", eta1=0.5)
    tr = Trainer(cfg, progress=False)
    n = tr.sim.num_actions
    noop = cfg.env.noop_index
    p = torch.full((n,), 0.5 / (n - 1))
    p[noop] = 0.5
    wm = WorldModel(num_actions=n, hidden=16, heads=2, history=4, partner_k=cfg.env.partner_k,
                    road_k=cfg.env.road_k)
    with torch.no_grad():
        wm.head[-1].weight.zero_()
        wm.head[-1].bias.copy_(p.log())
        tr.actor.head_w.zero_()
        tr.actor.head_b.zero_()  # uniform policy
    tr.prior = WorldModelPrior(wm.eval(), tr.sim)
    buf, _ = tr.collect()
    assert bool(buf["mask"].any())
    got = tr.learn(buf)["kl/prior"]
    want = -np.log(91) - (np.log(0.5) + 90 * np.log(0.5 / 90)) / 91
    assert n == 91 and got == pytest.approx(want, rel=1e-4)


# ------------------------------------------------------------------ continuous head
def _cont_cfg(wm_cfg) -> WorldModelConfig:
    return dataclasses.replace(wm_cfg, env=dataclasses.replace(wm_cfg.env, action_space="continuous"))


def test_laplace_mixture_matches_numpy():
    g = torch.Generator().manual_seed(0)
    N, K = 5, 3
    logits = torch.randn(N, K, generator=g, dtype=torch.float64)
    loc = torch.randn(N, K, 2, generator=g, dtype=torch.float64)
    log_scale = torch.randn(N, K, 2, generator=g, dtype=torch.float64) * 0.5 - 1.0
    x = torch.randn(N, 2, generator=g, dtype=torch.float64)
    mix = LaplaceMixture(logits, loc, log_scale)
    lg, mu, b, xx = logits.numpy(), loc.numpy(), np.exp(log_scale.numpy()), x.numpy()
    want = np.zeros(N)
    for n in range(N):
        w = np.exp(lg[n] - lg[n].max())
        w /= w.sum()
        dens = [w[k] * np.prod(np.exp(-np.abs(xx[n] - mu[n, k]) / b[n, k]) / (2 * b[n, k])) for k in range(K)]
        want[n] = np.log(sum(dens))
    np.testing.assert_allclose(mix.log_prob(x).numpy(), want, rtol=1e-10)
    # sampling and the moment-matched (mean, log_std) the tuple carries agree
    big = LaplaceMixture(logits[:1].expand(200_000, K), loc[:1].expand(200_000, K, 2),
                         log_scale[:1].expand(200_000, K, 2))
    draws = big.sample(torch.Generator().manual_seed(1))
    mean, log_std = mix
    np.testing.assert_allclose(draws.mean(0).numpy(), mean[0].numpy(), atol=0.02)
    np.testing.assert_allclose(draws.std(0).numpy(), log_std[0].exp().numpy(), rtol=0.02)


def test_the_continuous_magnet_is_the_top_mixture_component():
    """Two rows, two components: the most probable one is kept, alone, with its own location and
    scale; the KL bound of one component is exact (the closed form of Gaussian -> Laplace)."""
    logits = torch.tensor([[0.0, 2.0], [1.0, -1.0]])
    loc = torch.tensor([[[1.0, 0.1], [-2.0, 0.2]], [[3.0, -0.1], [0.0, 0.0]]])
    log_scale = torch.log(torch.tensor([[[0.5, 0.01], [0.25, 0.02]], [[1.0, 0.03], [2.0, 0.04]]]))
    top = LaplaceMixture(logits, loc, log_scale).top_component()
    assert top.num_components == 1
    torch.testing.assert_close(top.loc[:, 0], torch.tensor([[-2.0, 0.2], [3.0, -0.1]]))
    torch.testing.assert_close(top.log_scale[:, 0].exp(), torch.tensor([[0.25, 0.02], [1.0, 0.03]]))
    # a Gaussian sitting on the component's location: KL = sum_d [log(2b/s) - 1/2 log(2 pi e) + s sqrt(2/pi)/b]
    s_ = torch.tensor([[0.1, 0.005], [0.2, 0.01]])
    kl = top.kl_from((top.loc[:, 0], s_.log()))
    b = top.log_scale[:, 0].exp()
    want = (torch.log(2 * b / s_) - 0.5 * math.log(2 * math.pi * math.e) + s_ * math.sqrt(2 / math.pi) / b).sum(-1)
    torch.testing.assert_close(kl, want, rtol=1e-5, atol=1e-6)


def test_the_continuous_magnet_is_no_sharper_than_min_std(wm_cfg):
    """A continuous world model whose components are as sharp as the head allows: the prior widens
    each to the std `min_std` (Laplace scale std / sqrt 2) and leaves wider ones alone. Hand-computed:
    a Gaussian of that std on the location is KL = -1/2 log(2 pi e) + 1/2 log 2 + 2 / sqrt(pi)
    = 0.0561 nats per dimension, whatever the std."""
    from tg_gpudrive.engine.simulator import Simulator

    cfg = _cont_cfg(wm_cfg)
    wm = build_model(cfg).eval()
    K = cfg.mixtures
    with torch.no_grad():
        wm.head[-1].weight.zero_()
        bias = torch.zeros(K, 5)
        bias[:, 0] = torch.arange(K, dtype=torch.float32)  # component K-1 is the most probable
        bias[:, 3:] = -30.0  # log-scales at the head's minimum
        bias[K - 1, 4] = 30.0  # ... except the top component's curvature: the head's widest
        wm.head[-1].bias.copy_(torch.cat([bias[:, 0], bias[:, 1:].reshape(-1)]))
    sim = Simulator([generate_scene("merge", 3)], cfg.env, "cpu")
    sim.reset()
    min_std = (0.7, 0.001)
    prior = WorldModelPrior(wm, sim, min_std=min_std)
    raw = WorldModelPrior(wm, sim)
    C = 4
    ctx = prior.context(sim, C)
    obs = sim.obs[:, :C]
    top, sharp = prior.distribution(ctx, obs), raw.distribution(ctx, obs)
    b = top.log_scale[..., 0, :].exp()
    b_raw = sharp.log_scale[..., 0, :].exp()
    assert float(b_raw[..., 0].max()) < 0.7 / math.sqrt(2) and float(b_raw[..., 1].min()) > 0.001
    torch.testing.assert_close(b[..., 0], torch.full_like(b[..., 0], 0.7 / math.sqrt(2)))  # floored
    torch.testing.assert_close(b[..., 1], b_raw[..., 1])  # wider than the floor: untouched
    loc = top.loc[..., 0, :]
    kl = top.kl_from((loc, torch.log(torch.stack([torch.full_like(b[..., 0], 0.7), b[..., 1] * math.sqrt(2)], -1))))
    per_dim = -0.5 * math.log(2 * math.pi * math.e) + 0.5 * math.log(2) + 2 / math.sqrt(math.pi)
    assert per_dim == pytest.approx(0.0561, abs=1e-4)
    torch.testing.assert_close(kl, torch.full_like(kl, 2 * per_dim), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="min_std"):
        WorldModelPrior(wm, sim, min_std=(0.7, 0.0))


def test_gaussian_to_laplace_kl():
    """One component: KL(N(m, s) || Laplace(mu, b)) = log(2b) - log(s sqrt(2 pi e)) + E|x - mu| / b,
    E|x - mu| the folded-normal mean; `kl_from` is exact there, an upper bound for mixtures (close
    while the policy sits under one component), and differentiable."""
    from math import erf, exp, log, pi, sqrt

    m = torch.tensor([[0.3, -0.02], [-1.0, 0.05]], dtype=torch.float64, requires_grad=True)
    log_std = torch.tensor([[-0.5, -3.0], [0.2, -4.0]], dtype=torch.float64, requires_grad=True)
    mu = torch.tensor([[0.0, 0.0], [0.5, 0.04]], dtype=torch.float64)
    log_b = torch.tensor([[-0.3, -3.5], [0.0, -4.5]], dtype=torch.float64)
    one = LaplaceMixture(torch.zeros(2, 1, dtype=torch.float64), mu[:, None], log_b[:, None])

    def exact(n):
        m, log_std = m_.detach(), log_std_.detach()
        tot = 0.0
        for d in range(2):
            s, b, delta = exp(float(log_std[n, d])), exp(float(log_b[n, d])), float(m[n, d] - mu[n, d])
            fold = s * sqrt(2 / pi) * exp(-delta**2 / (2 * s * s)) + delta * erf(delta / (s * sqrt(2)))
            tot += log(2 * b) - log(s * sqrt(2 * pi * exp(1))) + fold / b
        return tot

    m_, log_std_ = m, log_std
    want = np.array([exact(0), exact(1)])
    kl = one.kl_from((m, log_std))
    np.testing.assert_allclose(kl.detach().numpy(), want, rtol=1e-9)
    np.testing.assert_allclose(one.kl_from((m, log_std), samples=1 << 18).detach().numpy(), want, rtol=0.01)
    kl.sum().backward()
    assert torch.isfinite(m.grad).all() and torch.isfinite(log_std.grad).all()
    assert float(m.grad.abs().min()) > 0 and float(log_std.grad.abs().min()) > 0
    # two components 4 apart: under one of them the bound is tight, between them it stays above
    two = LaplaceMixture(torch.zeros(2, 2, dtype=torch.float64), torch.tensor([[[-2.0, 0.0], [2.0, 0.0]]] * 2,
                         dtype=torch.float64), torch.full((2, 2, 2), -1.0, dtype=torch.float64))
    g = (torch.tensor([[-2.0, 0.0], [0.0, 0.0]], dtype=torch.float64), torch.full((2, 2), -1.5, dtype=torch.float64))
    bound, mc = two.kl_from(g), two.kl_from(g, samples=1 << 18)
    print(f"\nKL bound vs Monte Carlo: under a component {float(bound[0]):.4f} / {float(mc[0]):.4f}, "
          f"between two {float(bound[1]):.4f} / {float(mc[1]):.4f}")
    assert abs(float(bound[0] - mc[0])) < 0.01
    assert float(bound[1]) > float(mc[1]) - 0.01


@pytest.mark.slow
def test_continuous_head_memorises_a_tiny_dataset(wm_cfg):
    cfg = _cont_cfg(wm_cfg)
    data = _collect([generate_scene("merge", 3), generate_scene("t_junction", 4)], cfg)
    assert data["target"].dtype.is_floating_point and data["target"].shape[1] == 2
    keep = torch.randperm(data["target"].shape[0], generator=torch.Generator().manual_seed(0))[:128]
    data = {k: (v[keep] if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    torch.manual_seed(0)
    model = WorldModel(hidden=32, heads=4, partner_k=data["layout"][0], road_k=data["layout"][1],
                       action_space="continuous", mixtures=4)
    before = dataset_nll(model, data)
    fit(model, data, steps=600, batch_size=128, lr=3e-3, gen=torch.Generator().manual_seed(0))
    after = dataset_nll(model, data)
    base = baseline_nlls(data, cfg.env, data)  # every baseline is input-blind; fitted on the same set
    blind = min(base["constant_velocity_laplace"], base["constant_velocity_gaussian"], base["marginal"])
    # the lowest NLL the head can reach: every component at its narrowest scale, on the target
    floor = float(torch.log(2 * model.action_scale * np.exp(-4.0)).sum())
    with torch.no_grad():
        mix = model(data["obs"], data["hist"])
        nearest = (mix.loc - data["target"][:, None]).abs().div(model.action_scale).sum(-1).min(-1).values
    print(f"\ncontinuous tiny set: nll {before['nll']:.3f} -> {after['nll']:.3f} (floor {floor:.3f}); "
          f"input-blind {blind:.3f}; accel MAE of the top component {after['mae_accel']:.3f} m/s^2 "
          f"(predicting 0: {float(data['target'][:, 0].abs().mean()):.3f}); nearest component "
          f"{float(nearest.mean()):.4f} of the box")
    assert after["nll"] < blind - 2.0
    assert after["nll"] < floor + 1.5
    assert float(nearest.mean()) < 0.02
    assert after["mae_accel"] < 0.15 * float(data["target"][:, 0].abs().mean())


def _continuous_sim(scenes, cfg, n_ctrl=2):
    from tg_gpudrive.engine.control import control_masks
    from tg_gpudrive.engine.simulator import Simulator

    veh = control_masks(scenes, cfg.env, "vehicles")
    ctrl = [m & (np.cumsum(m) <= n_ctrl) for m in veh]
    return Simulator(scenes, cfg.env, "cpu", controlled=ctrl, background=[v & ~c for v, c in zip(veh, ctrl)])


def test_continuous_driver_writes_finite_in_range_actions(heldout, wm_cfg):
    cfg = _cont_cfg(wm_cfg)
    torch.manual_seed(0)
    model = build_model(dataclasses.replace(cfg, hidden=16))
    with torch.no_grad():  # push the untrained head's locations far outside the box: the driver clips
        model.head[-1].bias[model.mixtures:].fill_(3.0)
    sim = _continuous_sim(heldout[:2], cfg)
    sim.reset()
    drv = WorldModelDriver(model.eval(), rows="background", seed=0)
    box = torch.tensor([cfg.env.max_accel, cfg.env.max_curvature])
    for step in range(5):
        sim.actions.fill_(-7.0)
        drv(sim)
        bg = (sim.background != 0) & (sim.present != 0)
        act = sim.actions[bg][:, :2]
        assert bg.sum() > 5 and torch.isfinite(act).all()
        assert bool((act.abs() <= box + 1e-6).all())
        assert bool((sim.actions[~bg] == -7.0).all())
        if step == 0:
            assert bool((act.abs() >= box - 1e-6).any())  # clipped at the box
        sim.actions[~bg] = 0.0
        sim.step()
        moved = (sim.background != 0) & (sim.alive != 0)
        assert torch.allclose(sim.applied_action[moved][:, :2], act[moved[bg]], atol=1e-6)
    # greedy: the most probable component's location, clipped
    WorldModelDriver(model, rows="background", greedy=True)(sim)
    assert torch.isfinite(sim.actions).all()


def test_temperature_shrinks_the_sampled_spread(heldout, wm_cfg):
    """Hand-checkable: a Laplace(0, b) draw has E|x| = b; at temperature T the scale is b T, so
    E|x| = b T. Two components with weights 1/4, 3/4 at T = 1/2 get weights 1/16 : 9/16, i.e.
    0.1 / 0.9. T = 0 is the most probable component's location, with no randomness."""
    n = 200_000
    b = torch.tensor([0.5, 0.01], dtype=torch.float64)
    one = LaplaceMixture(torch.zeros(n, 1, dtype=torch.float64), torch.zeros(n, 1, 2, dtype=torch.float64),
                         b.log().expand(n, 1, 2))
    for T in (1.0, 0.3, 0.1):
        spread = one.sample(torch.Generator().manual_seed(0), temperature=T).abs().mean(0)
        np.testing.assert_allclose(spread.numpy(), (b * T).numpy(), rtol=0.02)
    two = LaplaceMixture(torch.tensor([0.0, np.log(3.0)], dtype=torch.float64).expand(n, 2),
                         torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64).expand(n, 2, 2),
                         torch.full((n, 2, 2), np.log(0.01), dtype=torch.float64))
    for T, w_right in ((1.0, 0.75), (0.5, 0.9)):
        x = two.sample(torch.Generator().manual_seed(1), temperature=T)
        assert float((x[:, 0] > 0).double().mean()) == pytest.approx(w_right, abs=0.01)
    assert torch.equal(two.sample(temperature=0.0), two.mode_loc())
    with pytest.raises(ValueError):
        two.sample(temperature=-1.0)
    # the driver: continuous defaults to CONTINUOUS_TEMPERATURE, discrete to 1, T = 0 is greedy
    cfg = _cont_cfg(wm_cfg)
    torch.manual_seed(0)
    model = build_model(dataclasses.replace(cfg, hidden=16)).eval()
    assert WorldModelDriver(model).temperature == WorldModelDriver.CONTINUOUS_TEMPERATURE < 1.0
    assert WorldModelDriver(WorldModel(hidden=16)).temperature == 1.0
    spread = {}
    for T in (1.0, 0.1, 0.0):
        sim = _continuous_sim(heldout[:2], cfg)
        sim.reset()
        WorldModelDriver(model, rows="background", temperature=T, seed=0)(sim)
        bg = (sim.background != 0) & (sim.present != 0)
        with torch.no_grad():
            hb = WorldModelDriver(model).history
            hb.sync(sim)
            w, a = bg.nonzero(as_tuple=True)
            mode = model(sim.obs[w, a], hb.features(sim)[w, a]).mode_loc()
        box = torch.tensor([cfg.env.max_accel, cfg.env.max_curvature])
        spread[T] = float(((sim.actions[bg][:, :2] - mode.clamp(-box, box)) / box).abs().mean())
    print(f"\ndriver spread around the mode (box units): T=1 {spread[1.0]:.4f}, T=0.1 {spread[0.1]:.4f}, "
          f"T=0 {spread[0.0]:.2e}")
    assert spread[0.0] < 1e-6 and spread[0.1] < 0.5 * spread[1.0]


def test_continuous_magnet_kl_is_the_mixture_estimate(wm_cfg, tmp_path):
    from tg_gpudrive.learn.train import Trainer

    cfg_wm = _cont_cfg(wm_cfg)
    torch.manual_seed(0)
    model = build_model(dataclasses.replace(cfg_wm, hidden=16))
    save_world_model(model, tmp_path / "wm.pt", cfg_wm.env)
    base = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    cfg = dataclasses.replace(base, env=dataclasses.replace(base.env, action_space="continuous"), num_worlds=2,
                              num_scenes=2, rollout_steps=4, updates=1, epochs=1, minibatches=1, hidden=32,
                              quantiles=8, out_dir=str(tmp_path / "run"), prior="world_model",
                              prior_model=str(tmp_path / "wm.pt"))
    tr = Trainer(cfg, progress=False)
    assert isinstance(tr.prior, WorldModelPrior) and not tr.prior.model.discrete
    actor0 = copy.deepcopy(tr.actor.state_dict())
    buf, _ = tr.collect()
    assert buf["prior"].shape[-1] == tr.prior.context_dim
    kl_reported = tr.learn(buf)["kl/prior"]
    tr.actor.load_state_dict(actor0)
    m = buf["mask"]
    with torch.no_grad():
        out = tr.actor(buf["obs"][m], m.nonzero()[:, 2])
        mix = tr.prior.distribution(buf["prior"][m], buf["obs"][m])
        want = float(mix.kl_from(out).mean())
        moment = float(tr.head.kl(out, tuple(mix)).mean())  # what a Gaussian-only KL would give
    print(f"\ncontinuous magnet KL: reported {kl_reported:.3f}, mixture estimate {want:.3f}, "
          f"moment-matched Gaussian {moment:.3f}")
    assert isinstance(mix, LaplaceMixture) and np.isfinite(kl_reported)
    assert kl_reported == pytest.approx(want, rel=1e-4, abs=1e-5)
    assert abs(want - moment) > 1e-3


# ------------------------------------------------------------------ closed loop
def test_corrective_target_steers_back_to_the_log():
    """Hand-made: the log runs along +x at 10 m/s (1 m per 0.1 s step) and is at x = 10 m now. An
    agent 2 m to its left (right) turns right (left), one behind speeds up, one ahead slows down
    and, however far ahead, keeps its course instead of turning back to the logged position; one on
    the log holds course and speed."""
    T, t = 40, 10
    xs = torch.arange(T, dtype=torch.float32)
    log_pos = torch.stack([xs, torch.zeros(T)], -1)[None, None]  # (1, 1, T, 2)
    log_vel = torch.tensor([10.0, 0.0]).expand(1, 1, T, 2)
    cases = {"left": (10.0, 2.0), "right": (10.0, -2.0), "behind": (7.0, 0.0), "ahead": (13.0, 0.0),
             "far_ahead": (18.0, 0.0), "on": (10.0, 0.0)}
    n = len(cases)
    pos = torch.tensor(list(cases.values()))[None]  # (1, n, 2): one world, n agents sharing the log
    tgt = corrective_from_log(pos, torch.zeros(1, n), torch.tensor([10.0, 0.0]).expand(1, n, 2),
                              torch.tensor([t]), log_pos.expand(1, n, T, 2), torch.zeros(1, n, T),
                              log_vel.expand(1, n, T, 2), torch.ones(1, n, T, dtype=torch.bool), dt=0.1,
                              cfg=EngineConfig())
    got = {name: tuple(tgt.action[0, i].tolist()) for i, name in enumerate(cases)}
    assert bool(tgt.valid.all())
    assert got["left"][1] < -0.02 and got["right"][1] > 0.02
    assert got["left"][1] == pytest.approx(-got["right"][1])
    assert got["behind"][0] > 0.5 and got["ahead"][0] < -0.5 and got["far_ahead"][0] < got["ahead"][0]
    assert abs(got["ahead"][1]) < 1e-6 and abs(got["far_ahead"][1]) < 1e-6
    assert abs(got["on"][0]) < 1e-4 and abs(got["on"][1]) < 1e-6
    cfg = EngineConfig()
    centre = 3 * cfg.curvature_bins + 6  # the no-op bin
    idx = tgt.index[0].tolist()
    assert idx[-1] == centre
    assert idx[0] % cfg.curvature_bins < 6 < idx[1] % cfg.curvature_bins


def test_corrective_target_recovers_a_displaced_vehicle(heldout, wm_cfg):
    """In the engine: on the log the labels are the inverse of the logged motion itself, and a
    vehicle pushed 1.5 m sideways is steered back by them."""

    from tg_gpudrive.engine.simulator import Simulator
    from tg_gpudrive.worldmodel.data import full_horizon_env

    cfg = _cont_cfg(wm_cfg)
    sim = Simulator(heldout[:1], full_horizon_env(cfg.env), "cpu")
    sim.reset()
    log_pos, log_yaw = sim.slot_log("log_pos"), sim.slot_log("log_yaw")
    log_speed = sim.slot_log("log_vel").norm(dim=-1)
    t = int(sim.world_step[0])
    tgt = corrective_target(sim)
    v = tgt.valid & (sim.integrated != 0) & (sim.speed > 1.0)
    accel = (log_speed[:, :, t + 1] - log_speed[:, :, t]) / sim.model.dt
    arc = log_speed[:, :, t] * sim.model.dt + 0.5 * accel * sim.model.dt**2
    kappa = torch.remainder(log_yaw[:, :, t + 1] - log_yaw[:, :, t] + np.pi, 2 * np.pi) - np.pi
    want = torch.stack([accel, (kappa / arc).clamp(-0.3, 0.3)], -1)
    assert int(v.sum()) >= 4
    torch.testing.assert_close(tgt.action[v], want[v], atol=2e-3, rtol=0.05)
    ctrl = (sim.integrated[0] != 0) & (sim.speed[0] > 3.0)
    i = int(ctrl.nonzero()[0])
    yaw0 = float(sim.yaw[0, i])
    left = torch.tensor([-np.sin(yaw0), np.cos(yaw0)], dtype=torch.float32)
    sim.pos[0, i] += 1.5 * left  # the State itself: a lateral error the log never had
    tgt = corrective_target(sim)
    assert bool(tgt.valid[0, i]) and float(tgt.action[0, i, 1]) < 0  # turns right, back towards the log

    def lateral() -> float:
        t = int(sim.world_step[0])
        d = sim.pos[0, i] - log_pos[0, i, t]
        y = float(sim.yaw[0, i])
        return float(-np.sin(y) * d[0] + np.cos(y) * d[1])

    start = lateral()
    for _ in range(30):
        sim.step(corrective_target(sim).action)
    # critically damped at W_LAT = 1.5 rad/s: (1 + 4.5) exp(-4.5) of the offset is left after 3 s
    print(f"\ncorrective target: lateral offset {start:.2f} m -> {lateral():.2f} m after 3 s")
    assert start > 1.4 and abs(lateral()) < 0.4


def test_closed_loop_finetuning_runs_and_logs(shipped, wm_cfg, tmp_path):
    import csv
    import json

    arch = {k: shipped.hparams[k] for k in ("hidden", "heads", "history", "max_partners", "max_roads")}
    cfg = dataclasses.replace(wm_cfg, num_scenes=2, val_scenes=1, num_worlds=2, steps=0, init_model=str(SHIPPED),
                              batch_size=64, **arch, closed_loop_steps=4, closed_loop_rounds=2, closed_loop_horizon=12,
                              out_dir=str(tmp_path))
    res = train_world_model(cfg, progress=False)
    rows = list(csv.DictReader((tmp_path / "closed_loop.csv").open()))
    assert [int(r["round"]) for r in rows] == [1, 2] and int(rows[-1]["step"]) == 4
    assert int(rows[1]["dataset_samples"]) > int(rows[0]["dataset_samples"]) > int(rows[0]["visited_samples"]) > 0
    for r in rows:
        assert all(np.isfinite(float(r[k])) for k in ("train_nll", "visited_nll_before", "visited_nll"))
        assert 0.0 <= float(r["rollout_deviation_m"]) < math.inf  # a distance, not NaN or inf
    summary = json.loads((tmp_path / "closed_loop.json").read_text())
    assert set(summary["val_background_before"]) == {"vehicles", "collision_rate", "offroad_rate"}
    assert summary == json.loads(json.dumps(res["closed_loop"]))
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ck["closed_loop_done"]
    tuned = load_world_model(tmp_path / "model.pt")
    changed = [k for k, v in tuned.state_dict().items() if not torch.equal(v, shipped.state_dict()[k])]
    assert changed  # the fine-tuning steps moved the weights
    # a resumed, finished run does not repeat the phase
    again = train_world_model(cfg, resume=tmp_path, progress=False)
    assert again["closed_loop"] == "done before the resume"


def test_closed_loop_keeps_each_finished_round(shipped, wm_cfg, tmp_path, monkeypatch):
    """A run stopped in its second round (a time limit) leaves model.pt with the first round's weights."""
    import tg_gpudrive.worldmodel.train as wm_train

    arch = {k: shipped.hparams[k] for k in ("hidden", "heads", "history", "max_partners", "max_roads")}
    cfg = dataclasses.replace(wm_cfg, num_scenes=2, val_scenes=0, num_worlds=2, steps=0, init_model=str(SHIPPED),
                              batch_size=64, **arch, closed_loop_steps=4, closed_loop_rounds=2, closed_loop_horizon=12,
                              out_dir=str(tmp_path))
    calls = []
    real = wm_train.closed_loop_samples

    def stop_in_round_two(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # what a timeout's signal does between rounds
        return real(*a, **k)

    monkeypatch.setattr(wm_train, "closed_loop_samples", stop_in_round_two)
    with pytest.raises(KeyboardInterrupt):
        train_world_model(cfg, progress=False)
    saved = torch.load(tmp_path / "model.pt", weights_only=False)
    assert saved["closed_loop_round"] == 1 and saved["step"] == 2
    tuned = load_world_model(tmp_path / "model.pt")
    assert any(not torch.equal(v, shipped.state_dict()[k]) for k, v in tuned.state_dict().items())


def test_shipped_continuous_model_drives_traffic_within_issue_12s_bar(heldout, wm_cfg):
    """The packaged continuous model (GPU: teacher forcing, then 9 closed-loop rounds at T = 0.1) drives
    every vehicle of six held-out scenes (75) for a full episode: measured 0 / 0 against the expert's
    0 / 0 (512 held-out scenes on the GPU: 0.009 / 0.001). Its predecessor with 2 rounds (not packaged)
    measured 0.053 / 0.120 here. `load_shipped` picks it for a continuous simulator."""
    from tg_gpudrive.engine.simulator import Simulator
    from tg_gpudrive.worldmodel.prior import load_shipped

    env = dataclasses.replace(wm_cfg.env, action_space="continuous")
    model = load_world_model("shipped_continuous")
    assert not model.discrete
    wm, ex = _background(model, heldout, env, None)
    assert wm["collision_rate"] - ex["collision_rate"] <= 0.02
    assert wm["offroad_rate"] - ex["offroad_rate"] <= 0.02
    assert not load_shipped(Simulator(heldout[:1], env, "cpu")).discrete
    assert load_shipped(Simulator(heldout[:1], wm_cfg.env, "cpu")).discrete


def test_samples_of_dense_real_scenes_leave_no_agent_out(wm_cfg):
    """On a real WOMD scene with more agents than env.max_agents, the teacher-forced and closed-loop samples
    are those of worlds sized for every agent: the parked cars and pedestrians beyond the slot count stay
    in the scene, so the observed partners are the same."""
    from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
    from tg_gpudrive.worldmodel.closed_loop import closed_loop_samples

    scene = load_gpudrive_json(sorted((Path(__file__).parent / "data").glob("womd_*.json"))[0])
    small = dataclasses.replace(wm_cfg.env, max_agents=4)
    assert scene.num_agents > small.max_agents
    big = dataclasses.replace(wm_cfg.env, max_agents=scene.num_agents)
    taught = [_collect([scene], dataclasses.replace(wm_cfg, env=env))["obs"] for env in (small, big)]
    assert taught[0].shape[0] > 0 and torch.equal(taught[0], taught[1])
    model = WorldModel(hidden=16, heads=2, partner_k=min(small.partner_k, wm_cfg.max_partners),
                       road_k=min(small.road_k, wm_cfg.max_roads), history=wm_cfg.history)
    loop = [closed_loop_samples(model, [scene], env, horizon=5, history=wm_cfg.history, max_partners=wm_cfg.max_partners,
                                max_roads=wm_cfg.max_roads)[0]["obs"] for env in (small, big)]
    assert loop[0].shape[0] > 0 and torch.equal(loop[0], loop[1])
