"""The acting and the learning process of `pipeline: true` (learn/pipeline.py), on the CPU with gloo and on two
GPUs with NCCL when there are two: the two processes end on the weights of a one-process reference that collects
each batch with the weights from one update before, an early stop and its resume continue as the run that went
through, and the run's files say where the time went."""

from __future__ import annotations

import csv
import dataclasses

import pytest
import torch
import torch.multiprocessing as mp

from tg_gpudrive.config import REPO_CONFIGS, ConfigError, TrainConfig, load_config

UPDATES = 4
STOP_AT = 2  # the early stop of the interrupted run


def _two_gpus() -> bool:
    from tg_gpudrive.engine.simulator import cuda_available

    return cuda_available() and torch.cuda.device_count() >= 2


KINDS = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not _two_gpus(), reason="needs two CUDA devices"))]


def tiny_cfg(out, **kw) -> TrainConfig:
    """Four updates of a few merges, a resampling of the scenes after the second."""
    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    return dataclasses.replace(cfg, num_worlds=2, num_scenes=8, rollout_steps=4, hidden=16, quantiles=4, epochs=2,
                               minibatches=2, updates=UPDATES, resample_every=2, checkpoint_every=100,
                               out_dir=str(out), **kw)


def _worker(rank, world, port, out, kind, stop_at, resume, result):
    """One process of a pipeline of `world`; the learners put their final actor weights in `result`."""
    from tg_gpudrive.learn import distributed
    from tg_gpudrive.learn.train import Trainer

    with distributed.process_group(rank, world, port, kind):
        tr = Trainer(tiny_cfg(out, pipeline=True, device=kind), out, resume=resume, progress=False)
        verdict = tr.verdict

        def stop_early(*args):  # as a quality target met at update `stop_at` would: save and stop there
            save, end = verdict(*args)
            return (True, True) if tr.update == stop_at else (save, end)

        tr.verdict = stop_early
        tr.train()
        if rank % 2 == 0:  # a learner; numpy, as tensors would not outlive the process
            result.put((rank, {k: v.cpu().numpy().copy() for k, v in tr.actor.state_dict().items()}))


