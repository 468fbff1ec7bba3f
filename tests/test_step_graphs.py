"""The fixed-shape steps of learn/graphs.py, for the update and for the rollout. The loss over every slot of a
minibatch's groups, dead slots weighted 0, equals the loss over the live rows, gradients included, whatever
the dead slots hold. An update through StepGraphs moves the weights as the eager update does: on the CPU
without graphs, on CUDA replayed from its captured graph (several updates, so replays, short last
minibatches and new rollouts follow a capture). A rollout that acts on every slot (RolloutGraphs) fills the
buffers the live-row rollout fills, on the CPU as it is and on CUDA from its captured steps."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tg_gpudrive.learn import update as update_mod
from tg_gpudrive.learn.graphs import RolloutGraphs, StepGraphs
from tg_gpudrive.learn.update import advantages, flatten, minibatch_loss, padded_rows, ppo_update

from test_learn_collector_update import CASES, _setup


def _grads(loss, nets):
    params = [*nets.actor.parameters(), *nets.critic.parameters()]
    return torch.autograd.grad(loss, params, allow_unused=True)


def _junk(groups):
    """The groups with every dead slot's entries replaced by non-finite values (actions out of range)."""
    dead = ~groups.mask
    out = {}
    for name in groups.keys():
        x = getattr(groups, name)
        if name == "mask":
            out[name] = x
        elif isinstance(x, tuple):
            out[name] = tuple(_spoil(t, dead) for t in x)
        else:
            out[name] = _spoil(x, dead)
    return dataclasses.replace(groups, **out)


def _spoil(x, dead):
    d = dead.reshape(*dead.shape, *(1,) * (x.dim() - dead.dim()))
    bad = torch.full_like(x, 10**6) if not x.is_floating_point() else torch.full_like(x, float("nan"))
    return torch.where(d, bad, x)


def every_slot(mask):
    """Rows of every slot of a minibatch's groups (mask (n, C)), the dead ones weighted 0: the fillers are the dead
    slots themselves."""
    n, C = mask.shape
    return torch.arange(n).repeat_interleave(C), torch.arange(C).repeat(n), mask.reshape(-1).float()


@pytest.mark.parametrize("fillers", ["padded", "every slot"])
@pytest.mark.parametrize("case", CASES)
def test_the_fixed_row_loss_is_the_live_rows_loss_whatever_the_fillers_read(tmp_path, case, fillers):
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, case)
    batch = collector.collect()
    groups = flatten(batch, advantages(cfg, batch), nets.head.discrete)
    # a third of the slots dead (the tiny rollout's agents all live through it)
    dead = torch.rand(groups.mask.shape, generator=torch.Generator().manual_seed(5)) < 0.35
    groups = dataclasses.replace(groups, mask=groups.mask & ~dead)
    idx = torch.randperm(groups.mask.shape[0], generator=torch.Generator().manual_seed(3))[:11]
    lam = torch.linspace(0.1, 0.9, groups.mask.shape[1])
    loss, parts = minibatch_loss(cfg, groups, idx, lam, nets, prior)
    first = int(groups.mask[idx, 0].float().argmax())  # a group whose slot 0 is live, first: the fillers repeat it
    assert bool(groups.mask[idx[first], 0])
    idx = torch.cat([idx[first:first + 1], idx[:first], idx[first + 1:]])
    mi = groups.mask[idx]
    if fillers == "padded":  # fillers at (0, 0), a live row read again with weight 0
        g, c, w = padded_rows(mi.nonzero(as_tuple=True), int(mi.sum()) + 9)
    else:
        g, c, w = every_slot(mi)
    fixed, fparts = minibatch_loss(cfg, _junk(groups), idx, lam, nets, prior, (g, c), row_weight=w)
    torch.testing.assert_close(fixed, loss, rtol=1e-5, atol=1e-6)
    for k in parts:
        torch.testing.assert_close(fparts[k], parts[k], rtol=1e-5, atol=1e-6)
    for a, b in zip(_grads(fixed, nets), _grads(loss, nets)):
        if b is None:
            assert a is None or not bool(a.any())
            continue
        assert bool(torch.isfinite(a).all())
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_padded_rows_put_the_live_rows_first_and_weigh_the_fillers_zero():
    g, c, w = padded_rows((torch.tensor([0, 2, 2]), torch.tensor([1, 0, 3])), 5)
    assert g.tolist() == [0, 2, 2, 0, 0] and c.tolist() == [1, 0, 3, 0, 0] and w.tolist() == [1, 1, 1, 0, 0]
    out = (torch.full((4,), 7), torch.full((4,), 7), torch.full((4,), 7.0))  # stale buffers are overwritten
    assert padded_rows((torch.tensor([1]), torch.tensor([2])), 4, out) is out
    assert out[0].tolist() == [1, 0, 0, 0] and out[1].tolist() == [2, 0, 0, 0] and out[2].tolist() == [1, 0, 0, 0]
    with pytest.raises(ValueError, match="3 live rows do not fit in 2"):
        padded_rows((torch.tensor([0, 1, 2]), torch.tensor([0, 0, 0])), 2)


