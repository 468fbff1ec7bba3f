"""Distributed CCE-MAPPO on CPU with gloo and 2 processes: the ranks' averaged gradients equal a
single-process run over the union of the batches, the ranks keep the same weights, and a 2-rank run trains,
checkpoints, and resumes with 1 rank."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from tg_gpudrive import cli
from tg_gpudrive.config import REPO_CONFIGS, TrainConfig, load_config

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"
G = 8  # groups (world x step) in the synthetic batch


def tiny_cfg(out) -> TrainConfig:
    return dataclasses.replace(load_config(TrainConfig, SMALL), num_worlds=2, num_scenes=4, rollout_steps=4,
                               epochs=1, minibatches=1, hidden=16, quantiles=8, updates=1,
                               normalize_advantages=False, out_dir=str(out))


def synthetic_batch(trainer) -> dict:
    g = torch.Generator().manual_seed(42)
    C, D, A = 4, trainer.sim.obs_dim, trainer.sim.num_actions
    obs = torch.randn(G, C, D, generator=g)
    obs[..., 10] = 1.0  # first partner row present
    obs[..., 10 + trainer.cfg.env.partner_k * 10] = 1.0  # first road row present
    act = torch.randint(0, A, (G, C), generator=g)
    prior = torch.randn(G, C, A, generator=g)  # the discrete magnet's logits, as the rollout stores them
    return {"obs": obs, "act": act, "logp": torch.randn(G, C, generator=g) - 4, "mask": torch.ones(G, C, dtype=torch.bool),
            "prior": prior, "adv_r": torch.randn(G, C, generator=g), "adv_c": torch.randn(G, C, generator=g),
            "ret_r": torch.randn(G, C, generator=g), "q_target": torch.randn(G, C, 8, generator=g),
            "old": torch.randn(G, C, A, generator=g)}


def grads_of(trainer, idx, fixed_rows: bool = False) -> list[torch.Tensor]:
    """The gradients of one optimiser step on the groups `idx` of the synthetic batch, averaged over the
    ranks as every step averages them (update.clip_and_step). `fixed_rows`: the loss over the live rows padded
    with zero-weight fillers, as a step of learn/graphs.py runs it."""
    from tg_gpudrive.learn import distributed
    from tg_gpudrive.learn.update import Groups, minibatch_loss, padded_rows

    trainer.opt.zero_grad()
    groups = Groups.of(synthetic_batch(trainer))
    mi = groups.mask[idx]
    rows, weight = None, None
    if fixed_rows:
        *rows, weight = padded_rows(mi.nonzero(as_tuple=True), mi.numel())
    loss, _ = minibatch_loss(trainer.cfg, groups, idx, torch.full((4,), 0.3),
                             trainer.nets, trainer.prior, rows, row_weight=weight)  # one multiplier per slot
    loss.backward()
    distributed.average_gradients_(trainer.params)
    return [p.grad.clone() for p in trainer.params]


def _grads_worker(rank, world, port, out, result, fixed_shape):
    from tg_gpudrive.learn import distributed
    from tg_gpudrive.learn.train import Trainer

    with distributed.process_group(rank, world, port, "cpu"):
        tr = Trainer(dataclasses.replace(tiny_cfg(out / "two"), cuda_graphs=fixed_shape), progress=False)
        half = torch.arange(rank * G // 2, (rank + 1) * G // 2)
        gr = grads_of(tr, half, fixed_rows=fixed_shape)
        if rank == 0:
            result.put([x.numpy() for x in gr])


@pytest.mark.slow
@pytest.mark.parametrize("fixed_shape", [False, True], ids=["live rows", "fixed-shape steps"])
def test_averaged_gradients_equal_single_process_union(tmp_path, fixed_shape):
    from tg_gpudrive.learn.distributed import free_port
    from tg_gpudrive.learn.train import Trainer

    ctx = mp.get_context("spawn")
    q = ctx.SimpleQueue()
    mp.spawn(_grads_worker, args=(2, free_port(), tmp_path, q, fixed_shape), nprocs=2)
    two = q.get()
    single = grads_of(Trainer(tiny_cfg(tmp_path / "one"), progress=False), torch.arange(G))
    assert len(two) == len(single)
    for a, b in zip(two, single):
        torch.testing.assert_close(torch.as_tensor(a), b, atol=1e-5, rtol=1e-4)
    assert any(float(b.abs().sum()) > 0 for b in single)


def _weights_worker(rank, world, port, out, result, fixed_rows):
    from tg_gpudrive.learn import distributed
    from tg_gpudrive.learn.train import Trainer

    with distributed.process_group(rank, world, port, "cpu"):
        cfg = dataclasses.replace(tiny_cfg(out), updates=2, minibatches=2, cuda_graphs=fixed_rows)
        tr = Trainer(cfg, progress=False)  # each rank seeds its own draws (seed + rank), its weights too
        first = torch.cat([p.detach().flatten() for p in tr.params])
        tr.train()
        last = torch.cat([p.detach().flatten() for p in tr.params])
        firsts, lasts = (distributed.gather_floats(x.tolist(), "cpu") for x in (first, last))
        caps = distributed.gather_floats([float(tr.graphs.cap) if tr.graphs else 0.0], "cpu")
        if rank == 0:  # a few booleans: a large message would fill the queue's pipe before the parent reads it
            result.put((firsts[0] == firsts[1], lasts[0] == lasts[1], float((last - first).abs().max()),
                        [c[0] for c in caps]))


@pytest.mark.slow
@pytest.mark.parametrize("fixed_rows", [False, True], ids=["live rows", "fixed-row steps"])
def test_the_ranks_start_from_rank_0s_weights_and_keep_them_equal(tmp_path, fixed_rows):
    """The ranks draw different rollouts but take the same steps: they start from rank 0's weights and every
    step applies the same averaged gradients, so their weights stay equal, and training moved them. With the
    fixed-row steps of learn/graphs.py the ranks hold one row capacity, so that they capture together."""
    from tg_gpudrive.learn.distributed import free_port

    ctx = mp.get_context("spawn")
    q = ctx.SimpleQueue()
    mp.spawn(_weights_worker, args=(2, free_port(), tmp_path, q, fixed_rows), nprocs=2)
    same_start, same_end, moved, caps = q.get()
    assert same_start and same_end and moved > 0
    assert caps[0] == caps[1] and (caps[0] > 0) == fixed_rows


@pytest.mark.slow
def test_two_rank_run_checkpoints_and_resumes_with_one(tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--config", str(SMALL), "--out", str(run), "--set", "updates=2", "--set", "num_worlds=2",
            "--set", "rollout_steps=4", "--set", "hidden=16", "--set", "quantiles=4", "--set", "num_scenes=8"]
    assert cli.main(args + ["--nproc", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["world_size"] == 2 and ck["update"] == 2 and out["ranks"] == 2
    # where each rank's time went: a row per rank and update; a rank's rollout plus its wait is the
    # same on both ranks (both wait for the slowest), and metrics.csv names the slowest rollout
    timing = list(csv.DictReader((run / "timing.csv").open()))
    assert [(r["update"], r["rank"]) for r in timing] == [("1", "0"), ("1", "1"), ("2", "0"), ("2", "1")]
    metrics = list(csv.DictReader((run / "metrics.csv").open()))
    for u in ("1", "2"):
        rows = [r for r in timing if r["update"] == u]
        own = [float(r["rollout_s"]) for r in rows]
        until = [float(r["rollout_s"]) + float(r["wait_s"]) for r in rows]
        assert all(x > 0 for x in own) and all(float(r["update_s"]) > 0 for r in rows)
        assert abs(until[0] - until[1]) < 0.5 * max(until) and min(until) >= max(own) - 0.05
        m = next(r for r in metrics if r["update"] == u)
        assert float(m["time/rollout_slowest_s"]) == pytest.approx(max(own), rel=1e-4)
        assert float(m["time/rollout_s"]) == pytest.approx(own[0], rel=1e-4)
    assert cli.main(["train", "--config", str(SMALL), "--resume", str(run), "--set", "updates=3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["world_size"] == 1 and ck["update"] == 3 and out["update"] == 3
    timing = list(csv.DictReader((run / "timing.csv").open()))
    assert [(r["update"], r["rank"]) for r in timing][-1] == ("3", "0") and len(timing) == 5


def _slow_lead_worker(rank, world, port, out, result):
    """Two ranks, a checkpoint after every update whose writing takes the lead an extra 0.8 s."""
    import time

    from tg_gpudrive.learn import distributed
    from tg_gpudrive.learn.train import Trainer

    with distributed.process_group(rank, world, port, "cpu"):
        tr = Trainer(dataclasses.replace(tiny_cfg(out), updates=3, checkpoint_every=1), out, progress=False)
        save = tr.save

        def slow_save():
            path = save()
            if rank == 0:
                time.sleep(0.8)
            return path

        tr.save = slow_save
        tr.train()
        if rank == 0:
            result.put((tr.wall, tr.elapsed))


@pytest.mark.slow
def test_the_lead_writing_a_checkpoint_stays_outside_the_other_ranks_clock(tmp_path):
    """The update's clock (wall_s, the time-to-quality clock) counts rollout and update alone on every rank
    count: the ranks start it together, so the lead's checkpoint writes between updates show in no rank's wait
    for the slowest rollout."""
    from tg_gpudrive.learn.distributed import free_port

    ctx = mp.get_context("spawn")
    result = ctx.SimpleQueue()
    mp.spawn(_slow_lead_worker, args=(2, free_port(), tmp_path, result), nprocs=2, join=True)
    wall, elapsed = result.get()
    assert elapsed - wall > 1.6  # the two writes between the three updates, outside the clock
    timing = list(csv.DictReader((tmp_path / "timing.csv").open()))
    waits = [float(r["wait_s"]) for r in timing if r["update"] != "1"]
    assert len(waits) == 4 and max(waits) < 0.4, waits  # 0.8 s each without the common start


def test_shards_are_disjoint_cover_the_source_and_mix_scene_types():
    from tg_gpudrive.data.sources import resolve_scenes
    from tg_gpudrive.learn.distributed import ShardSource

    src = resolve_scenes("procedural:all", n=60, seed=0)
    shards = [ShardSource(src, r, 2) for r in range(2)]
    got = [set(int(i) for i in s.indices) for s in shards]
    assert got[0].isdisjoint(got[1]) and got[0] | got[1] == set(range(60))
    assert len(shards[0]) + len(shards[1]) == 60
    # scene i of procedural:all has type i % 6: every rank must see every type, in similar shares
    for s in shards:
        counts = np.bincount(s.indices % 6, minlength=6)
        assert counts.min() >= 2, counts
    assert shards[1].get(0).scene_id == src.get(int(shards[1].indices[0])).scene_id


def _gather_worker(rank, world, port, backend_seen, result):
    from tg_gpudrive.learn import distributed

    with distributed.process_group(rank, world, port, "cpu"):
        if backend_seen != "gloo":  # as under NCCL: objects go through a gloo group of their own
            distributed.dist.get_backend = lambda group=None: backend_seen
        got = distributed.gather_to_lead({"rank": rank, "state": np.arange(3) + rank})
        made = distributed._OBJECT_GROUP is not None
        if rank == 0:
            result.put(([g["rank"] for g in got], [g["state"].tolist() for g in got], made))
        else:
            assert got is None


@pytest.mark.parametrize("backend", ["gloo", "nccl"])
def test_every_rank_state_reaches_the_lead(backend):
    """gather_to_lead: rank 0 gets every rank's object in rank order, the others None; with a backend
    other than gloo (NCCL on GPUs) the objects travel through a gloo group made for them."""
    from tg_gpudrive.learn.distributed import free_port

    ctx = mp.get_context("spawn")
    q = ctx.SimpleQueue()
    mp.spawn(_gather_worker, args=(2, free_port(), backend, q), nprocs=2)
    ranks, states, made = q.get()
    assert ranks == [0, 1] and states == [[0, 1, 2], [1, 2, 3]] and made == (backend != "gloo")


def _agree_worker(rank, world, port, result):
    from tg_gpudrive.learn import distributed

    with distributed.process_group(rank, world, port, "cpu"):
        votes = [distributed.every_rank(ok, "cpu") for ok in (True, rank == 0, rank == 1, False)]
        result.put((rank, votes))


def test_every_rank_agrees_only_when_all_do():
    """every_rank: a rank's failed capture makes every rank fall back (graphs.StepGraphs), so that their
    collectives keep matching."""
    from tg_gpudrive.learn.distributed import every_rank, free_port

    assert every_rank(True, "cpu") and not every_rank(False, "cpu")  # one process: its own vote
    ctx = mp.get_context("spawn")
    q = ctx.SimpleQueue()
    mp.spawn(_agree_worker, args=(2, free_port(), q), nprocs=2)
    got = dict(q.get() for _ in range(2))
    assert got == {0: [True, False, False, False], 1: [True, False, False, False]}