def pipelined(out, kind, stop_at=0, resume=None, processes=2) -> dict:
    """The final actor weights of a pipeline run of `processes` processes, after checking that its learners
    all end on them."""
    from tg_gpudrive.learn.distributed import free_port

    result = mp.get_context("spawn").SimpleQueue()
    mp.spawn(_worker, args=(processes, free_port(), out, kind, stop_at, resume, result), nprocs=processes, join=True)
    learners = dict(result.get() for _ in range(processes // 2))
    for w in learners.values():
        for k, v in w.items():
            assert (v == learners[0][k]).all(), k  # the learners averaged their gradients
    return {k: torch.from_numpy(v) for k, v in learners[0].items()}


def reference(out, kind, lag: int) -> dict:
    """One process, one update at a time: batch i collected with the weights after update i - lag (the first
    ones with the initial weights), from draws of a generator of its own, as the acting process makes them."""
    from tg_gpudrive.learn.train import Trainer

    tr = Trainer(tiny_cfg(out, device=kind), out, progress=False)
    tr.collector.gen = torch.Generator(device=tr.device).manual_seed(tr.cfg.seed)
    nets = (tr.actor, tr.critic)
    weights = [[{k: v.clone() for k, v in m.state_dict().items()} for m in nets]]  # after 0, 1, ... updates
    for i in range(UPDATES):
        if i > 0 and i % tr.cfg.resample_every == 0:
            tr._resample()
        for m, w in zip(nets, weights[max(i - lag, 0)]):
            m.load_state_dict(w)
        batch, _ = tr.collect()
        for m, w in zip(nets, weights[i]):
            m.load_state_dict(w)
        tr.learn(batch)
        weights.append([{k: v.clone() for k, v in m.state_dict().items()} for m in nets])
    return {k: v.cpu() for k, v in weights[-1][0].items()}


def distance(a: dict, b: dict) -> float:
    return sum(float((a[k] - b[k]).double().pow(2).sum()) for k in a) ** 0.5


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_the_pipeline_learns_one_update_behind_and_resumes_exactly(tmp_path, kind):
    whole = pipelined(tmp_path / "whole", kind)
    lagged, unlagged = reference(tmp_path / "lag1", kind, 1), reference(tmp_path / "lag0", kind, 0)
    if kind == "cpu":  # the same arithmetic in the same order
        for k, v in lagged.items():
            torch.testing.assert_close(whole[k], v, rtol=1e-5, atol=1e-6, msg=k)
    # on the GPU its atomics reorder sums: nearer the lagged reference than the unlagged one is by far
    assert distance(whole, lagged) < 0.05 * distance(whole, unlagged)
    # the two processes' clocks: the learner waits and updates, the actor rolls out and waits for weights
    timing = list(csv.DictReader((tmp_path / "whole" / "timing.csv").open()))
    assert [(r["update"], r["rank"]) for r in timing] == [(str(u), str(r)) for u in range(1, 5) for r in (0, 1)]
    assert all(float(r["update_s"]) > 0 and float(r["rollout_s"]) == 0 for r in timing if r["rank"] == "0")
    assert all(float(r["rollout_s"]) > 0 and float(r["update_s"]) == 0 for r in timing if r["rank"] == "1")
    # the scenes visited are the actor's, which resampled after the second update (the learner never does)
    visited = [int(r["scenes_visited"]) for r in csv.DictReader((tmp_path / "whole" / "metrics.csv").open())]
    assert visited == [2, 2, 4, 4]
    # stopped early with a batch in flight, then resumed: the weights of the run that went through
    stopped = pipelined(tmp_path / "part", kind, stop_at=STOP_AT)
    ck = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=False)
    assert ck["update"] == STOP_AT and ck["world_size"] == 2 and "acting" in ck["other_ranks"][0]
    resumed = pipelined(tmp_path / "part", kind, resume=tmp_path / "part")
    if kind == "cpu":
        for k, v in whole.items():
            torch.testing.assert_close(resumed[k], v, rtol=0, atol=0, msg=k)
    assert distance(resumed, whole) < 0.05 * distance(stopped, whole)


@pytest.mark.slow
def test_two_pairs_learn_together_and_resume_exactly(tmp_path):
    """Four processes: two actors, two learners that average their gradients, count both actors' episodes and
    stop together; stopped early and resumed, they end where the run that went through ends."""
    whole = pipelined(tmp_path / "whole", "cpu", processes=4)
    timing = list(csv.DictReader((tmp_path / "whole" / "timing.csv").open()))
    assert [(r["update"], r["rank"]) for r in timing][:4] == [("1", str(r)) for r in range(4)]
    assert all(float(r["rollout_s"]) > 0 and float(r["update_s"]) == 0 for r in timing if r["rank"] in "13")
    metrics = list(csv.DictReader((tmp_path / "whole" / "metrics.csv").open()))
    slowest = max(float(r["rollout_s"]) for r in timing[:4] if r["rank"] in "13")  # the actors' rows
    assert float(metrics[0]["time/rollout_slowest_s"]) == pytest.approx(slowest, abs=1e-6)
    pipelined(tmp_path / "part", "cpu", stop_at=STOP_AT, processes=4)
    ck = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=False)
    assert ck["world_size"] == 4 and [("acting" in r) for r in ck["other_ranks"]] == [True, False, True]
    resumed = pipelined(tmp_path / "part", "cpu", resume=tmp_path / "part", processes=4)
    for k, v in whole.items():
        torch.testing.assert_close(resumed[k], v, rtol=0, atol=0, msg=k)


def test_a_pipeline_needs_an_even_number_of_processes(tmp_path):
    from tg_gpudrive.learn.train import Trainer

    with pytest.raises(ConfigError, match="pipeline: true needs an even number of processes"):
        Trainer(tiny_cfg(tmp_path, pipeline=True), tmp_path, progress=False)