def test_the_step_capacity_rounds_up_to_a_sixteenth_and_never_shrinks_until_new_buffers(tmp_path):
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, "discrete")
    steps = StepGraphs(cfg, nets, opt)
    assert steps.capacity(100, 320) == 100  # sixteenths of 320 slots: 20
    assert steps.capacity(101, 320) == 120
    assert steps.capacity(0, 320) == 20  # at least one row
    assert steps.capacity(400, 320) == 320  # never more than the slots
    steps.cap = 120
    assert steps.capacity(30, 320) == 120


def _few_then_full(tmp_path, epochs: int, compiled: bool = False):
    """Two updates, eager and through StepGraphs: on a rollout with a third of its slots live, then on the whole
    rollout, whose minibatches need more rows than the first capacity holds. (the weights after each way, the
    steps' capacity after each update, torch.compile's graphs after each update; `compiled`: the steps' loss
    through torch.compile)."""
    import torch._dynamo

    from tg_gpudrive.learn.update import eager_steps

    weights, caps, graphs = {}, [], []
    for mode in ("eager", "steps"):
        cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path / mode, "discrete", epochs=epochs,
                                                                      minibatches=3, cuda_graphs=True,
                                                                      compile_update=compiled and mode == "steps")
        batch = collector.collect()
        full = flatten(batch, advantages(cfg, batch), nets.head.discrete)
        few = dataclasses.replace(full, mask=full.mask & (torch.rand(full.mask.shape,
                                                                     generator=torch.Generator().manual_seed(2)) < 0.3))
        lam = torch.linspace(0.1, 0.9, full.mask.shape[1])
        steps = StepGraphs(cfg, nets, opt)
        torch._dynamo.reset()
        torch._dynamo.utils.counters.clear()
        for groups in (few, full):
            ugen = torch.Generator().manual_seed(4)
            if mode == "eager":
                eager_steps(cfg, groups, lam, nets, opt, ugen, prior)
            else:
                steps.run(groups, lam, ugen, prior)
                caps.append(steps.cap)
                graphs.append(torch._dynamo.utils.counters["stats"]["unique_graphs"])
        weights[mode] = [p.detach().clone() for p in (*nets.actor.parameters(), *nets.critic.parameters())]
    return weights, caps, graphs


def test_more_live_rows_grow_the_step_capacity_and_the_steps_stay_the_eager_ones(tmp_path):
    """The second rollout needs more rows than the first capacity holds, so the steps take new row buffers; both
    updates move the weights as the eager steps do."""
    weights, caps, _ = _few_then_full(tmp_path, epochs=2)
    assert caps[0] < caps[1]
    for a, b in zip(weights["steps"], weights["eager"]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=2e-5)


