"""A trained policy's acting temperature (TrainConfig.act_temperature, `--temperature`): its samples follow
the distribution sharpened by T (a NumPy softmax of logits / T; a Gaussian's standard deviation x T), 0
takes the mode, a checkpoint acts at its own temperature unless told otherwise, and a bad value is a
one-line error naming the flag or the key."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from tg_gpudrive import cli
from tg_gpudrive.agents import open_policy
from tg_gpudrive.agents.policy import PolicyHead, tempered
from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.config import REPO_CONFIGS, ConfigError, TrainConfig, from_dict, load_config, to_dict
from tg_gpudrive.data.sources import resolve_scenes

LOGITS = [1.5, 0.2, -0.7, 0.9, -2.0]
SCENES = "procedural:merge"


def softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max())
    return e / e.sum()


@pytest.mark.parametrize("t", [1.0, 0.5, 0.2, 2.0])
def test_discrete_samples_follow_the_softmax_of_logits_over_t(device, t):
    torch.manual_seed(0)
    logits = torch.tensor(LOGITS, device=device)
    draws = PolicyHead(True).dist(tempered(logits.expand(200_000, -1), t)).sample().cpu().numpy()
    freq = np.bincount(draws, minlength=len(LOGITS)) / draws.size
    np.testing.assert_allclose(freq, softmax(np.array(LOGITS) / t), atol=0.004)


def test_continuous_samples_keep_their_mean_and_shrink_their_spread_by_t(device):
    torch.manual_seed(0)
    mean = torch.tensor([0.3, -1.0], device=device).expand(200_000, -1)
    log_std = torch.log(torch.tensor([0.8, 0.2], device=device)).expand(200_000, -1)
    x = PolicyHead(False).dist(tempered((mean, log_std), 0.5)).sample().cpu().numpy()
    np.testing.assert_allclose(x.mean(0), [0.3, -1.0], atol=0.01)
    np.testing.assert_allclose(x.std(0), [0.4, 0.1], rtol=0.01)
    assert tempered((mean, log_std), 1.0)[1] is log_std  # temperature 1: the actor's own output


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """An untrained checkpoint (its actions are spread out, so sampling shows) and a copy that acts at 0."""
    from tg_gpudrive.learn.train import Trainer

    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    runs = {}
    for name, t in (("sampled", 1.0), ("mode", 0.0)):
        run = tmp_path_factory.mktemp(name)
        cfg_t = dataclasses.replace(cfg, num_worlds=1, num_scenes=1, rollout_steps=4, epochs=1, minibatches=1,
                                    hidden=16, quantiles=4, updates=1, prior="expert", cost_limit_mode="absolute",
                                    act_temperature=t, out_dir=str(run))
        Trainer(cfg_t, run, progress=False).save()
        runs[name] = run
    return runs


def _actions(run, seed: int, temperature=None) -> np.ndarray:
    src = resolve_scenes(SCENES, n=2, seed=0)
    opened = open_policy(str(run), [src[0], src[1]], "cpu", temperature=temperature)
    torch.manual_seed(seed)
    opened.policy(opened.sim)
    return opened.sim.actions_index.cpu().numpy().copy()


def test_a_checkpoint_acts_at_its_own_temperature_unless_told(tiny_run):
    # sampled: two seeds draw different actions; at the checkpoint's temperature 0, or when told 0, the same
    assert not np.array_equal(_actions(tiny_run["sampled"], 0), _actions(tiny_run["sampled"], 1))
    assert np.array_equal(_actions(tiny_run["mode"], 0), _actions(tiny_run["mode"], 1))
    assert np.array_equal(_actions(tiny_run["sampled"], 0, temperature=0.0),
                          _actions(tiny_run["sampled"], 1, temperature=0.0))
    assert np.array_equal(_actions(tiny_run["sampled"], 0, temperature=0.0), _actions(tiny_run["mode"], 0))
    # told 1, the checkpoint that acts at 0 samples again
    assert not np.array_equal(_actions(tiny_run["mode"], 0, temperature=1.0),
                              _actions(tiny_run["mode"], 1, temperature=1.0))


def test_evaluate_reports_the_temperature_it_acted_at(tiny_run, capsys):
    def temperature(*flags):
        assert cli.main(["evaluate", "--checkpoint", str(tiny_run["mode"]), "--scenes", SCENES, "--episodes", "1",
                         "--device", "cpu", "--json", *flags]) == 0
        return json.loads(capsys.readouterr().out.strip().splitlines()[-1])["temperature"]

    assert temperature() == 0.0 and temperature("--temperature", "0.7") == 0.7
    assert temperature("--deterministic") == 0.0


@pytest.mark.parametrize("flags, message", [
    (["--temperature", "-1"], "--temperature: expected a number >= 0"),
    (["--deterministic", "--temperature", "0.5"], "--deterministic is --temperature 0"),
])
def test_a_bad_temperature_is_a_one_line_error(tiny_run, capsys, flags, message):
    assert cli.main(["evaluate", "--checkpoint", str(tiny_run["sampled"]), "--scenes", SCENES, "--episodes", "1",
                     "--device", "cpu", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_a_negative_act_temperature_names_the_key():
    bad = {**to_dict(TrainConfig()), "act_temperature": -0.5}
    with pytest.raises(ConfigError, match="act_temperature"):
        from_dict(TrainConfig, bad, "run.yaml")


def test_the_shipped_policy_acts_sharpened():
    """The packaged policy's temperature, chosen on its training scenes (BENCHMARKS.md): below 1, not the mode."""
    t = load_checkpoint("shipped", "shipped")["config"]["act_temperature"]
    assert 0 < t < 1 and math.isfinite(t)
