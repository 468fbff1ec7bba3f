"""CCE-MAPPO training: it learns, resumes exactly, stops cleanly on NaN; the prior, control
selection and the evaluate CLI behave."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_gpudrive import cli
from tg_gpudrive.checkpoint import kept_policies
from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, TrainConfig, load_config
from tg_gpudrive.engine.control import control_mask
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.agents.prior import ExpertPrior
from tg_gpudrive.learn.train import Trainer, TrainingError
from tg_gpudrive.agents.policy import categorical_kl, load_policy
from tg_gpudrive.engine.simulator import Simulator

from scenes import crossing_scene

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"


def tiny(tmp_path, **kw) -> TrainConfig:
    cfg = load_config(TrainConfig, SMALL)
    base = dict(num_worlds=2, num_scenes=4, rollout_steps=8, epochs=1, minibatches=2, hidden=32, quantiles=8,
                updates=4, checkpoint_every=2, out_dir=str(tmp_path))
    base.update(kw)
    return dataclasses.replace(cfg, **base)


def rows(path):
    return list(csv.DictReader((path / "metrics.csv").open()))


@pytest.mark.parametrize("history", [0, 3], ids=["obs", "obs+history"])
def test_resume_continues_exactly(tmp_path, history):
    """4 updates in one go == 2 updates, a kill, and a resume for 2 more (bit for bit on cpu), with
    and without the actor's motion history (its window is part of the checkpoint)."""
    a, b = tmp_path / "a", tmp_path / "b"
    Trainer(tiny(a, actor_history=history), a, progress=False).train()
    Trainer(tiny(b, updates=2, actor_history=history), b, progress=False).train()
    # the "kill": a later row that was logged after the last checkpoint must be dropped on resume
    with (b / "metrics.csv").open("a") as f:
        f.write(",".join(["999"] * len(rows(b)[0])) + "\n")
    with (b / "timing.csv").open("a") as f:
        f.write("999,0,1.0,0.0,1.0\n")
    Trainer(tiny(b, actor_history=history), b, resume=b, progress=False).train()
    ra, rb = rows(a), rows(b)
    assert len(ra) == len(rb) == 4
    timing = (b / "timing.csv").read_text().splitlines()  # the wall-clock phases, one row per update here
    assert [t.split(",")[0] for t in timing] == ["update", "1", "2", "3", "4"]
    for x, y in zip(ra, rb):
        for k in x:
            if k not in ("wall_s", "elapsed_s", "agent_steps_per_s", "rollout_agent_steps_per_s") \
                    and not k.startswith("time/"):
                assert x[k] == y[k], (x["update"], k)
    assert (a / "curves.png").stat().st_size > 10_000
    # the user's clock holds the time-to-quality clock and runs on across the resume
    for r in (ra, rb):
        el, wall = [float(x["elapsed_s"]) for x in r], [float(x["wall_s"]) for x in r]
        assert all(e >= w > 0 for e, w in zip(el, wall)) and el == sorted(el)


def test_nan_loss_stops_and_keeps_last_checkpoint(tmp_path):
    tr = Trainer(tiny(tmp_path, updates=2, checkpoint_every=1), tmp_path, progress=False)
    tr.train()
    saved = (tmp_path / "checkpoint.pt").read_bytes()
    tr.cfg = dataclasses.replace(tr.cfg, updates=3)
    with torch.no_grad():
        for p in tr.actor.parameters():
            p.fill_(float("nan"))
    with pytest.raises(TrainingError, match=r"non-finite policy output .* update 2.*last good checkpoint"):
        tr.train()
    assert (tmp_path / "checkpoint.pt").read_bytes() == saved


@pytest.mark.parametrize("closed_loop", [False, True])
def test_expert_prior_peaks_on_the_expert_action(closed_loop):
    sc = generate_scene("merge", 3)
    sim = Simulator([sc], EngineConfig(max_agents=32, road_k=8, partner_k=4), "cpu")
    sim.reset()
    prior = ExpertPrior(sim, closed_loop=closed_loop)
    C = sim.max_controlled
    logits = prior.distribution(prior.context(sim, C))
    t = int(sim.world_step[0])
    want = sim.slot_log("expert_index")[0, :C, t]
    # at reset every agent sits on its log: the closed-loop teacher agrees with the logged one
    assert (logits[0].argmax(-1) == want).all()
    # the magnet is a real distribution: KL of the expert-greedy policy to it is small, of uniform large.
    # (The closed-loop prior centres on the unquantised action, at most halfway between two bins,
    # so the nearest bin holds about half its mass or more: KL <= ln 2 plus the far bins' share.)
    greedy = torch.full_like(logits, -20.0).scatter(-1, want.long()[None, :, None], 0.0)
    assert categorical_kl(greedy, logits).max() < (0.8 if closed_loop else 0.2)
    assert categorical_kl(torch.zeros_like(logits), logits).min() > 2.0
    # the uniform floor bounds log p from below (so does the KL of any policy: <= -log(floor / N));
    # without it the far bins are practically impossible
    lp = torch.log_softmax(logits, -1)
    assert lp.min() >= math.log(0.05 / 91) - 1e-4 and lp.min() < math.log(0.05 / 91) + 0.01
    bare = torch.log_softmax(ExpertPrior(sim, closed_loop=closed_loop, floor=0.0).distribution(
        prior.context(sim, C)), -1)
    assert bare.min() < -100.0
    with pytest.raises(ValueError, match="floor"):
        ExpertPrior(sim, floor=1.0)


