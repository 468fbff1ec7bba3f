"""The rollout collector and the CCE-MAPPO update on their own, without a Trainer: a rollout of two
CPU worlds has the documented shapes and masks, and one update moves the weights and reports finite
numbers (or stops with NonFinite on a NaN reward)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch._dynamo

from tg_gpudrive.agents.policy import PolicyHead, build_models
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HIST_DIM, HistoryBuffer
from tg_gpudrive.learn import losses as L
from tg_gpudrive.learn.collector import Networks, NonFinite, Rollout, RolloutCollector
from tg_gpudrive.learn.train import make_prior
from tg_gpudrive.learn.update import advantages, flatten, make_optimizer, ppo_update

from test_train import rows, tiny

CASES = {"discrete": dict(), "continuous+history": dict(prior="expert", actor_history=3)}


def _setup(tmp_path, case: str, device: str = "cpu", **kw):
    """A 2-world simulator, the networks, optimiser and multipliers of a tiny run (`kw` on its config), and
    its collector."""
    cfg = tiny(tmp_path, **CASES[case], **kw)
    if case.startswith("continuous"):
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, action_space="continuous"))
    torch.manual_seed(0)
    src = resolve_scenes(cfg.scenes, n=cfg.num_worlds, seed=cfg.seed)
    sim = Simulator([src.get(i) for i in range(cfg.num_worlds)], cfg.env, device)
    actor, critic = build_models(cfg, sim, device)
    nets = Networks(actor, critic, PolicyHead(cfg.env.discrete))
    gen = torch.Generator(device=device).manual_seed(0)
    hist = HistoryBuffer(cfg.actor_history) if cfg.actor_history else None
    prior = make_prior(cfg, sim)
    sim.reset()
    collector = RolloutCollector(cfg, sim, nets, prior, gen, device, hist)
    opt = make_optimizer(cfg, [*actor.parameters(), *critic.parameters()], device == "cuda")
    lagrange = L.LagrangeMultiplier(cfg.lambda_init, cfg.lambda_lr, (cfg.env.max_agents,)).to(device)
    return cfg, sim, nets, collector, opt, lagrange, gen, prior


@pytest.mark.parametrize("case", CASES)
def test_collector_fills_a_rollout_of_the_documented_shapes(tmp_path, case):
    cfg, sim, nets, collector, *_ = _setup(tmp_path, case)
    batch = collector.collect()
    T, W, C = cfg.rollout_steps, cfg.num_worlds, max(sim.max_controlled, 1)
    assert isinstance(batch, Rollout) and batch.mask.dtype == torch.bool
    assert batch.obs.shape == (T, W, C, sim.obs_dim)
    assert batch.value.shape == (T + 1, W, C) and batch.quant.shape == (T + 1, W, C, cfg.quantiles)
    for x in (batch.logp, batch.reward, batch.cost, batch.done):
        assert x.shape == (T, W, C)
    m = batch.mask
    assert bool(m[0].any())  # agents acted at the first step
    assert torch.isfinite(batch.logp[m]).all() and set(batch.done.unique().tolist()) <= {0.0, 1.0}
    if nets.head.discrete:  # the no-op where an agent did not act; the magnet's logits on its live rows
        assert (batch.act[~m] == cfg.env.noop_index).all()
        assert batch.prior.shape == (T, W, C, sim.num_actions) and batch.old.shape == (T, W, C, sim.num_actions)
        assert (batch.logp[m] <= 0).all()
    else:
        assert batch.act.shape == (T, W, C, cfg.env.act_dim) and (batch.act[~m] == 0).all()
        assert batch.prior.shape[:3] == (T, W, C) and batch.prior.shape[-1] == 4  # the expert's context
        assert all(o.shape == batch.act.shape for o in batch.old)
    assert (batch.hist is None) == (cfg.actor_history == 0)
    if batch.hist is not None:
        assert batch.hist.shape == (T, W, C, cfg.actor_history, HIST_DIM)
    st = batch.stats
    assert st["terms"].shape == (len(sim.reward_term_names),) and float(st["alive"]) > 0
    assert float(st["episodes"]) >= float(st["goal"]) >= 0
    # by name, as the scripts read it, and back
    assert batch["mask"] is batch.mask and ("hist" in batch) == (batch.hist is not None)
    again = Rollout.of(dict(batch, reward=batch.reward * 2))
    assert torch.equal(again.reward, 2 * batch.reward) and again.obs is batch.obs
    groups = flatten(batch, advantages(cfg, batch), nets.head.discrete)
    assert groups.obs.shape == (T * W, C, sim.obs_dim) and groups.q_target.shape[:2] == (T * W, C)


def test_the_cost_critic_loss_takes_its_huber_threshold_from_cost_kappa(tmp_path, monkeypatch):
    from tg_gpudrive.learn.update import minibatch_loss

    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, "discrete")
    batch = collector.collect()
    groups = flatten(batch, advantages(cfg, batch), nets.head.discrete)
    idx, lam = torch.arange(groups.mask.shape[0]), torch.zeros(groups.mask.shape[1])
    real, seen = L.quantile_huber_loss, []

    def spy(*args, kappa, **kwargs):
        seen.append(kappa)
        return real(*args, kappa=kappa, **kwargs)

    monkeypatch.setattr(L, "quantile_huber_loss", spy)
    parts = {k: minibatch_loss(dataclasses.replace(cfg, cost_kappa=k), groups, idx, lam, nets, prior)[1]
             for k in (0.0, 1.0)}
    assert seen == [0.0, 1.0]
    assert float(parts[0.0]["loss/cost_quantile"]) != float(parts[1.0]["loss/cost_quantile"])
    torch.testing.assert_close(parts[0.0]["loss/value"], parts[1.0]["loss/value"])


@pytest.mark.parametrize("case", CASES)
def test_one_update_moves_the_weights_and_reports_finite_numbers(tmp_path, case):
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, case)
    batch = collector.collect()
    before = [p.detach().clone() for p in (*nets.actor.parameters(), *nets.critic.parameters())]
    n_actor = len(list(nets.actor.parameters()))
    budget = torch.tensor(0.0)  # any cost is over it: lambda rises on the slots that had agents
    lam0 = lagrange.value.detach().clone()
    out = ppo_update(cfg, batch, nets, opt, lagrange, budget, gen, prior)
    want = {"loss/policy", "loss/value", "loss/cost_quantile", "kl/prior", "kl/prev", "entropy", "clip_frac",
            "cvar", "cost_to_go", "constraint", "lambda", "lambda_max", "cost_budget"}
    assert set(out) == want and all(math.isfinite(v) for v in out.values()), out
    after = [p.detach() for p in (*nets.actor.parameters(), *nets.critic.parameters())]
    moved = [not torch.equal(a, b) for a, b in zip(before, after)]
    assert any(moved[:n_actor]) and any(moved[n_actor:])
    seen = batch.mask.any((0, 1))
    assert (lagrange.value[:len(seen)][seen] >= lam0[:len(seen)][seen]).all()


def test_a_nan_reward_stops_the_update_with_nonfinite(tmp_path):
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, "discrete")
    batch = collector.collect()
    batch.reward[0, 0, 0] = float("nan")
    with pytest.raises(NonFinite, match="non-finite loss") as e:
        ppo_update(cfg, batch, nets, opt, lagrange, torch.tensor(1.0), gen, prior)
    assert e.value.what == "non-finite loss" and "mean policy" in e.value.detail


def test_magnet_fraction_computes_the_prior_on_that_share_of_live_rows_and_weighs_their_kl(tmp_path):
    """magnet_fraction 0.25: per step, ceil(n / 4) of the n live rows get the prior's logits (those of the
    full computation) and weight 4, the other rows weight 0, so their stored logits, whatever they hold,
    do not reach the loss."""
    CASES["quarter"] = dict(magnet_fraction=0.25)
    try:
        cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path / "q", "quarter")
        full = _setup(tmp_path / "f", "discrete")[3]
    finally:
        del CASES["quarter"]
    batch, ref = collector.collect(), full.collect()
    assert ref.prior_weight is None and batch.prior_weight.shape == batch.mask.shape
    for t in range(cfg.rollout_steps):
        live = int(batch.mask[t].sum())
        w = batch.prior_weight[t]
        assert int((w > 0).sum()) == math.ceil(0.25 * live) and set(w.unique().tolist()) <= {0.0, 4.0}
        assert bool(batch.mask[t][w > 0].all())  # only live rows are picked
    picked = batch.prior_weight[0] > 0  # step 0: the same state in both rollouts
    torch.testing.assert_close(batch.prior[0][picked], ref.prior[0][picked])
    # the loss reads the picked rows only
    groups = flatten(batch, advantages(cfg, batch), True)
    idx = torch.arange(groups.mask.shape[0])
    lam = torch.zeros(cfg.env.max_agents)
    from tg_gpudrive.learn.update import minibatch_loss
    loss, parts = minibatch_loss(cfg, groups, idx, lam[: groups.mask.shape[1]], nets, prior)
    junk = dataclasses.replace(groups, prior=torch.where((groups.prior_weight > 0)[..., None], groups.prior,
                                                         torch.full_like(groups.prior, 30.0).index_fill_(-1, torch.tensor([0]), -30.0)))
    loss2, parts2 = minibatch_loss(cfg, junk, idx, lam[: groups.mask.shape[1]], nets, prior)
    assert float(parts2["kl/prior"]) == pytest.approx(float(parts["kl/prior"]), rel=1e-6) and float(parts["kl/prior"]) > 0
    # and they weigh 1 / fraction: the mean weighted KL estimates the mean KL over all live rows
    g, c = groups.mask.nonzero(as_tuple=True)
    assert float(groups.prior_weight[g, c].mean()) == pytest.approx(1.0, abs=0.25)


CUDA_ONLY = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("fraction, compiled, device", [
    (1.0, False, "cpu"), (0.25, False, "cpu"),
    pytest.param(0.25, True, "cpu", marks=pytest.mark.slow, id="0.25-compile_rollout-cpu"),
    pytest.param(0.25, True, "cuda", marks=CUDA_ONLY, id="0.25-compile_rollout-cuda")])
def test_values_and_magnet_after_the_rollout_equal_those_of_each_step(tmp_path, fraction, compiled, device,
                                                                      monkeypatch):
    """The critic's values and the magnet's logits, computed from the stored observations and contexts
    after the rollout (in batches cut small here; with compile_rollout through torch.compile, the batches'
    row counts a dynamic size), equal those of the state at each step: a second simulator replays the
    rollout's actions, and at every step the critic and the prior run on its live state, eagerly."""
    import tg_gpudrive.learn.collector as collector_mod
    monkeypatch.setattr(collector_mod, "CRITIC_SLOTS", 3 * 16)  # a few steps per critic call
    monkeypatch.setattr(collector_mod, "MAGNET_ROWS", 7)
    CASES["replay"] = dict(magnet_fraction=fraction)
    try:
        # float32 throughout: under amp the GPU's rollout stores its observations in bf16, the replay reads them
        # in float32, and the trained magnet's logits part by more than the passes do
        cfg, sim, nets, collector, *_, prior = _setup(tmp_path / "a", "replay", device, compile_rollout=compiled,
                                                      amp=False)
        _, sim2, _, _, *_, prior2 = _setup(tmp_path / "b", "replay", device, amp=False)
    finally:
        del CASES["replay"]
    torch._dynamo.utils.counters.clear()
    batch = collector.collect()
    if compiled:  # both passes went through the compiler
        assert collector._compiled.keys() == {"critic", "magnet"}
        assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 2
    T, C = cfg.rollout_steps, batch.mask.shape[-1]
    take = batch.mask if batch.prior_weight is None else batch.prior_weight > 0
    tol = dict(rtol=1e-5, atol=1e-5) if device == "cpu" else dict(rtol=1e-4, atol=1e-4)  # the GPU's own kernels
    for t in range(T + 1):
        obs, mask = sim2.obs[:, :C], sim2.active[:, :C] != 0
        value, quant = nets.critic(obs, mask)
        torch.testing.assert_close(batch.value[t][mask], value[mask], **tol)
        torch.testing.assert_close(batch.quant[t][mask], quant[mask], **tol)
        # the heads run on the live rows alone: the others hold 0, which no target reads, since a live row
        # that does not end its episode is live at the next step (what the bootstrap reads)
        assert not batch.value[t][~mask].any() and not batch.quant[t][~mask].any()
        if t > 0:
            assert not (batch.mask[t - 1] & (batch.done[t - 1] == 0) & ~mask).any()
        if t == T:
            break
        assert torch.equal(batch.mask[t], mask)
        ctx = prior2.context(sim2, C)
        torch.testing.assert_close(batch.prior[t][take[t]], prior2.distribution(ctx[take[t]], obs[take[t]]), **tol)
        sim2.actions_index[:, :C] = batch.act[t].to(torch.int32)
        sim2.step()
    assert int(take.sum()) > 0