def _updates(tmp_path, device, graphs: bool, capture: bool = True, n: int = 3, compiled: bool = False):
    """`n` rollouts and updates of a tiny run whose updates have short last minibatches; the weights and
    multipliers after them, and the StepGraphs (or None). `compiled`: the steps' loss through torch.compile."""
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path, "discrete", device, epochs=2,
                                                                  minibatches=5, cuda_graphs=graphs,
                                                                  compile_update=compiled)
    steps = StepGraphs(cfg, nets, opt) if graphs else None
    if steps is not None:
        steps.capturable = capture
    ugen = torch.Generator(device=device).manual_seed(1)
    budget = torch.tensor(0.0, device=device)
    for _ in range(n):
        batch = collector.collect()
        ppo_update(cfg, batch, nets, opt, lagrange, budget, ugen, prior, graphs=steps)
    weights = [p.detach().clone() for p in (*nets.actor.parameters(), *nets.critic.parameters())]
    return weights, lagrange.value.detach().clone(), steps


def test_an_update_through_step_graphs_moves_the_weights_as_the_eager_one_on_the_cpu(tmp_path):
    eager, lam_e, _ = _updates(tmp_path / "e", "cpu", graphs=False)
    fixed, lam_f, steps = _updates(tmp_path / "f", "cpu", graphs=True)
    assert not steps.graphed and steps.warm > 0  # the CPU runs the fixed-shape steps without graphs
    for a, b in zip(fixed, eager):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=2e-5)
    torch.testing.assert_close(lam_f, lam_e)


@pytest.mark.slow
def test_the_compiled_loss_moves_the_weights_as_the_eager_one_on_the_cpu(tmp_path):
    """compile_update: the fixed-shape steps' loss through torch.compile (inductor's fused kernels; a cold
    compile takes about 20 s on a 2-core CPU) ends three updates on the eager update's weights."""
    import torch._dynamo

    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    eager, lam_e, _ = _updates(tmp_path / "e", "cpu", graphs=False)
    fused, lam_c, steps = _updates(tmp_path / "c", "cpu", graphs=True, compiled=True)
    assert steps.loss is not minibatch_loss and torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 1
    for a, b in zip(fused, eager):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(lam_c, lam_e)
    # a warm start (a new process's, here a reset) finds the traced forward and backward pass in torch.compile's
    # autograd cache instead of tracing them again: the graph holds no autocast region that would bar it
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    _updates(tmp_path / "w", "cpu", graphs=True, compiled=True, n=1)
    aot = torch._dynamo.utils.counters["aot_autograd"]
    assert aot["autograd_cache_hit"] >= 1 and aot["autograd_cache_bypass"] == 0, dict(aot)


@pytest.mark.slow
def test_the_compiled_live_row_loss_moves_the_weights_as_the_eager_one_on_the_cpu(tmp_path):
    """compile_update without the fixed-shape steps: the live rows' loss through torch.compile, their count a
    dynamic size, compiled once for minibatches of every count (the first one's shape, then a symbolic one)."""
    import torch._dynamo

    torch._dynamo.reset()
    update_mod.compiled_live_loss.cache_clear()
    torch._dynamo.utils.counters.clear()
    eager, lam_e, _ = _updates(tmp_path / "e", "cpu", graphs=False)
    fused, lam_c, _ = _updates(tmp_path / "c", "cpu", graphs=False, compiled=True)
    assert 1 <= torch._dynamo.utils.counters["stats"]["unique_graphs"] <= 2  # compiled, not once per minibatch
    for a, b in zip(fused, eager):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(lam_c, lam_e)


@pytest.mark.slow
def test_a_grown_step_capacity_does_not_compile_the_loss_again(tmp_path):
    """compile_update: after the capacity grew, the compiled loss (its row count a symbolic size) serves the new
    row buffers without a second compilation, and the weights stay the eager steps' ones."""
    weights, caps, graphs = _few_then_full(tmp_path, epochs=1, compiled=True)
    assert caps[0] < caps[1]
    assert graphs[0] >= 1 and graphs[1] == graphs[0]
    for a, b in zip(weights["steps"], weights["eager"]):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("graphs", [True, False], ids=["replayed", "live_rows"])