def test_corrective_expert_steers_back_to_the_log(device):
    """Agents of crossing_scene displaced from their logs: the teacher turns and speeds back."""
    sim = Simulator([crossing_scene()], EngineConfig(max_agents=4, road_k=8, partner_k=2), device)
    sim.reset()
    a0, i0 = (x.clone() for x in sim.corrective_expert())
    # on the log, driving straight at constant speed: no turn, (almost) no acceleration
    assert torch.allclose(a0[0, :3, 1], torch.zeros(3, device=a0.device), atol=1e-4)
    assert a0[0, :3, 0].abs().max() < 0.5
    # A 2 m left of its log (+y) and C 4 m behind its own
    sim.pos[0, 0, 1] += 2.0
    sim.pos[0, 2, 0] -= 4.0
    a, idx = sim.corrective_expert()
    assert a[0, 0, 1] < -0.02  # curvature < 0: turn right, back towards y = 0
    assert a[0, 2, 0] > 1.0  # speed up to close the gap
    assert abs(float(a[0, 2, 1])) < 1e-4
    cfg = sim.cfg
    ia, ik = idx[0, 0] // cfg.curvature_bins, idx[0, 0] % cfg.curvature_bins
    assert ik < cfg.curvature_bins // 2 and 0 <= ia < cfg.accel_bins  # the grid index agrees


def test_nearest_conflict_control_picks_k_nearest():
    sc = generate_scene("dense_intersection", 1)
    cfg = EngineConfig()
    mask = control_mask(sc, cfg, "nearest_conflict", k=3)
    assert mask.sum() == 3
    cp = np.asarray(sc.metadata["conflict_point"])
    d = np.linalg.norm(sc.log_pos[:, cfg.init_steps] - cp, axis=1)
    ok = control_mask(sc, cfg, "vehicles")
    assert d[mask].max() <= d[ok & ~mask].min()
    with pytest.raises(ValueError, match="not in the scene"):
        control_mask(sc, cfg, "ids", ids=[123456789])