def test_a_pass_whose_compilation_fails_runs_as_it_is_and_says_so_once(caplog):
    """compile_rollout's passes (compiling.Compiled): a compiler failure is logged once and the pass runs without
    compilation from then on, with its own results; an error of the pass itself, or the device running out of
    memory, still reaches the caller."""
    from tg_gpudrive.learn.compiling import Compiled

    def double(x):
        if x.shape[0] == 0:
            raise ValueError("no rows")
        return 2 * x

    def compiler_failure(*args, **kwargs):
        raise RuntimeError("InductorError: AssertionError\nits stack")

    p = Compiled(double, "test pass")
    p.compiled = compiler_failure
    with caplog.at_level("WARNING"):
        for _ in range(3):
            torch.testing.assert_close(p(torch.ones(4)), torch.full((4,), 2.0))
    warned = [r.getMessage() for r in caplog.records if "could not be compiled" in r.getMessage()]
    assert len(warned) == 1 and "test pass" in warned[0] and "InductorError: AssertionError" in warned[0]
    assert p.compiled is None
    with pytest.raises(ValueError, match="no rows"):
        p(torch.ones(0))

    def out_of_memory(*args, **kwargs):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory")

    q = Compiled(double, "test pass")
    q.compiled = out_of_memory  # the device's limit is no compiler failure: it reaches the caller, nothing falls back
    with pytest.raises(torch.cuda.OutOfMemoryError):
        q(torch.ones(4))
    assert q.compiled is out_of_memory


