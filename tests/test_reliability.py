"""Runs that cannot corrupt each other, and every mistake named: the run-directory lock, Ctrl-C and a
full disk during training, --set applied or refused with a checkpoint, ranges of config values, and a
fuzz of every --set key with random values (a config or one ConfigError naming the key; an accepted
engine config builds and steps)."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
import socket
import subprocess
import sys
import typing
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_gpudrive import checkpoint as ckpt_mod
from tg_gpudrive import cli
from tg_gpudrive.checkpoint import save_atomic
from tg_gpudrive.config import REPO_CONFIGS, ConfigError, TrainConfig, from_dict
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.learn.rundir import LOCK, RunLock
from tg_gpudrive.learn.train import Trainer
from tg_gpudrive.worldmodel.train import WorldModelConfig

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"
TINY = ["--config", str(SMALL), "--set", "num_worlds=2", "--set", "num_scenes=2", "--set", "rollout_steps=4",
        "--set", "epochs=1", "--set", "minibatches=1", "--set", "hidden=16", "--set", "quantiles=4"]


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# ----------------------------------------------------------------------------- one run per directory
def test_a_run_directory_held_by_a_live_run_refuses_a_second(tmp_path, capsys):
    run = tmp_path / "run"
    with RunLock(run):  # this process writes there, as a first `train` would
        assert cli.main(["train", "--out", str(run), *TINY, "--set", "updates=1"]) == 2
        err = capsys.readouterr().err
        assert f"PID {os.getpid()}" in err and len(err.strip().splitlines()) == 1
        assert cli.main(["train", "--out", str(run), "--overwrite", *TINY, "--set", "updates=1"]) == 2
    assert not (run / "metrics.csv").exists() and not (run / LOCK).exists()  # nothing written, lock released


def test_a_stale_lock_is_taken_over_with_a_warning(tmp_path, capsys, caplog):
    run = tmp_path / "run"
    run.mkdir()
    (run / LOCK).write_text(f"{dead_pid()} {socket.gethostname()}\n")
    assert cli.main(["train", "--out", str(run), *TINY, "--set", "updates=1", "--json"]) == 0
    assert "no longer running" in caplog.text
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["out_dir"] == str(run)
    assert not (run / LOCK).exists()


def test_two_runs_started_together_do_not_share_a_directory(tmp_path):
    """Two `train` processes into one --out at once: one runs, the other fails at once naming it."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "tg_gpudrive.cli", "train", "--out", str(run), *TINY, "--set", "updates=3",
           "--set", "device=cpu"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    codes = sorted(p.returncode for p in procs)
    runs = [d for d in tmp_path.iterdir() if (d / "metrics.csv").exists()]
    if codes == [0, 0]:  # the second started after the first had finished: it went to run-2
        assert len(runs) == 2, (outs, list(tmp_path.iterdir()))
    else:
        assert codes == [0, 2], outs
        loser = next(err for (_, err), p in zip(outs, procs) if p.returncode == 2)
        assert "is being written by another run (PID" in loser
        assert runs == [run]
    for d in runs:  # each metrics.csv holds one run: updates 1, 2, 3 once
        lines = (d / "metrics.csv").read_text().strip().splitlines()[1:]
        assert len(lines) == 3