def test_train_and_evaluate_cli(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", "--config", str(SMALL), "--out", str(run), "--set", "updates=1",
                     "--set", "num_worlds=2", "--set", "rollout_steps=4", "--set", "hidden=16",
                     "--set", "quantiles=4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["checkpoint"].endswith("checkpoint.pt") and "lambda" in out
    assert cli.main(["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "2",
                     "--collision-mode", "stop", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert ev["episodes"] > 0 and 0 <= ev["goal_rate"] <= 1 and ev["collision_mode"] == "stop"
    for key in ("collision_rate", "offroad_rate", "mean_cost", "mean_min_distance", "mean_speed"):
        assert key in ev
    assert cli.main(["train", "--config", str(SMALL), "--set", "nope=1"]) == 2
    assert "unknown key 'nope'" in capsys.readouterr().err


@pytest.mark.slow
def test_small_cpu_config_learns(tmp_path):
    """The README's CPU config learns to drive, on the road, and does not collapse.

    Measured (2-core CPU, 2026-11-23, ~70 s): the first finished episodes (near-uniform policy)
    reach the goal 0.02 of the time and leave the road 0.97; after 30 updates goal 0.43, off-road
    0.10, collision 0.00, entropy ~0.5. On 16 held-out merges (seed 90000) the trained policy must
    beat the built-in constant and random policies on goal rate and on off-road; a policy collapsed
    to one action (entropy ~0, or the constant policy's rates) fails."""
    from tg_gpudrive.data.sources import resolve_scenes
    from tg_gpudrive.agents.policy import load_policy
    from tg_gpudrive.agents.builtin import builtin_policy
    from tg_gpudrive.rollout import run_rollout

    cfg = dataclasses.replace(load_config(TrainConfig, SMALL), out_dir=str(tmp_path))
    Trainer(cfg, tmp_path, progress=False).train()
    r = [x for x in rows(tmp_path) if x["goal_rate"] not in ("", "nan")]
    first, last = r[0], r[-1]
    assert float(first["goal_rate"]) < 0.15 and float(first["offroad_rate"]) > 0.7
    assert float(last["offroad_rate"]) <= float(first["offroad_rate"]) - 0.4, (first, last)  # off-road falls
    assert float(last["entropy"]) > 0.1, last  # not collapsed to one action

    src = resolve_scenes("procedural:merge", n=16, seed=90000)
    scenes = [src.get(i) for i in range(16)]
    rates = {}
    for name in ("trained", "constant", "random"):
        sim = Simulator(scenes, cfg.env, "cpu")
        pol = load_policy(tmp_path, sim) if name == "trained" else builtin_policy(name, 0, "cpu")
        rates[name] = run_rollout(sim, pol, sim.episode_length)
    t = rates["trained"]
    for base in ("constant", "random"):
        b = rates[base]
        assert t["goal_rate"] > b["goal_rate"] and t["offroad_rate"] < b["offroad_rate"], (rates, base)


def test_nan_in_the_loss_itself_is_caught(tmp_path):
    tr = Trainer(tiny(tmp_path, updates=1, checkpoint_every=1), tmp_path, progress=False)
    buf, _ = tr.collect()
    buf.reward[0, 0, 0] = float("nan")
    with pytest.raises(TrainingError, match=r"non-finite loss in update 0.*last good checkpoint"):
        tr.learn(buf)


def _window_reached(win, cfg, stats) -> bool:
    win.add(stats)
    return win.reached(cfg)


def test_target_goal_rate_counts_the_last_window_of_updates_episodes():
    from tg_gpudrive.learn.quality import RATE_WINDOW
    from tg_gpudrive.learn.targets import RateWindow
    win, cfg = RateWindow(), TrainConfig(target_goal_rate=0.95)
    st = lambda g, n, c=0, o=0: {"goal": torch.tensor(float(g)), "episodes": torch.tensor(float(n)),  # noqa: E731
                                 "collided": torch.tensor(float(c)), "offroad": torch.tensor(float(o))}
    assert RATE_WINDOW == 10  # the hand-computed sums below
    for _ in range(9):
        assert not _window_reached(win, cfg, st(10, 10))  # a window is not full before its 10th update
    assert not _window_reached(win, cfg, st(0, 10))  # 90 / 100 = 0.90
    assert not _window_reached(win, cfg, st(90, 100))  # (80 + 0 + 90) / 190 = 0.895
    assert _window_reached(win, cfg, st(300, 300))  # (70 + 0 + 90 + 300) / 480 = 0.958
    assert not _window_reached(win, TrainConfig(target_goal_rate=0.0), st(100, 100))  # 0 switches the target off


def test_target_quality_needs_collision_and_offroad_within_bounds_too():
    from tg_gpudrive.learn.targets import RateWindow
    win, cfg = RateWindow(), TrainConfig(target_goal_rate=0.95, target_max_collision=0.05, target_max_offroad=0.02)
    st = lambda g, c, o: {"goal": torch.tensor(float(g)), "episodes": torch.tensor(100.0),  # noqa: E731
                          "collided": torch.tensor(float(c)), "offroad": torch.tensor(float(o))}
    for _ in range(10):
        assert not _window_reached(win, cfg, st(100, 6, 0))  # goal 1.0 but collision 0.06 > 0.05
    win = RateWindow()
    for _ in range(9):
        assert not _window_reached(win, cfg, st(96, 5, 2))
    assert _window_reached(win, cfg, st(96, 5, 2))  # 0.96 / 0.05 / 0.02 over 10 updates: every bound inclusive
    assert not _window_reached(win, cfg, st(96, 5, 12))  # off-road (9 x 2 + 12) / 1000 = 0.03 > 0.02
    win.recent = win.recent[:-1]
    assert not _window_reached(win, cfg, st(96, 15, 2))  # collision (9 x 5 + 15) / 1000 = 0.06 > 0.05


def test_the_heldout_check_decides_when_the_window_meets_the_bar(tmp_path, monkeypatch):
    """With target_heldout, a training window that meets the quality bar stops training only once
    held-out scenes meet it too: every check is a row of heldout.csv, the deciding one in target.json."""
    import tg_gpudrive.learn.targets as targets_mod

    monkeypatch.setattr(targets_mod.RateWindow, "reached", lambda self, cfg: True)  # the window always meets it
    kw = dict(updates=6, target_goal_rate=0.5, target_heldout="procedural:merge", target_heldout_worlds=2,
              target_heldout_seed=777)
    # the held-out evaluation itself: one episode in each held-out world, all their policy agents counted
    a = tmp_path / "a"
    Trainer(tiny(a, **{**kw, "updates": 1}), a, progress=False).train()
    row = list(csv.DictReader((a / "heldout.csv").open()))
    assert len(row) == 1 and row[0]["update"] == "1"
    assert int(float(row[0]["episodes"])) > 0 and 0 <= float(row[0]["goal_rate"]) <= 1
    # the decision: held-out rates below the bar twice, then above it
    goals = iter([0.1, 0.2, 0.9])
    seen = []

    def fake_rollout(sim, policy, steps, episodes_per_world=None):
        seen.append((sim.num_worlds, steps, episodes_per_world))
        policy(sim)  # the current actor drives the held-out worlds
        return {"goal_rate": next(goals), "collision_rate": 0.0, "offroad_rate": 0.0, "episodes": 7}

    monkeypatch.setattr(targets_mod, "run_rollout", fake_rollout)
    b = tmp_path / "b"
    tr = Trainer(tiny(b, **kw), b, progress=False)
    tr.train()
    assert tr.update == 3 and all(x == (2, tr.sim.episode_length, 1) for x in seen)  # each world's first episode
    checks = list(csv.DictReader((b / "heldout.csv").open()))
    assert [(c["update"], c["met"]) for c in checks] == [("1", "0"), ("2", "0"), ("3", "1")]
    target = json.loads((b / "target.json").read_text())
    assert target["update"] == 3 and target["heldout"]["goal_rate"] == 0.9
    from tg_gpudrive.config import ConfigError

    with pytest.raises(ConfigError, match="target_heldout"):  # a check with no target to meet
        dataclasses.replace(tiny(b), target_heldout="procedural:merge")


def test_time_to_quality_takes_the_first_full_window_meeting_all_three_bounds():
    from tg_gpudrive.learn.quality import time_to_quality
    row = lambda u, g, c, o, n=10: {"update": u, "wall_s": 2.0 * u, "episodes": n,  # noqa: E731
                                    "goal_rate": g, "collision_rate": c, "offroad_rate": o}
    rows = [row(1, 1.0, 0.0, 0.0), row(2, 1.0, 0.0, 0.0)]  # perfect, but shorter than the window
    assert time_to_quality(rows, window=3) is None
    rows += [row(3, 0.9, 0.1, 0.0)]  # window 1-3: goal 0.967, collision 0.033
    got = time_to_quality(rows, window=3)
    assert got["update"] == 3 and got["wall_s"] == 6.0 and abs(got["goal_rate"] - 29 / 30) < 1e-12
    assert "elapsed_s" not in got  # a metrics.csv from before the column
    rows[2]["elapsed_s"] = "7.5"
    assert time_to_quality(rows, window=3)["elapsed_s"] == 7.5
    rows = [row(1, 1.0, 0.0, 0.1), row(2, 1.0, 0.0, 0.0), row(3, 1.0, 0.0, 0.0, n=0),
            row(4, 1.0, 0.0, 0.0)]
    # window 1-3: off-road 1 / 20 = 0.05 > 0.02; window 2-4 (update 3 had no episode): 0
    assert time_to_quality(rows, window=3)["update"] == 4
    rows = [{**row(u, 0.99, 0.0, 0.0), "goal_rate": "", "episodes": "0"} for u in (1, 2, 3)]
    assert time_to_quality(rows, window=3) is None  # no episode ended: no rate, no quality


def test_policy_step_does_not_shrink_when_the_critic_loss_is_large(tmp_path):
    """Actor and critic gradients are clipped apart: rewards 10^4 times larger blow up the
    critic's regression gradient but must leave the actor's (normalised-advantage) step alone."""
    moved = []
    for scale in (1.0, 1e4):
        torch.manual_seed(0)
        tr = Trainer(tiny(tmp_path / str(scale), eta1=0.0, entropy_coef=0.0), tmp_path / str(scale),
                     progress=False)
        buf, _ = tr.collect()
        buf.reward.mul_(scale)
        before = [p.detach().clone() for p in tr.actor.parameters()]
        tr.learn(buf)
        moved.append(sum(float((p.detach() - b).abs().sum()) for p, b in zip(tr.actor.parameters(), before)))
    assert moved[0] > 0
    assert moved[1] > 0.5 * moved[0], moved


def test_logged_cost_cvar_is_the_tail_of_the_logs_cost_to_go():
    """Two logged cars side by side 3 m apart all episode (beta 4 m): cost 1 at every step, so
    the cost-to-go after k steps left is (1 - gamma^k) / (1 - gamma), the same for both cars;
    CVaR_0.5 is the mean of the upper half of those values."""
    from tg_gpudrive.learn.train import logged_cost_cvar
    from tg_gpudrive.scene import make_scene

    T = 41
    pos = np.zeros((2, T, 2))
    pos[:, :, 0] = np.arange(T) * 1.0
    pos[1, :, 1] = 3.0
    goal = np.array([[500.0, 0.0], [500.0, 3.0]])  # never reached
    sc = make_scene(pos, np.zeros((2, T)), log_vel=np.tile([10.0, 0.0], (2, T, 1)), goal=goal)
    sim = Simulator([sc], EngineConfig(max_agents=4, init_steps=1, beta=4.0, partner_k=2, road_k=4), "cpu")
    gamma, L_ = 0.9, sim.episode_length
    ctg = np.array([(1 - gamma**k) / (1 - gamma) for k in range(1, L_ + 1)] * 2)
    tail = np.sort(ctg)[len(ctg) // 2:]
    assert len(ctg) % 2 == 0
    got = float(logged_cost_cvar(sim, 0.5, gamma))
    assert got == pytest.approx(tail.mean(), rel=1e-4)
    assert float(logged_cost_cvar(sim, 0.0, gamma)) == pytest.approx(ctg.mean(), rel=1e-4)


def test_a_run_directory_holds_one_run(tmp_path, capsys):
    """A second train into the same directory goes to NAME-2 and says so; --overwrite replaces the
    run; --resume of a missing run is an error that creates nothing."""
    run = tmp_path / "run"
    small = ["--config", str(SMALL), "--set", "updates=1", "--set", "num_worlds=2", "--set", "rollout_steps=4",
             "--set", "hidden=16", "--set", "quantiles=4", "--json"]
    assert cli.main(["train", "--out", str(run), *small]) == 0
    assert cli.main(["train", "--out", str(run), *small]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["out_dir"] == str(tmp_path / "run-2") and len(rows(run)) == 1 and len(rows(tmp_path / "run-2")) == 1
    assert cli.main(["train", "--out", str(run), "--overwrite", *small]) == 0
    assert len(rows(run)) == 1 and not (tmp_path / "run-3").exists()
    capsys.readouterr()
    missing = tmp_path / "nothing"
    assert cli.main(["train", "--config", str(SMALL), "--resume", str(missing)]) == 2
    assert "no run to continue" in capsys.readouterr().err and not missing.exists()


def test_windowed_rates_are_episode_weighted_and_never_nan():
    from tg_gpudrive.learn.quality import windowed_rates

    nan = float("nan")
    r = [{"episodes": 0, "goal_rate": nan, "collision_rate": nan, "offroad_rate": nan},
         {"episodes": 10, "goal_rate": 0.5, "collision_rate": 0.1, "offroad_rate": 0.2},
         {"episodes": 0, "goal_rate": nan, "collision_rate": nan, "offroad_rate": nan},
         {"episodes": 30, "goal_rate": 1.0, "collision_rate": 0.0, "offroad_rate": 0.0}]
    assert windowed_rates(r[:1]) is None  # no episode yet: nothing to show, not NaN
    assert windowed_rates(r[:3]) == pytest.approx({"goal_rate": 0.5, "collision_rate": 0.1, "offroad_rate": 0.2})
    # (10 x 0.5 + 30 x 1.0) / 40, and the window drops the oldest rows
    assert windowed_rates(r)["goal_rate"] == pytest.approx(0.875)
    assert windowed_rates(r, window=1)["goal_rate"] == pytest.approx(1.0)
    csv_rows = [{k: str(v) for k, v in x.items()} for x in r]  # as metrics.csv gives them
    assert windowed_rates(csv_rows)["collision_rate"] == pytest.approx(0.025)


def test_evaluate_names_agent_and_scene_episodes(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", "--config", str(SMALL), "--out", str(run), "--set", "updates=1", "--set",
                     "num_worlds=2", "--set", "rollout_steps=4", "--set", "hidden=16", "--set", "quantiles=4"]) == 0
    capsys.readouterr()
    assert cli.main(["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "3",
                     "--worlds", "3", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert ev["scene_episodes"] == 3 and ev["agent_episodes"] == ev["episodes"] > 3


@pytest.mark.parametrize("damage", ["truncated", "flipped", "text", "empty"])
def test_a_damaged_checkpoint_is_a_one_line_error_naming_the_file(tmp_path, capsys, caplog, damage):
    run = tmp_path / "run"
    Trainer(tiny(run, updates=2, checkpoint_every=1), run, progress=False).train()  # two saves: a previous one
    ck = run / "checkpoint.pt"
    data = ck.read_bytes()
    ck.write_bytes({"truncated": data[: len(data) // 2], "flipped": data[:200] + bytes(b ^ 0xFF for b in data[200:400])
                    + data[400:], "text": b"not a checkpoint\n", "empty": b""}[damage])
    capsys.readouterr()
    prev = run / "checkpoint.prev.pt"
    assert prev.is_file()
    # the previous checkpoint kept beside it stands in, with a warning naming both files
    assert cli.main(["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "1",
                     "--json"]) == 0
    warned = [r.getMessage() for r in caplog.records if "previous checkpoint" in r.getMessage()]
    assert len(warned) == 1 and str(ck) in warned[0] and "damaged" in warned[0], warned
    assert f"using the previous checkpoint {prev} instead" in warned[0]
    capsys.readouterr()
    prev.unlink()  # without it: one line naming the damaged file
    assert cli.main(["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "1",
                     "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(ck) in err and "damaged" in err, err


def test_resume_falls_back_to_the_previous_checkpoint_and_drops_a_cut_metrics_row(tmp_path):
    run = tmp_path / "run"
    Trainer(tiny(run, updates=4, checkpoint_every=2), run, progress=False).train()  # saves at 2 and 4
    assert (run / "checkpoint.prev.pt").is_file()
    (run / "checkpoint.pt").write_bytes(b"")  # the newest is lost
    with (run / "metrics.csv").open("a") as f:
        f.write("5,0.1")  # a row cut short by a kill
    tr = Trainer(tiny(run, updates=5, checkpoint_every=2), run, resume=run, progress=False)
    assert tr.update == 2  # the previous checkpoint
    tr.train()
    assert [int(r["update"]) for r in rows(run)] == [1, 2, 3, 4, 5]


def test_training_writes_tensorboard_events_when_installed(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    Trainer(tiny(tmp_path, updates=2), tmp_path, progress=False).train()
    acc = EventAccumulator(str(tmp_path))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"kl/prior", "lambda", "reward/goal_progress", "entropy"} <= tags
    assert [e.step for e in acc.Scalars("lambda")] == [1, 2]


def test_kept_policies_are_listed_in_order_and_load(tmp_path):
    """keep_policy_every = 1 keeps policies/update_000001.pt and update_000002.pt, which load as policies;
    files that are not ours are passed over."""
    Trainer(tiny(tmp_path, updates=2, keep_policy_every=1), tmp_path, progress=False).train()
    (tmp_path / "policies" / "update_notes.pt").write_text("x")
    kept = kept_policies(tmp_path)
    assert [u for u, _ in kept] == [1, 2] and kept_policies(tmp_path / "nowhere") == []
    sim = Simulator([generate_scene("merge", 5)], tiny(tmp_path).env, "cpu")
    sim.reset()
    load_policy(kept[0][1], sim)(sim)
    assert kept[0][1].stat().st_size < (tmp_path / "checkpoint.pt").stat().st_size


def test_init_policy_fine_tunes_from_a_trained_run(tmp_path):
    """init_policy starts the actor and critic from another run's weights (TrafficGamer fine-tunes a
    pretrained driver) while the optimiser, multipliers and update count start fresh; the first
    rollout of the new run acts as the old policy does. A run whose networks differ is a one-line
    error naming each key, before any training."""
    from tg_gpudrive.config import ConfigError

    src = tmp_path / "src"
    Trainer(tiny(src, updates=2, lambda_init=0.0), src, progress=False).train()
    old = torch.load(src / "checkpoint.pt", weights_only=False)
    dst = tmp_path / "dst"
    tr = Trainer(tiny(dst, init_policy=str(src), env=dataclasses.replace(tiny(dst).env, beta=6.0)), dst,
                 progress=False)
    for k, v in tr.actor.state_dict().items():
        assert torch.equal(v.cpu(), old["actor"][k].cpu()), k
    for k, v in tr.critic.state_dict().items():
        assert torch.equal(v.cpu(), old["critic"][k].cpu()), k
    assert tr.update == 0 and not tr.opt.state  # a fresh optimiser and counter
    fresh = Trainer(tiny(tmp_path / "fresh"), tmp_path / "fresh", progress=False)
    assert not all(torch.equal(v, fresh.actor.state_dict()[k]) for k, v in tr.actor.state_dict().items())
    with pytest.raises(ConfigError, match=r"init_policy .*hidden 32 \(this run: 64\).*env.accel_bins"):
        Trainer(tiny(tmp_path / "bad", init_policy=str(src), hidden=64,
                     env=dataclasses.replace(tiny(dst).env, accel_bins=5)), tmp_path / "bad", progress=False)
    # more partner and road rows: the pooled encoders take the same weights
    wider = Trainer(tiny(tmp_path / "wide", init_policy=str(src),
                         env=dataclasses.replace(tiny(dst).env, road_k=2 * tiny(dst).env.road_k,
                                                 partner_k=tiny(dst).env.partner_k + 1)),
                    tmp_path / "wide", progress=False)
    for k, v in wider.actor.state_dict().items():
        assert torch.equal(v.cpu(), old["actor"][k].cpu()), k
    with pytest.raises(ConfigError, match=r"init_policy shipped: .*hidden 128"):
        Trainer(tiny(tmp_path / "bad2", init_policy="shipped"), tmp_path / "bad2", progress=False)


def test_init_policy_grows_per_slot_heads_and_a_window_onto_a_plain_policy(tmp_path):
    """A fine-tune may add per-slot heads and a motion window to a policy trained without them (the issue's
    per-agent actors and history of the other agents, fine-tuned from the shipped policy): the heads start as
    copies of the shared one and the run trains. Fewer heads, or another window, is still a one-line error."""
    from tg_gpudrive.config import ConfigError

    src = tmp_path / "src"
    Trainer(tiny(src, updates=1), src, progress=False).train()
    old = torch.load(src / "checkpoint.pt", weights_only=False)["actor"]
    dst = tmp_path / "dst"
    tr = Trainer(tiny(dst, init_policy=str(src), heads=3, actor_history=2, actor_history_partners=1, updates=1), dst,
                 progress=False)
    grown = tr.actor.state_dict()
    assert all(torch.equal(grown["head_w"][i].cpu(), old["head_w"][0].cpu()) for i in range(3))
    assert torch.equal(grown["encoder.ego.0.weight"].cpu(), old["encoder.ego.0.weight"].cpu())
    assert tr.train()["update"] == 1
    with pytest.raises(ConfigError, match=r"heads 3 \(this run: 2\)"):
        Trainer(tiny(tmp_path / "bad", init_policy=str(dst), heads=2, actor_history=2, actor_history_partners=1),
                tmp_path / "bad", progress=False)
    with pytest.raises(ConfigError, match=r"actor_history 2 \(this run: 3\)"):
        Trainer(tiny(tmp_path / "bad2", init_policy=str(dst), heads=3, actor_history=3, actor_history_partners=1),
                tmp_path / "bad2", progress=False)


def test_training_on_dense_real_scenes_drops_no_agent_and_replays_beyond_its_cap(tmp_path):
    """With env.max_agents below a real scene's agent count, every agent still gets a slot; the policy
    drives at most max_agents per world and the rest replay their logs, counted."""
    data = Path(__file__).parent / "data"
    cfg = tiny(tmp_path, updates=1, scenes=str(data), num_scenes=2, num_worlds=2, prior="expert")
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, max_agents=4))
    tr = Trainer(cfg, tmp_path, progress=False)
    assert tr.sim.report()["agents_dropped"] == 0 and tr.sim.max_agents >= 81
    assert int(tr.sim.policy_agents.sum(1).max()) <= 4
    out = tr.train()
    assert tr.left_to_replay > 0 and out["scenes_unplayable"] == 0


@pytest.mark.parametrize("steps, ended", [(4, False), (100, True)])
def test_the_final_line_reads_the_windowed_rates_never_nan(tmp_path, capsys, steps, ended):
    """A run whose last update ended no episode still reports the window's rates (or says none ended)."""
    assert cli.main(["train", "--config", str(SMALL), "--out", str(tmp_path / "run"), "--set", "updates=1",
                     "--set", "num_worlds=2", "--set", f"rollout_steps={steps}", "--set", "hidden=16",
                     "--set", "quantiles=4"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "nan" not in line and line.startswith("run: ")
    assert ("no episode ended yet" in line) != ended
    if ended:
        assert "(the last 10 updates' episodes)" in line


def test_the_timeout_rate_counts_the_episodes_that_ended_without_goal_crash_or_off_road(tmp_path):
    """metrics.csv's timeout_rate against the engine's own record of the episodes that ended
    (Simulator.finished_episodes after every step): those without a goal, a collision or leaving the road."""
    tr = Trainer(tiny(tmp_path, updates=3, rollout_steps=100, num_worlds=4), tmp_path, progress=False)
    step, late = tr.sim.step, []

    def counting_step(*a, **k):
        step(*a, **k)
        f = tr.sim.finished_episodes()
        late.append(int(((f["goal"] == 0) & (f["collided"] == 0) & (f["offroad"] == 0)).sum()))

    tr.sim.step = counting_step
    tr.train()
    got = [float(r["timeout_rate"]) * float(r["episodes"]) for r in rows(tmp_path) if float(r["episodes"]) > 0]
    assert sum(late) > 0  # some episodes ran out of time
    assert sum(got) == pytest.approx(sum(late))


def _watch_rows(lam, con, budget=1.0):
    return [{"lambda": l, "cvar": c, "cost_to_go": c, "cost_budget": budget} for l, c in zip(lam, con)]


def test_the_bar_watch_warns_once_when_the_cost_stalls_above_its_bar():
    from tg_gpudrive.learn.bar_watch import BarWatch

    cfg = dataclasses.replace(load_config(TrainConfig, SMALL), alpha=0.875)
    fed = lambda watch, rows: [m for m in map(watch.add, rows) if m]  # noqa: E731
    # stalled at 3x the bar while lambda climbs: one warning, after a whole window, naming the figures
    said = fed(BarWatch(cfg, window=10), _watch_rows(np.linspace(1, 4, 30), np.full(30, 3.0)))
    assert len(said) == 1 and "CVaR_0.875" in said[0] and "budget of 1" in said[0] and "lambda_max" in said[0]
    assert len(fed(BarWatch(cfg, window=10), _watch_rows(np.linspace(1, 4, 9), np.full(9, 3.0)))) == 0
    # coming down (3 -> 1.6: the last tenth under 0.8 x the first) or within 1.5x its budget: no warning
    assert not fed(BarWatch(cfg, window=10), _watch_rows(np.linspace(1, 4, 10), np.linspace(3.0, 1.6, 10)))
    assert not fed(BarWatch(cfg, window=10), _watch_rows(np.linspace(1, 4, 30), np.full(30, 1.4)))
    # one update of the window within the margin is enough to stay quiet
    con = np.full(10, 3.0)
    con[4] = 1.2
    assert not fed(BarWatch(cfg, window=10), _watch_rows(np.linspace(1, 4, 10), con))
    # at its cap: says so, and points to the bar instead of a cap
    capped = fed(BarWatch(dataclasses.replace(cfg, lambda_max=2.0), window=10), _watch_rows(np.full(10, 2.0),
                                                                                             np.full(10, 3.0)))
    assert len(capped) == 1 and "cap lambda_max = 2" in capped[0] and "cost_limit" in capped[0]
    # on the mean cost-to-go with lambda_on: mean; never without a constraint
    mean = fed(BarWatch(dataclasses.replace(cfg, lambda_on="mean"), window=10),
               [dict(r, cvar=0.0) for r in _watch_rows(np.ones(10), np.full(10, 3.0))])
    assert len(mean) == 1 and "mean cost-to-go" in mean[0]
    assert not fed(BarWatch(dataclasses.replace(cfg, constraint=False), window=10),
                   _watch_rows(np.ones(10), np.full(10, 3.0)))
    # the warm-up's rows (multipliers held) are not watched: a whole window after it, not from update 1
    numbered = [dict(r, update=u) for u, r in enumerate(_watch_rows(np.linspace(1, 4, 30), np.full(30, 3.0)), 1)]
    when = lambda watch: next(r["update"] for r in numbered if watch.add(r))  # noqa: E731
    assert when(BarWatch(cfg, window=10)) == 10
    assert when(BarWatch(dataclasses.replace(cfg, lambda_warmup=5), window=10)) == 15


def test_training_warns_when_its_bar_is_out_of_reach(tmp_path, monkeypatch, caplog):
    """A bar of 0 on a cost that every step pays (beta far beyond the scene) cannot be met: the trainer says so
    once its window of updates is in; the same run with a bar it meets at once says nothing."""
    from tg_gpudrive.learn import bar_watch

    monkeypatch.setattr(bar_watch, "WINDOW", 3)
    cfg = tiny(tmp_path / "far", updates=4, cost_limit_mode="absolute", cost_limit=0.0, lambda_lr=0.5)
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, beta=500.0))
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive.learn.train"):
        Trainer(cfg, tmp_path / "far", progress=False).train()
    said = [r.getMessage() for r in caplog.records if "out of reach" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("update 3:") and "budget of 0" in said[0]
    caplog.clear()
    met = dataclasses.replace(cfg, cost_limit=1e6, out_dir=str(tmp_path / "met"))
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive.learn.train"):
        Trainer(met, tmp_path / "met", progress=False).train()
    assert not [r for r in caplog.records if "out of reach" in r.getMessage()]