@pytest.mark.parametrize("groups, mb", [(10, 3), (12, 4), (5, 8)])
def test_epoch_live_rows_are_each_minibatchs_own(groups, mb):
    """The live rows found once an epoch are, minibatch by minibatch, those its own mask gives (uneven last
    minibatch, empty ones and a single short one included)."""
    from tg_gpudrive.learn.update import epoch_live_rows
    mask = torch.rand(groups, 4, generator=torch.Generator().manual_seed(groups)) < 0.4
    mask[:mb] = False  # the first minibatch has no live row
    live = epoch_live_rows(mask, mb)
    assert len(live) == len(range(0, groups, mb))
    for (g, c), s in zip(live, range(0, groups, mb)):
        ref_g, ref_c = mask[s:s + mb].nonzero(as_tuple=True)
        assert torch.equal(g, ref_g) and torch.equal(c, ref_c)
    assert len(live[0][0]) == 0


def test_magnet_fraction_is_for_the_discrete_magnet():
    from tg_gpudrive.config import ConfigError, EngineConfig, TrainConfig

    with pytest.raises(ConfigError, match="magnet_fraction"):
        TrainConfig(magnet_fraction=0.5, env=EngineConfig(action_space="continuous"))
    with pytest.raises(ConfigError, match="magnet_fraction"):
        TrainConfig(magnet_fraction=0.0)