# ----------------------------------------------------------------------------- Ctrl-C and a full disk
def test_ctrl_c_saves_the_last_finished_update_and_says_how_to_resume(tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    real = Trainer.collect
    calls = {"n": 0}

    def collect(self):
        calls["n"] += 1
        if calls["n"] == 2:  # during the second update
            os.kill(os.getpid(), signal.SIGINT)
        return real(self)

    monkeypatch.setattr(Trainer, "collect", collect)
    assert cli.main(["train", "--out", str(run), *TINY, "--set", "updates=5", "--set", "checkpoint_every=10"]) == 130
    err = capsys.readouterr().err
    assert "Ctrl-C" in err and f"tg-gpudrive train --resume {run}" in err
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["update"] == 2  # the update under way finished, then was saved
    assert not (run / LOCK).exists()
    monkeypatch.setattr(Trainer, "collect", real)
    assert cli.main(["train", "--resume", str(run)]) == 0
    assert torch.load(run / "checkpoint.pt", weights_only=False)["update"] == 5


def test_a_full_disk_leaves_the_last_good_checkpoint_and_no_tmp(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    save_atomic({"update": 1}, path, keep_previous=True)

    def full(obj, f):
        f.write(b"x" * 100)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ckpt_mod.torch, "save", full)
    with pytest.raises(OSError, match=f"could not save {path} .No space left on device.; {path} is the last good"):
        save_atomic({"update": 2}, path, keep_previous=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    assert torch.load(path, weights_only=False)["update"] == 1


def test_train_on_a_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    def full(obj, f):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ckpt_mod.torch, "save", full)
    assert cli.main(["train", "--out", str(tmp_path / "run"), *TINY, "--set", "updates=1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("tg-gpudrive train: error: could not save") and "No space left" in err[-1]
    assert not list((tmp_path / "run").glob("*.tmp"))


def test_one_line_errors_by_hand(capsys):
    """Bad input exits 2 with one line naming the program, another OS error exits 1 with its file, a clean run
    keeps its code; a bug (here a KeyError) is not swallowed."""
    from tg_gpudrive.cli import one_line_errors

    def fail(e):
        def run():
            raise e
        return run

    assert one_line_errors("tool.py", lambda: 0) == 0
    assert one_line_errors("tool.py", fail(FileNotFoundError("--runs: no checkpoint at /x"))) == 2
    assert one_line_errors("tool.py", fail(OSError(errno.ENOSPC, "No space left on device", "/d/f"))) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["tool.py: error: --runs: no checkpoint at /x", "tool.py: error: No space left on device: /d/f"]
    with pytest.raises(KeyError):
        one_line_errors("tool.py", fail(KeyError("a bug")))


@pytest.mark.parametrize("script", ["heldout_eval", "advantage_balance", "crash_anatomy", "goal_misses",
                                    "budget_by_knob", "slim_checkpoints"])
def test_a_script_given_a_missing_run_says_so_in_one_line(script, tmp_path):
    """The analysis scripts follow the CLI's rule: a run that is not there is one line and exit 2, not a
    traceback, and it says so before any scene is built (the default procedural scenes take minutes here)."""
    missing = str(tmp_path / "no_such_run")
    args = {"heldout_eval": ["--runs", missing, "--scenes", "procedural:merge", "--num-scenes", "1",
                             "--device", "cpu"],
            "advantage_balance": ["--runs", missing, "--device", "cpu"],
            "crash_anatomy": ["--policies", missing, "--scenes", "procedural:merge", "--device", "cpu"],
            "goal_misses": ["--policies", missing, "--scenes", "procedural:merge", "--device", "cpu"],
            "budget_by_knob": ["--checkpoint", missing, "--scenes", "procedural:merge", "--device", "cpu"],
            "slim_checkpoints": [missing]}[script]
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(root / "scripts" / f"{script}.py"), *args], capture_output=True,
                         text=True, timeout=300)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and lines and lines[-1].startswith(f"{script}.py: error: "), out.stderr[-800:]
    assert "no_such_run" in lines[-1] and "Traceback" not in out.stderr


# ----------------------------------------------------------------------------- --set with a checkpoint
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    run = tmp_path_factory.mktemp("ck") / "run"
    assert cli.main(["train", "--out", str(run), *TINY, "--set", "updates=1", "--set", "env.partner_k=4"]) == 0
    return run


def _evaluate(run, *extra):
    return cli.main(["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "2",
                     "--json", *extra])


def test_evaluate_applies_the_keys_a_network_allows(trained, capsys):
    assert _evaluate(trained, "--set", "collision_mode=remove", "--set", "beta=2", "--set", "view_angle=120") == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["collision_mode"] == "remove"
    assert _evaluate(trained, "--set", "max_agents=3") == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["max_agents"] == 3


@pytest.mark.parametrize("key,value,words", [
    ("partner_k", "8", "partner_k=8: fixed by the network trained in"),
    ("dynamics", "delta_local", "dynamics"),
    ("bogus_key", "3", "unknown key 'bogus_key'"),
])
def test_evaluate_refuses_fixed_and_unknown_keys(trained, capsys, key, value, words):
    assert _evaluate(trained, "--set", f"{key}={value}") == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1


def test_resume_names_a_key_the_saved_networks_fix(trained, capsys):
    assert cli.main(["train", "--resume", str(trained), "--set", "env.partner_k=3"]) == 2
    err = capsys.readouterr().err
    assert "env.partner_k=3: fixed by the network" in err and "without --resume" in err


# ----------------------------------------------------------------------------- value ranges
@pytest.mark.parametrize("text,key", [
    ("env.beta=-1", "env.beta"), ("lr=0", "lr"), ("lr=-0.001", "lr"), ("gamma=1.5", "gamma"),
    ("minibatches=1000", "minibatches"), ("env.partner_k=0", "env.partner_k"), ("env.goal_radius=.nan", "env.goal_radius"),
    ("env.accel_bins=4", "env.accel_bins"), ("epochs=0", "epochs"), ("alpha=1", "alpha"),
])
def test_out_of_range_values_are_refused_naming_key_and_file(tmp_path, capsys, text, key):
    assert cli.main(["train", "--out", str(tmp_path / "run"), *TINY, "--set", text]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(SMALL) in err and key in err
    assert not (tmp_path / "run" / "metrics.csv").exists()


def test_broken_yaml_in_a_file_or_a_set_value_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("lr: [1, 2\n")
    assert cli.main(["train", "--config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{bad}: invalid YAML at line 2" in err
    assert cli.main(["train", *TINY, "--set", "lr=[1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--set lr=[1: the value is not valid YAML" in err


def test_convert_refuses_a_nan_tolerance_and_a_file_as_store(tmp_path, capsys):
    src = str(REPO_CONFIGS.parent / "tests" / "data")
    assert cli.main(["convert", src, "--out", str(tmp_path / "s"), "--simplify", "nan"]) == 2
    assert "simplify tolerance" in capsys.readouterr().err
    (tmp_path / "f").write_text("x")
    assert cli.main(["convert", src, "--out", str(tmp_path / "f")]) == 2
    assert "a file is there" in capsys.readouterr().err


# ----------------------------------------------------------------------------- fuzz of --set keys
VALUES = [-1, 0, 1, 2, 3, 7, 0.5, -0.25, 1e9, float("nan"), float("inf"), "x", "stop", [1, 2], True, None]


def leaf_keys(cls, prefix="") -> list[tuple[str, typing.Any]]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out += leaf_keys(tp, prefix + f.name + ".")
        else:
            out.append((prefix + f.name, tp))
    return out


def nest(key: str, value) -> dict:
    d: dict = {}
    node = d
    parts = key.split(".")
    for p in parts[:-1]:
        node[p] = {}
        node = node[p]
    node[parts[-1]] = value
    return d


def test_fuzz_every_set_key_gives_a_config_or_one_error_naming_it():
    """Every leaf key of TrainConfig (engine, reward and augmentation keys included) with every value
    of VALUES (and 3 random draws of up to 3 keys at once, 150 times): either a config or a ConfigError
    naming a key given; engine configs accepted with a single key build a Simulator that steps."""
    rng = np.random.default_rng(0)
    keys = [k for k, _ in leaf_keys(TrainConfig)]
    scene = generate_scene("merge", 0)
    stepped = 0
    trials = [[(k, v)] for k in keys for v in VALUES]
    trials += [[(keys[i], VALUES[j]) for i, j in zip(rng.integers(len(keys), size=3), rng.integers(len(VALUES), size=3))]
               for _ in range(150)]
    for trial in trials:
        data: dict = {}
        for k, v in trial:
            for top, sub in nest(k, v).items():
                data[top] = {**data.get(top, {}), **sub} if isinstance(sub, dict) else sub
        try:
            cfg = from_dict(TrainConfig, data, "fuzz.yaml")
        except ConfigError as e:
            msg = str(e)
            assert msg.startswith("fuzz.yaml: ") and "\n" not in msg, msg
            assert any(k in msg or k.split(".")[-1] in msg for k, _ in trial), (trial, msg)
            continue
        if len(trial) == 1 and trial[0][0].startswith("env.") and trial[0][0] not in (
                "env.use_graph", "env.max_agents") and stepped < 60:
            env = dataclasses.replace(cfg.env, max_agents=max(cfg.env.max_agents, scene.num_agents))
            sim = Simulator([scene], env, "cpu")
            sim.reset()
            for _ in range(3):
                sim.step()  # the action buffers as they are
            stepped += 1
    assert stepped >= 20


def test_a_script_without_a_main_guard_is_told_why_scene_workers_died(tmp_path):
    """Many procedural scenes are generated in spawned worker processes, which import the main script
    again: a script that builds scenes at its top level kills them. The error says so and names the guard,
    instead of a bare BrokenProcessPool."""
    script = tmp_path / "no_guard.py"
    script.write_text("import os\n"
                      "os.cpu_count = lambda: 3  # enough cores for the worker pool on any machine\n"
                      "from tg_gpudrive.data.sources import ProceduralSource\n"
                      "ProceduralSource(['merge'], n=64).get_many(range(64))\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode != 0
    # the last line of the script's own traceback: the dead workers' semaphores may draw a warning from
    # multiprocessing's resource tracker (another process) after it, at shutdown
    lines = [ln for ln in r.stderr.strip().splitlines() if "resource_tracker" not in ln]
    last = lines[-1]
    assert last.startswith("RuntimeError: procedural:merge: the worker processes") and '__name__ == "__main__"' in last


def test_a_run_without_matplotlib_keeps_its_files_and_says_why_no_curves(tmp_path, monkeypatch, caplog):
    """curves.png needs the render extra; without it the run's end logs one line and returns, so a finished
    run is never reported as a crash."""
    import builtins

    from tg_gpudrive.learn.runlog import RunLog

    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ModuleNotFoundError(f"No module named '{name}'", name="matplotlib")
        return real_import(name, *args, **kwargs)

    run = RunLog(tmp_path, lead=True)
    run.metrics({"update": 1, "agent_steps": 10, "goal_rate": 0.5})
    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    with caplog.at_level("WARNING"):
        assert run.plot() is None
    assert "matplotlib is not installed" in caplog.text
    assert (tmp_path / "metrics.csv").exists() and not (tmp_path / "curves.png").exists()


def test_an_empty_set_value_clears_a_string_key():
    """`--set init_policy=` (or `init_policy:` left empty in YAML) is the empty string: a config that fine-tunes
    a checkpoint can be trained from scratch without editing it."""
    cfg = from_dict(TrainConfig, {"init_policy": None}, "x.yaml")
    assert cfg.init_policy == ""
    with pytest.raises(ConfigError, match="x.yaml: lr: expected a number"):
        from_dict(TrainConfig, {"lr": None}, "x.yaml")
    # where the empty string would mean the working directory, it is refused
    for key in ("scenes", "out_dir", "device"):
        with pytest.raises(ConfigError, match=f"x.yaml: {key}: must not be empty"):
            from_dict(TrainConfig, {key: None}, "x.yaml")
    with pytest.raises(ValueError, match="scene spec is empty"):
        resolve_scenes("  ")
    for key in ("scenes", "out_dir"):  # the world model's trainer too
        with pytest.raises(ConfigError, match=f"x.yaml: {key}: must not be empty"):
            from_dict(WorldModelConfig, {key: None}, "x.yaml")
