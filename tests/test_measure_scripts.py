"""The scripts of the GPU jobs (scripts/gpu_measure.sh, scripts/gpu_real.sh): each Python one answers --help and
runs on small files made here (metrics.csv / timing.csv / checkpoints written by hand, so no simulator is built),
and the real-scene job trains the recipe it names."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tg_gpudrive.checkpoint import POLICY, WORLD_MODEL, load_checkpoint

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"
MEASURE_SCRIPTS = ("slim_checkpoints", "summarize_runs", "scale_timing", "plot_curves")

METRICS = ("update", "agent_steps", "episodes", "goal_rate", "collision_rate", "offroad_rate", "entropy",
           "kl/prior", "lambda", "lambda_max", "cvar", "cost_budget", "wall_s", "elapsed_s",
           "agent_steps_per_s", "rollout_agent_steps_per_s")


def run(name: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPTS / f"{name}.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def write_csv(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def metrics_row(update: int, episodes, goal, collision=0.01, offroad=0.0) -> dict:
    return dict(zip(METRICS, (update, 100 * update, episodes, goal, collision, offroad, 1.5, 0.3, 0.2, 1.0, 0.1,
                              0.5, 2.0 * update, 2.5 * update, 1000 * update, 2000 * update)))


@pytest.mark.parametrize("name", MEASURE_SCRIPTS)
def test_help(name):
    out = run(name, "--help")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: {name}.py")


def test_summarize_runs(tmp_path):
    write_csv(tmp_path / "good" / "metrics.csv", [metrics_row(u, 10, 0.97) for u in range(1, 15)])
    write_csv(tmp_path / "early" / "metrics.csv", [metrics_row(u, "", "", "", "") for u in range(1, 3)])
    write_csv(tmp_path / "wm" / "metrics.csv", [{"step": 1, "loss": 0.5}])  # a world model's log: skipped
    out = run("summarize_runs", tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "early: 2 updates, goal nan coll nan off nan (0 episodes), ent 1.50 klp 0.30 lambda 0.20 (max 1.00) "
        "cvar 0.10 budget 0.50 wall 4s",
        "  time to quality: not reached",
        "good: 14 updates, goal 0.970 coll 0.010 off 0.000 (100 episodes), ent 1.50 klp 0.30 lambda 0.20 "
        "(max 1.00) cvar 0.10 budget 0.50 wall 28s",
        "  time to quality: 20 s of rollouts and updates, 25 s elapsed (update 10)"]


def test_summarize_runs_compares_quality_stops_across_gpu_counts(tmp_path):
    """Runs that stopped at quality (target.json): one GPU at seeds 0 (cold 60 s, warm 30 s) and 1 (40 s), two GPUs
    at seed 0 (18 s) and four at seeds 0 and 1 (15 s, 20 s), a two-GPU run of a seed with no one-GPU run and one
    with no config.json (no seed): summarised, not compared. Each several-GPU run is compared with its seed's
    fastest one-GPU run; the ratios per GPU count sum the seeds both have: four GPUs (15 + 20) / (30 + 40) =
    0.50x."""
    runs = {"a_one_s0": (1, 0, 60.0), "a_one_s0_warm": (1, 0, 30.0), "a_one_s1": (1, 1, 40.0), "b_two_s0": (2, 0, 18.0),
            "b_two_s7": (2, 7, 10.0), "c_four_s0": (4, 0, 15.0), "c_four_s1": (4, 1, 20.0)}
    for name, (gpus, seed, wall) in runs.items():
        write_csv(tmp_path / name / "metrics.csv", [{**metrics_row(u, 10, 0.97), "ranks": gpus} for u in range(1, 4)])
        (tmp_path / name / "config.json").write_text(json.dumps({"seed": seed}))
        (tmp_path / name / "target.json").write_text(json.dumps({"update": 3, "wall_s": wall, "heldout": {
            "goal_rate": 0.96, "collision_rate": 0.02, "offroad_rate": 0.01, "episodes": 3463}}))
    write_csv(tmp_path / "d_two" / "metrics.csv", [{**metrics_row(1, 10, 0.97), "ranks": 2}])
    (tmp_path / "d_two" / "target.json").write_text(json.dumps({"update": 1, "wall_s": 5.0}))  # no config.json
    out = run("summarize_runs", tmp_path)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert "  quality stop: 30.0 s (update 3), held out goal 0.960 coll 0.020 off 0.010 (3463 episodes)" in lines
    assert "  quality stop: 5.0 s (update 1)" in lines
    assert lines[-5:] == ["b_two_s0: 2 GPUs 18.0 s against 30.0 s on one (seed 0): 0.60x",
                          "c_four_s0: 4 GPUs 15.0 s against 30.0 s on one (seed 0): 0.50x",
                          "c_four_s1: 4 GPUs 20.0 s against 40.0 s on one (seed 1): 0.50x",
                          "2 GPUs: 0.60x one GPU's time to quality over seeds [0]",
                          "4 GPUs: 0.50x one GPU's time to quality over seeds [0, 1]"]


def test_scale_timing(tmp_path):
    write_csv(tmp_path / "scale2" / "metrics.csv", [metrics_row(u, 1, 0.0) for u in range(1, 7)])
    write_csv(tmp_path / "scale2" / "timing.csv", [{"update": u, "rank": r, "rollout_s": 0.1 * u + r,
                                                    "wait_s": 0.01 * r, "update_s": 0.2}
                                                   for u in range(1, 7) for r in (0, 1)])
    (tmp_path / "scale1").mkdir()  # a run that left nothing
    (tmp_path / "other").mkdir()
    out = run("scale_timing", tmp_path, "--glob", "scale*")
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "scale1: nan agent steps/s end to end, rollout nan",
        "scale2: 4,500 agent steps/s end to end, rollout 9,000",
        "  rank 0: rollout 0.450 s, wait 0.000 s, update 0.200 s",
        "  rank 1: rollout 1.450 s, wait 0.010 s, update 0.200 s"]


def test_slim_checkpoints(tmp_path):
    weights = {"w": torch.arange(4.0)}
    full = {"kind": POLICY, "config": {"hidden": 32, "env": {"partner_k": 8}}, "actor": weights,
            "critic": weights, "update": 7, "lagrange": {"lam": torch.tensor(0.5)},
            "opt": {"state": torch.zeros(50_000)}, "engine": torch.zeros(50_000), "rng": {}, "wall": 1.0}
    (tmp_path / "cce").mkdir()
    torch.save(full, tmp_path / "cce" / "checkpoint.pt")
    (tmp_path / "old").mkdir()  # written before checkpoints named their kind
    torch.save({k: v for k, v in full.items() if k != "kind"}, tmp_path / "old" / "checkpoint.pt")
    (tmp_path / "wm").mkdir()
    torch.save({"kind": WORLD_MODEL, "hparams": {}, "opt": {}}, tmp_path / "wm" / "checkpoint.pt")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    untouched = {n: (tmp_path / n / "checkpoint.pt").read_bytes() for n in ("wm", "bad")}
    big = (tmp_path / "cce" / "checkpoint.pt").stat().st_size

    out = run("slim_checkpoints", tmp_path)
    assert out.returncode == 0, out.stderr
    assert "bad" in out.stderr and "cannot be read" in out.stderr
    for name in ("cce", "old"):
        path = tmp_path / name / "checkpoint.pt"
        load_checkpoint(path, kind=POLICY)  # what evaluate and init_policy read
        ck = torch.load(path, weights_only=False)  # the kept entries as stored
        assert sorted(ck) == ["actor", "config", "critic", "kind", "lagrange", "update"]
        assert ck["config"] == full["config"] and ck["update"] == 7 and torch.equal(ck["actor"]["w"], weights["w"])
        assert path.stat().st_size < big / 10
    for name, data in untouched.items():
        assert (tmp_path / name / "checkpoint.pt").read_bytes() == data
    slim = (tmp_path / "cce" / "checkpoint.pt").stat().st_size
    assert run("slim_checkpoints", tmp_path).returncode == 0  # slimming again keeps what the slim file holds
    assert sorted(torch.load(tmp_path / "cce" / "checkpoint.pt", weights_only=False)) == [
        "actor", "config", "critic", "kind", "lagrange", "update"]
    assert (tmp_path / "cce" / "checkpoint.pt").stat().st_size == slim


def test_plot_curves(tmp_path):
    write_csv(tmp_path / "metrics.csv", [metrics_row(u, 10, 0.5) for u in range(1, 4)])
    out = run("plot_curves", tmp_path / "metrics.csv", tmp_path / "curves.png")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"


def test_profile_train_names_every_phase_of_an_iteration():
    """scripts/profile_train.py on two CPU worlds: every named phase of the rollout and the update is
    there, with host time, and the iteration's own wall clock is split into rollout and update."""
    import json

    r = subprocess.run([sys.executable, str(SCRIPTS / "profile_train.py"), "--config",
                        str(SCRIPTS.parent / "configs" / "train" / "small_cpu.yaml"), "--set", "num_worlds=2",
                        "--set", "rollout_steps=4", "--set", "hidden=16", "--set", "quantiles=4",
                        "--warmup", "1", "--iters", "1", "--rows", "0", "--json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    phases = res["phases"]
    want = {f"rollout/{p}" for p in ("live_rows", "actor", "sample", "buffers", "critic", "magnet", "magnet.context",
                                     "magnet.forward", "engine")}
    want |= {f"update/{p}" for p in ("advantages", "lagrange", "live_rows", "forward", "backward", "optimizer")}
    assert want <= set(phases), sorted(phases)
    assert all(phases[p]["host_ms"] > 0 for p in want)
    # per step: the engine and the magnet's context; after the steps, once: the values and the magnet's logits
    assert phases["rollout/engine"]["calls"] == 4 and phases["rollout/magnet"]["calls"] == 4
    assert phases["rollout/critic"]["calls"] == 1 and phases["rollout/magnet.forward"]["calls"] == 1
    assert res["rollout_s"] > 0 and res["update_s"] > 0 and res["agent_steps_per_s"] > 0


def test_bench_world_model_times_the_forward_per_row_count():
    """scripts/bench_world_model.py's forward part on the CPU: one float32 timing per row count (no bf16
    without CUDA), as positive milliseconds."""
    import json

    r = run("bench_world_model", "--device", "cpu", "--threads", "1", "--skip", "train,inference,prior",
            "--forward-rows", 8, 32, "--steps", 1)
    assert r.returncode == 0, r.stderr[-2000:]
    fwd = json.loads(r.stdout)["forward"]
    assert set(fwd) == {"8_float32_ms", "32_float32_ms"} and min(fwd.values()) > 0


def test_budget_by_knob_prints_the_logs_and_the_policys_risk_per_knob():
    """scripts/budget_by_knob.py on two procedural scenes: a row per (beta, alpha), the budget is cost_limit
    times the logs' CVaR, CVaR grows with alpha, and no cost fires for anyone at beta 0.5 m (closer than
    any two boxes' centres can come without a collision)."""
    import json

    r = subprocess.run([sys.executable, str(SCRIPTS / "budget_by_knob.py"), "--checkpoint", "constant",
                        "--num-scenes", "2", "--betas", "0.5", "6", "--alphas", "0", "0.5", "--cost-limit", "0.5",
                        "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [json.loads(x) for x in r.stdout.strip().splitlines()]
    assert [(x["beta"], x["alpha"]) for x in rows] == [(0.5, 0.0), (0.5, 0.5), (6.0, 0.0), (6.0, 0.5)]
    for x in rows:
        assert x["budget"] == pytest.approx(0.5 * x["logs_cvar"]) and x["logs_states"] > 0
    assert rows[0]["logs_cvar"] == 0 and rows[0]["policy_cvar"] == 0
    assert rows[3]["logs_cvar"] >= rows[2]["logs_cvar"] > 0 and rows[3]["policy_cvar"] >= rows[2]["policy_cvar"]
    # an engine setting for every beta: the hinge cost is below the step cost wherever that fires, and not 0
    r = subprocess.run([sys.executable, str(SCRIPTS / "budget_by_knob.py"), "--checkpoint", "constant",
                        "--num-scenes", "2", "--betas", "6", "--alphas", "0", "--set", "cost_shape=hinge", "--json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    hinge = json.loads(r.stdout.strip().splitlines()[0])
    assert 0 < hinge["logs_cvar"] < rows[2]["logs_cvar"]


def test_the_real_scene_job_trains_the_shipped_recipe(tmp_path):
    """scripts/gpu_real.sh builds each run's scene mix itself (shares, generator knobs, the real store); for a plan
    line on `womd_dev_train+fast20` with no extra generator knobs it is the mix of configs/train/real_mix.yaml, the
    shipped policy's recipe, with the stores' folder in place of the default cache."""
    import yaml

    job = (SCRIPTS / "gpu_real.sh").read_text().splitlines()
    knobs = next(line for line in job if line.startswith("urban_knobs="))
    start = job.index(next(line for line in job if line.startswith("mix()")))
    body = job[start:job.index("}", start) + 1]
    script = "\n".join([f"stores={tmp_path}", knobs, *body, "mix womd_dev_train+fast20"])
    got = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60, check=True).stdout.strip()
    recipe = yaml.safe_load((SCRIPTS.parent / "configs" / "train" / "real_mix.yaml").read_text())["scenes"]
    assert got == recipe.replace("~/.cache/tg_gpudrive", str(tmp_path))