def test_lambda_max_bounds_the_trainers_multipliers(tmp_path):
    """lambda_max > 0 builds the trainer's multipliers with that upper bound; 0 leaves them unbounded; a start
    above the bound, or a negative bound, is a config error naming the field."""
    from tg_gpudrive.config import ConfigError, TrainConfig
    from tg_gpudrive.learn.train import Trainer

    capped = Trainer(tiny(tmp_path / "capped", lambda_max=1.5, lambda_init=1.0), progress=False)
    assert capped.lagrange.upper == 1.5
    capped.lagrange.update(torch.full_like(capped.lagrange.value, 1e3), 0.0)
    assert float(capped.lagrange.value.max()) == 1.5
    assert math.isinf(Trainer(tiny(tmp_path / "free"), progress=False).lagrange.upper)
    with pytest.raises(ConfigError, match="lambda_init: must not exceed lambda_max"):
        TrainConfig(lambda_max=1.0, lambda_init=2.0)
    with pytest.raises(ConfigError, match="lambda_max"):
        TrainConfig(lambda_max=-1.0)


@pytest.mark.parametrize("per_vehicle", [False, True], ids=["per-slot", "per-vehicle"])
def test_lambda_warmup_holds_the_multipliers_while_the_cost_critic_fits(tmp_path, per_vehicle):
    """lambda_warmup 2: the first two updates leave the multipliers at lambda_init (the rows' lambda), the third
    steps them as a run without the warm-up steps its first; a negative warm-up is a config error naming it."""
    from tg_gpudrive.config import ConfigError, TrainConfig
    from tg_gpudrive.learn.train import Trainer

    sets = dict(lambda_init=0.5, lambda_lr=0.5, cost_limit_mode="absolute", cost_limit=0.0, updates=3,
                lambda_per_vehicle=per_vehicle)
    lams = {}
    for warm in (0, 2):
        out = tmp_path / f"w{warm}"
        Trainer(tiny(out, lambda_warmup=warm, **sets), out, progress=False).train()
        lams[warm] = [float(r["lambda"]) for r in rows(out)]
    assert lams[2][:2] == [0.5, 0.5] and lams[2][2] > 0.5
    assert lams[0][0] > 0.5  # without it, the first update already steps them
    with pytest.raises(ConfigError, match="lambda_warmup"):
        TrainConfig(lambda_warmup=-1)