def test_compiled_steps_equal_eager_ones_on_cuda(tmp_path, graphs):
    fused, lam_c, steps = _updates(tmp_path / "c", "cuda", graphs=graphs, compiled=True)
    assert steps is None or (steps.graphed and steps.captures >= 1)
    eager, lam_e, _ = _updates(tmp_path / "e", "cuda", graphs=False)
    for a, b in zip(fused, eager):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(lam_c, lam_e)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_replayed_steps_equal_eager_ones_on_cuda(tmp_path):
    graphed, lam_g, steps = _updates(tmp_path / "g", "cuda", graphs=True)
    assert steps.graphed and steps.captures >= 1 and steps.opt_captures >= 1  # clipping and Adam replayed too
    unreplayed, lam_u, plain = _updates(tmp_path / "u", "cuda", graphs=True, capture=False)
    assert not plain.graphed
    eager, lam_e, _ = _updates(tmp_path / "e", "cuda", graphs=False)
    for g, u, e in zip(graphed, unreplayed, eager):
        torch.testing.assert_close(g, u, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(g, e, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(lam_g, lam_e)


def test_a_trainer_with_cuda_graphs_trains_and_resumes_exactly(tmp_path):
    """The config knob reaches the trainer; on the CPU its steps run without graphs, and a resumed run
    continues bit for bit."""
    from test_train import rows, tiny

    from tg_gpudrive.learn.train import Trainer

    a, b = tmp_path / "a", tmp_path / "b"
    Trainer(tiny(a, cuda_graphs=True, updates=3), a, progress=False).train()
    tr = Trainer(tiny(b, cuda_graphs=True, updates=2), b, progress=False)
    assert isinstance(tr.graphs, StepGraphs)
    tr.train()
    Trainer(tiny(b, cuda_graphs=True, updates=3), b, resume=b, progress=False).train()
    ra, rb = rows(a), rows(b)
    assert len(ra) == len(rb) == 3
    for key in ("loss/policy", "loss/value", "entropy", "goal_rate"):
        assert [r[key] for r in ra] == [r[key] for r in rb]
    assert ra[-1]["update"] == "3"
    # metrics.csv says whether the knob took: on the CPU nothing is captured, and nothing fell back
    assert [r["graphs/update_captures"] for r in ra] == ["0"] * 3 and ra[-1]["graphs/update_fell_back"] == "0"
    assert [r["graphs/optimizer_captures"] for r in ra] == ["0"] * 3


@pytest.mark.slow
def test_a_compiling_trainer_loads_the_compiler_while_it_builds_and_counts_only_its_own_graphs(tmp_path):
    """compile_update: the trainer has compiled a tiny function (the compiler's start-up) before its first
    update, on a thread that has ended by then; metrics.csv's compile/graphs counts the loss's graphs alone. A
    trainer that compiles nothing starts no preload."""
    import torch._dynamo
    from test_train import rows, tiny

    from tg_gpudrive.learn.train import Trainer

    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    Trainer(tiny(tmp_path / "plain", updates=1), tmp_path / "plain", progress=False)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 0
    tr = Trainer(tiny(tmp_path / "c", compile_update=True, updates=2), tmp_path / "c", progress=False)
    assert tr.graphs0 == torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1  # the preload's, done
    tr.train()
    graphs = [int(r["compile/graphs"]) for r in rows(tmp_path / "c")]
    assert graphs[0] >= 1 and graphs[-1] == torch._dynamo.utils.counters["stats"]["unique_graphs"] - 1


def test_a_failed_compiler_preload_is_logged_and_never_raised(caplog, monkeypatch):
    """The preload is a warm-up: its failure is logged, and waiting for it returns."""
    from tg_gpudrive.learn import compiling

    def broken(x):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(compiling, "_preload_fn", broken)
    with caplog.at_level("INFO", logger="tg_gpudrive.learn.compiling"):
        thread = compiling.start_compiler_preload("cpu")
        thread.join()
    assert not thread.is_alive()
    assert any("start-up failed" in r.getMessage() and "no compiler here" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device"))])
def test_the_trainer_steps_one_fused_adam_on_the_gpu_and_its_state_resumes(tmp_path, device):
    """On the GPU the optimiser is the fused Adam (one kernel for every parameter) with its step counters on the
    device (a CUDA graph can record its step), elsewhere the multi-tensor one; either way a resumed run's
    optimiser holds the state the saved one had."""
    from test_train import tiny

    from tg_gpudrive.learn.train import Trainer

    tr = Trainer(tiny(tmp_path, device=device, updates=2), tmp_path, progress=False)
    assert bool(tr.opt.defaults["fused"]) == bool(tr.opt.defaults["capturable"]) == (device == "cuda")
    tr.train()
    again = Trainer(tiny(tmp_path, device=device, updates=3), tmp_path, resume=tmp_path, progress=False)
    assert bool(again.opt.defaults["fused"]) == (device == "cuda")
    saved, loaded = tr.opt.state_dict()["state"], again.opt.state_dict()["state"]
    assert saved.keys() == loaded.keys() and len(saved) == len(tr.params)
    for k in saved:
        for name in ("step", "exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(loaded[k][name].cpu(), saved[k][name].cpu(), rtol=0, atol=0)
    again.train()
    assert all(torch.isfinite(p).all() for p in again.params)


ROLLOUT = {  # a world with fewer agents than the others: dead slots
    "discrete": dict(num_worlds=3, rollout_steps=24, magnet_fraction=0.25),  # the magnet on a quarter of the rows
    "continuous+history": dict(num_worlds=3, rollout_steps=24),  # the expert prior's context, the actor's window
}


def _rollouts(tmp_path, device, case: str, graphs: bool, n: int = 3):
    """`n` rollouts of a tiny run, acting on every slot through RolloutGraphs or on the live rows; the last
    rollout's buffers and counters, and the RolloutGraphs."""
    cfg, sim, nets, collector, *_ = _setup(tmp_path, case, device, **ROLLOUT[case])
    collector.graphs = RolloutGraphs(device) if graphs else None
    for _ in range(n):
        batch = collector.collect()
    return batch, collector.graphs


def _same_rollout(a, b, tol: dict) -> None:
    m = a.mask
    assert torch.equal(m, b.mask) and 0 < int(m.sum()) < m.numel()  # dead slots were there
    assert torch.equal(a.done, b.done)
    torch.testing.assert_close(a.act, b.act, **tol)  # the no-op where nobody acts
    for name in ("logp", "reward", "cost", "obs", "prior", "prior_ctx", "hist"):
        x, y = getattr(a, name), getattr(b, name)
        if x is not None and x.numel():
            take = m if a.prior_weight is None or name != "prior" else a.prior_weight > 0
            torch.testing.assert_close(x[take], y[take], **tol)
    if a.prior_weight is not None:
        assert torch.equal(a.prior_weight, b.prior_weight)
    for k in a.stats:
        torch.testing.assert_close(a.stats[k], b.stats[k], **tol)


@pytest.mark.parametrize("case", ROLLOUT)
def test_a_rollout_on_every_slot_fills_the_buffers_of_the_live_row_one(tmp_path, case):
    live, _ = _rollouts(tmp_path / "l", "cpu", case, graphs=False)
    dense, graphs = _rollouts(tmp_path / "d", "cpu", case, graphs=True)
    assert not graphs.graphed and graphs.seen  # the CPU runs the steps as they are
    _same_rollout(dense, live, dict(rtol=1e-5, atol=1e-5))


def test_a_fixed_shape_rollout_acts_on_the_integrated_slots_alone(tmp_path):
    """The fixed-shape steps feed the actor the controlled slots the engine integrates, not all W x C: the
    worlds with fewer agents than slots give it fewer rows."""
    cfg, sim, nets, collector, *_ = _setup(tmp_path, "discrete", **ROLLOUT["discrete"])
    collector.graphs = RolloutGraphs("cpu")
    forward, rows = nets.actor.forward, []
    nets.actor.forward = lambda obs, *a, **k: rows.append(len(obs)) or forward(obs, *a, **k)
    batch = collector.collect()
    C = batch.mask.shape[-1]
    integrated = int((sim.integrated[:, :C] != 0).sum())
    assert rows == [integrated] * cfg.rollout_steps and int(batch.mask.sum(-1).max()) <= integrated < sim.num_worlds * C


class _PartWatch(RolloutGraphs):
    """RolloutGraphs that notes whether a step's part is running (what a CUDA graph would capture)."""
    inside = False

    def run(self, owners, name, fn):
        def watched():
            _PartWatch.inside = True
            try:
                fn()
            finally:
                _PartWatch.inside = False
        super().run(owners, name, watched)


def test_after_a_failed_capture_the_updates_and_rollouts_go_on_the_live_rows(tmp_path):
    """A capture that fails (on a GPU: memory, an operation that cannot be captured) sends the updates to
    update.eager_steps and the rollouts to the live rows: their weights and buffers are then those of a run
    without graphs, bit for bit on the CPU."""
    eager, lam_e, _ = _updates(tmp_path / "e", "cpu", graphs=False)
    cfg, sim, nets, collector, opt, lagrange, gen, prior = _setup(tmp_path / "f", "discrete", epochs=2,
                                                                  minibatches=5)
    steps = StepGraphs(cfg, nets, opt)
    steps._fall_back()
    collector.graphs = RolloutGraphs("cpu")
    collector.graphs.capturable = False  # what a failed rollout capture leaves
    ugen = torch.Generator().manual_seed(1)
    for _ in range(3):
        batch = collector.collect()
        ppo_update(cfg, batch, nets, opt, lagrange, torch.tensor(0.0), ugen, prior, graphs=steps)
    assert not collector.graphs.seen and steps.warm == 0  # neither ran a fixed-shape step
    for a, b in zip((*nets.actor.parameters(), *nets.critic.parameters()), eager):
        assert torch.equal(a.detach(), b)
    assert torch.equal(lagrange.value.detach(), lam_e)


def test_an_engine_kernel_prior_is_read_outside_the_captured_parts(tmp_path):
    """The closed-loop expert's context is an engine (Warp) kernel on the engine's stream, which a torch
    capture would not record: a replay would hand the magnet a stale context. It is read before each
    step's part, and the part reads what it wrote."""
    cfg, sim, nets, collector, *_ = _setup(tmp_path, "continuous+history", **ROLLOUT["continuous+history"])
    assert collector.prior.closed_loop and not collector.prior.capturable
    calls = []
    corrective = sim.corrective_expert
    sim.corrective_expert = lambda: calls.append(_PartWatch.inside) or corrective()
    collector.graphs = _PartWatch("cpu")
    batch = collector.collect()
    assert len(calls) == cfg.rollout_steps and not any(calls)
    live, _ = _rollouts(tmp_path / "l", "cpu", "continuous+history", graphs=False, n=1)
    _same_rollout(batch, live, dict(rtol=1e-5, atol=1e-5))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("case", ROLLOUT)
def test_replayed_rollout_steps_fill_the_buffers_of_eager_ones_on_cuda(tmp_path, case):
    graphed, graphs = _rollouts(tmp_path / "g", "cuda", case, graphs=True)
    assert graphs.graphed and graphs.captures == 2 * ROLLOUT[case]["rollout_steps"]
    live, _ = _rollouts(tmp_path / "l", "cuda", case, graphs=False)
    _same_rollout(graphed, live, dict(rtol=1e-4, atol=1e-4))