def test_cost_advantage_names_a_rule():
    from tg_gpudrive.config import ConfigError, TrainConfig

    assert TrainConfig(cost_advantage="tail").cost_advantage == "tail"
    with pytest.raises(ConfigError, match="cost_advantage: expected gae or tail, got 'cvar'"):
        TrainConfig(cost_advantage="cvar")


@pytest.mark.parametrize("compiled, device, rule", [
    (False, "cpu", "gae"), (False, "cpu", "tail"),
    pytest.param(True, "cpu", "gae", marks=pytest.mark.slow, id="compile_rollout-cpu"),
    pytest.param(True, "cpu", "tail", marks=pytest.mark.slow, id="compile_rollout-cpu-tail"),
    pytest.param(True, "cuda", "gae", marks=CUDA_ONLY, id="compile_rollout-cuda"),
    pytest.param(True, "cuda", "tail", marks=CUDA_ONLY, id="compile_rollout-cuda-tail")])
def test_advantages_over_the_acting_columns_equal_those_over_every_slot(tmp_path, compiled, device, rule):
    """update.advantages computes its targets on the (world, slot) columns that act at some step: there they
    equal the targets of the whole (T, W, C) block, computed as losses.py states them (the quantiles sorted
    inside CVaR), and a column that never acts holds zeros. The critic's quantiles come sorted, which lets
    CVaR skip its sort. With compile_rollout the column targets go through torch.compile. The cost advantage
    is the one cost_advantage names."""
    cfg, sim, nets, collector, *_ = _setup(tmp_path, "discrete", device, num_worlds=3)  # a world with fewer agents
    batch = collector.collect()
    assert bool((batch.quant.diff(dim=-1) >= 0).all())
    with torch.no_grad():  # a cost to propagate, and a critic with spread
        noise = torch.rand(batch.cost.shape, generator=torch.Generator().manual_seed(3)).to(device)
        batch.cost.copy_(noise * batch.mask)
        batch.quant.add_(torch.linspace(0.0, 4.0, cfg.quantiles, device=device))
    cfg = dataclasses.replace(cfg, cost_nstep=3, compile_rollout=compiled, cost_advantage=rule, alpha=0.75)
    torch._dynamo.utils.counters.clear()
    tg = advantages(cfg, batch)
    assert (torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 1) == compiled
    q = batch.quant.clamp(0.0, L.cost_to_go_bound(cfg.gamma))
    adv_r, ret_r = L.gae(batch.reward, batch.value, batch.done, cfg.gamma, cfg.gae_lambda)
    adv_rule = L.cvar_tail_advantage if rule == "tail" else L.cvar_gae
    adv_c, cvar = adv_rule(batch.cost, q, batch.done, cfg.alpha, cfg.gamma, cfg.gae_lambda)
    if rule == "tail":  # it tells the sampled costs apart where the CVaR baseline rule does not
        assert not torch.allclose(adv_c, L.cvar_gae(batch.cost, q, batch.done, cfg.alpha, cfg.gamma,
                                                   cfg.gae_lambda)[0])
    q_target = L.cost_quantile_targets(batch.cost, q, batch.done, cfg.gamma, cfg.cost_nstep)
    acts = batch.mask.any(0)
    assert bool(acts.any()) and not bool(acts.all())  # columns that never act were there
    for got, want in ((tg.adv_r, adv_r), (tg.ret_r, ret_r), (tg.adv_c, adv_c), (tg.cvar, cvar),
                      (tg.q_target, q_target), (tg.ctg_mean, q.mean(-1))):
        assert got.shape == want.shape
        torch.testing.assert_close(got[:, acts], want[:, acts])
        assert not got[:, ~acts].any()


def test_lambda_on_mean_steps_the_multipliers_on_the_expected_cost_to_go(tmp_path):
    """lambda_on mean (TrafficGamer's Algorithm 1): each slot's multiplier moves by lambda_lr times the mean
    over its live states of E[Z(o)] (the quantiles' mean, inside the cost-to-go's support) minus the
    budget; lambda_on cvar uses CVaR_alpha(Z(o)), which is larger."""
    from tg_gpudrive.learn.update import lagrange_step

    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, "discrete")
    batch = collector.collect()
    with torch.no_grad():  # a cost critic with spread: CVaR and mean differ
        batch.quant.copy_(torch.linspace(0.0, 4.0, cfg.quantiles).expand_as(batch.quant))
    cfg = dataclasses.replace(cfg, lambda_on="mean", alpha=0.5)
    tg = advantages(cfg, batch)
    want_value = batch.quant.clamp(0.0, L.cost_to_go_bound(cfg.gamma)).mean(-1)
    torch.testing.assert_close(tg.ctg_mean, want_value)
    assert torch.equal(tg.constraint(cfg, batch.cost), tg.ctg_mean)
    assert float(tg.cvar.mean()) > float(tg.ctg_mean.mean()) + 0.5
    m = batch.mask
    C = m.shape[-1]
    cnt = m.sum((0, 1))
    jc = (want_value[:-1] * m).sum((0, 1)) / cnt.clamp(min=1)
    budget = torch.tensor(0.5)
    lam0 = lagrange.value.clone()
    lagrange_step(cfg, m, tg.constraint(cfg, batch.cost), lagrange, budget)
    seen = cnt > 0
    want = (lam0[:C] + cfg.lambda_lr * (jc - budget)).clamp(min=0)
    torch.testing.assert_close(lagrange.value[:C][seen], want[seen])
    assert bool(seen.any()) and bool((lagrange.value[:C][seen] > 0).all())


def test_lambda_on_mean_budget_is_one_per_beta_for_every_alpha(tmp_path):
    """With cost_limit_mode logs, lambda_on mean asks the logs' mean cost-to-go as the budget: the same
    at every alpha. lambda_on cvar asks their CVaR_alpha, which grows with alpha."""
    from tg_gpudrive.learn.train import Trainer

    from test_train import tiny

    def budget(**kw):
        cfg = tiny(tmp_path / str(len(kw)) / "_".join(f"{k}{v}" for k, v in kw.items()), cost_limit_mode="logs",
                   cost_limit=1.0, num_worlds=4, **kw)
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=12.0))
        return float(Trainer(cfg, progress=False).budget)

    mean_lo, mean_hi = budget(lambda_on="mean", alpha=0.25), budget(lambda_on="mean", alpha=0.75)
    cvar_lo, cvar_hi = budget(lambda_on="cvar", alpha=0.25), budget(lambda_on="cvar", alpha=0.75)
    assert mean_lo == pytest.approx(mean_hi) and mean_lo > 0
    assert cvar_hi > cvar_lo >= mean_lo


def test_start_budget_is_the_starting_policys_mean_cost_for_every_alpha(tmp_path):
    """cost_limit_mode start asks cost_limit x the starting actor's mean discounted cost-to-go over one
    sampled episode in every world: the same at every alpha, scaled by cost_limit; the run then trains as
    one given that budget as a number."""
    from tg_gpudrive.agents.policy import actor_policy
    from tg_gpudrive.learn.train import Trainer, cost_to_go

    from test_train import rows, tiny

    def trainer(name, **kw):
        cfg = tiny(tmp_path / name, lambda_on="cvar", num_worlds=4, updates=2, **kw)
        return Trainer(dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=12.0)), progress=False)

    lo = trainer("lo", cost_limit_mode="start", cost_limit=1.0, alpha=0.25)
    hi = trainer("hi", cost_limit_mode="start", cost_limit=1.0, alpha=0.75)
    twice = trainer("twice", cost_limit_mode="start", cost_limit=2.0, alpha=0.25)
    fixed = trainer("fixed", cost_limit_mode="absolute", cost_limit=float(lo.budget), alpha=0.25)
    torch.manual_seed(lo.cfg.seed)
    want = cost_to_go(fixed.sim, fixed.cfg.gamma, actor_policy(fixed.actor, fixed.sim)).mean()
    fixed.sim.reset()
    assert float(lo.budget) == pytest.approx(float(want)) and float(want) > 0
    assert float(hi.budget) == pytest.approx(float(lo.budget))
    assert float(twice.budget) == pytest.approx(2 * float(lo.budget))
    lo.train()
    fixed.train()
    learned = [[{k: v for k, v in r.items() if "time" not in k and not k.endswith(("_s", "_per_s"))} for r in rows(p)]
               for p in (tmp_path / "lo", tmp_path / "fixed")]
    assert learned[0] == learned[1]


def test_vehicle_lagrange_step_by_hand():
    """lambda_per_vehicle: worlds 0 and 2 hold scene 0, world 1 scene 1; each (scene, slot) multiplier
    moves by lambda_lr times the mean of the value over that vehicle's live states in all its worlds,
    minus the budget; vehicles without states keep theirs; the actor reads each world's own rows."""
    from tg_gpudrive.config import TrainConfig
    from tg_gpudrive.learn.update import vehicle_lagrange_step

    cfg = TrainConfig(per_agent_lambda=True, lambda_per_vehicle=True, lambda_lr=0.1)
    value = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]],
                          [[7.0, 8.0], [9.0, 10.0], [11.0, 12.0]],
                          [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])  # (T + 1, W, C)
    mask = torch.tensor([[[1, 0], [1, 1], [1, 0]],
                         [[1, 0], [0, 1], [0, 0]]], dtype=torch.bool)  # (T, W, C)
    keys = torch.tensor([0, 1, 0])
    lagrange = L.LagrangeMultiplier(0.2, 0.1, (3, 4))
    lam, seen = vehicle_lagrange_step(cfg, mask, value, lagrange, torch.tensor(2.0), keys)
    assert lam.shape == (3, 2) and bool((lam == 0.2).all())  # the multipliers before the step
    want = torch.full((3, 4), 0.2)
    want[0, 0] = 0.2 + 0.1 * ((1 + 7 + 5) / 3 - 2.0)  # scene 0, slot 0: worlds 0 (t 0, 1) and 2 (t 0)
    want[1, 0] = 0.2 + 0.1 * (3 - 2.0)  # scene 1, slot 0: world 1, t 0
    want[1, 1] = 0.2 + 0.1 * ((4 + 10) / 2 - 2.0)
    torch.testing.assert_close(lagrange.value, want)
    assert seen.tolist() == [[True, False, False, False], [True, True, False, False], [False] * 4]


def test_training_with_a_multiplier_per_vehicle(tmp_path):
    """A run with lambda_per_vehicle keeps a (scenes, slots) table; the vehicles of the scenes its worlds
    held move (the cost fires at beta 12 m against a zero budget), the others stay at lambda_init, and
    the run resumes with its table."""
    from tg_gpudrive.learn.train import Trainer

    from test_train import tiny

    cfg = tiny(tmp_path / "run", lambda_per_vehicle=True, num_scenes=12, num_worlds=2, resample_every=1,
               updates=3, cost_limit_mode="absolute", cost_limit=0.0, lambda_lr=0.5)
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=12.0))
    tr = Trainer(cfg, progress=False)
    tr.train()
    lam = tr.lagrange.value
    assert lam.shape == (12, cfg.env.max_agents)
    moved = (lam > 0).any(1)  # 3 draws of 2 worlds: at most 6 of the 12 scenes were played
    assert 1 <= int(moved.sum()) <= 6 and bool((lam[~moved] == 0).all())
    again = Trainer(dataclasses.replace(cfg, updates=4), resume=tmp_path / "run", progress=False)
    torch.testing.assert_close(again.lagrange.value, lam)


@pytest.mark.parametrize("mode", ["start", "logs"])
def test_cost_limit_beta_measures_the_bar_under_the_reference_beta(tmp_path, mode):
    """cost_limit_beta: a run at beta 3 gets the bar a run at beta 12 measures on the same worlds (the
    starting policy's or the logs' cost under beta 12, a heavier one than its own beta's), while it trains
    under its own beta; an absolute bar with a reference beta is a config error naming the key."""
    from tg_gpudrive.config import ConfigError, TrainConfig
    from tg_gpudrive.learn.train import Trainer

    from test_train import tiny

    def trainer(name, beta, **kw):
        cfg = tiny(tmp_path / name, lambda_on="cvar", num_worlds=4, updates=1, cost_limit_mode=mode,
                   cost_limit=1.0, alpha=0.5, **kw)
        return Trainer(dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=beta)), progress=False)

    ref = trainer("ref", 12.0)
    low = trainer("low", 3.0, cost_limit_beta=12.0)
    own = trainer("own", 3.0)
    assert float(low.budget) == pytest.approx(float(ref.budget)) and float(ref.budget) > 0
    assert float(own.budget) < float(low.budget)
    assert low.sim.model.beta == 3.0 and low.first_worlds is None
    same = trainer("same", 12.0, cost_limit_beta=12.0)
    assert float(same.budget) == pytest.approx(float(ref.budget))
    with pytest.raises(ConfigError, match="cost_limit_beta"):
        TrainConfig(cost_limit_mode="absolute", cost_limit_beta=2.0)


def test_sampled_lambda_steps_on_the_rollouts_cost_rate_not_the_critic():
    """lambda_on sampled: the constraint of a slot is its live steps' mean sampled cost x 1 / (1 - gamma),
    whatever the critic's quantiles say; cvar reads the critic."""
    from tg_gpudrive.config import ConfigError, TrainConfig
    from tg_gpudrive.learn.update import Targets, lagrange_step

    T, W, C = 4, 2, 2
    cfg = dataclasses.replace(TrainConfig(), lambda_on="sampled", lambda_lr=0.5, gamma=0.9,
                              env=dataclasses.replace(TrainConfig().env, max_agents=C))
    cost = torch.tensor([0.1, 0.0, 0.3, 0.0]).reshape(T, 1, 1).expand(T, W, C).clone()
    mask = torch.ones(T, W, C, dtype=torch.bool)
    mask[3] = False  # the last step's 0 is not lived, so the mean is 0.4 / 3 per slot
    high = torch.full((T + 1, W, C), 7.0)  # a critic far above the truth
    tg = Targets(adv_r=None, ret_r=None, adv_c=None, cvar=high, q_target=None, ctg_mean=high)
    value = tg.constraint(cfg, cost)
    assert value.shape == (T + 1, W, C)
    lagrange = L.LagrangeMultiplier(1.0, 0.5, shape=(C,))
    lagrange_step(cfg, mask, value, lagrange, torch.tensor(1.0))
    want = 1.0 + 0.5 * ((0.4 / 3) / (1 - 0.9) - 1.0)
    assert lagrange.value.tolist() == pytest.approx([want, want])
    assert torch.equal(tg.constraint(dataclasses.replace(cfg, lambda_on="cvar"), cost), high)
    with pytest.raises(ConfigError, match="gamma"):
        TrainConfig(lambda_on="sampled", gamma=1.0)


def test_sampled_start_budget_is_the_starting_policys_cost_rate(tmp_path):
    """lambda_on sampled with cost_limit_mode start: the budget is cost_limit x the starting actor's mean
    per-step cost over one sampled episode in every world x 1 / (1 - gamma), the figure lambda is stepped on."""
    from tg_gpudrive.agents.policy import actor_policy
    from tg_gpudrive.learn.train import Trainer, episode_costs

    from test_train import tiny

    def trainer(name, **kw):
        cfg = tiny(tmp_path / name, num_worlds=4, updates=1, lambda_on="sampled", **kw)
        return Trainer(dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=12.0)), progress=False)

    got = trainer("start", cost_limit_mode="start", cost_limit=0.5)
    ref = trainer("ref", cost_limit_mode="absolute", cost_limit=1.0)
    torch.manual_seed(ref.cfg.seed)
    cost, live = episode_costs(ref.sim, actor_policy(ref.actor, ref.sim))
    want = 0.5 * float(cost[live].mean()) / (1 - ref.cfg.gamma)
    assert want > 0 and float(got.budget) == pytest.approx(want, rel=1e-5)


def test_sampled_cvar_steps_each_slot_on_the_tail_of_its_vehicles_cost_rates():
    """lambda_on sampled_cvar: a slot's constraint is the mean of the largest ceil((1 - alpha) x n) of its n
    vehicles' mean sampled cost rates (hand-computed), so a higher alpha reads a heavier tail of the same
    rollout; a slot no vehicle held keeps its multiplier."""
    from tg_gpudrive.config import ConfigError, TrainConfig
    from tg_gpudrive.learn.update import lagrange_step, vehicle_cvar

    T, W, C = 2, 4, 2
    cost = torch.zeros(T, W, C)
    cost[:, :, 0] = torch.tensor([[0.0, 0.2, 0.4, 0.8], [0.0, 0.0, 0.4, 0.4]])  # slot 0 rates 0, .1, .4, .6
    mask = torch.ones(T, W, C, dtype=torch.bool)
    mask[:, :, 1] = False  # slot 1: no vehicle
    mask[1, 3, 0] = False  # vehicle 3 lived one step: its rate is 0.8
    # rates of slot 0: 0, 0.1, 0.4, 0.8; alpha 0.5: top 2 -> 0.6; alpha 0.875: top 1 -> 0.8; alpha 0: all -> 0.325
    for alpha, want in ((0.5, 0.6), (0.875, 0.8), (0.0, 0.325)):
        got = vehicle_cvar(cost, mask, alpha)
        assert got.tolist() == pytest.approx([want, 0.0])
    cfg = dataclasses.replace(TrainConfig(), lambda_on="sampled_cvar", alpha=0.5, lambda_lr=1.0, gamma=0.5,
                              env=dataclasses.replace(TrainConfig().env, max_agents=C))
    value = torch.cat([cost / (1 - cfg.gamma), torch.zeros(1, W, C)])
    lagrange = L.LagrangeMultiplier(1.0, 1.0, shape=(C,))
    lagrange_step(cfg, mask, value, lagrange, torch.tensor(0.5))
    assert lagrange.value.tolist() == pytest.approx([1.0 + 0.6 / 0.5 - 0.5, 1.0])
    with pytest.raises(ConfigError, match="sampled_cvar"):
        TrainConfig(lambda_on="sampled_cvar", lambda_per_vehicle=True)
