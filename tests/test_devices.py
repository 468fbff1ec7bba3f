"""Devices: "auto" is the default everywhere (cuda when Warp and torch see one, else cpu), an
explicit CUDA request without CUDA is a one-line error raised before anything is built (a
ValueError in Python, exit code 2 from the CLI), and the JSON reports name the device that ran.

Most tests patch `simulator.cuda_unavailable` (the one place that asks Warp and torch), so the
"auto -> cuda" branch is checked on a CPU-only machine without building anything on CUDA; the
tests of the real, unpatched path skip where a GPU is present."""

from __future__ import annotations

import json

import pytest
import torch

from tg_gpudrive import cli
from tg_gpudrive.engine import simulator as simulator_mod
from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, TrainConfig
from tg_gpudrive.learn import distributed
from tg_gpudrive.engine.simulator import Simulator, cuda_available, resolve_device
from tg_gpudrive.envs import vector
from tg_gpudrive.envs.single import TGSingleAgentEnv

from scenes import crossing_scene

HAS_CUDA = cuda_available()
no_gpu_only = pytest.mark.skipif(HAS_CUDA, reason="checks the real no-CUDA path; a GPU is visible here")
NO_WARP_CUDA = "no CUDA device is visible (Warp sees none)"


@pytest.fixture
def without_cuda(monkeypatch):
    monkeypatch.setattr(simulator_mod, "cuda_unavailable", lambda: NO_WARP_CUDA)


@pytest.fixture
def with_cuda(monkeypatch):
    # only resolution is exercised under this patch: nothing may be built on the pretend GPU
    monkeypatch.setattr(simulator_mod, "cuda_unavailable", lambda: None)
    monkeypatch.setattr(simulator_mod.wp, "get_cuda_device_count", lambda: 2)


def test_auto_resolves_to_what_is_there(without_cuda):
    assert resolve_device("auto") == "cpu"
    assert resolve_device(None) == "cpu"  # None is the default, not a separate cpu
    assert resolve_device("cpu") == "cpu"


def test_auto_resolves_to_cuda_when_visible(with_cuda):
    assert resolve_device("auto") == "cuda:0"
    assert resolve_device("cuda") == "cuda:0"
    assert resolve_device(torch.device("cuda", 1)) == "cuda:1"
    with pytest.raises(ValueError, match=r"device='cuda:2': only 2 CUDA device\(s\) visible"):
        resolve_device("cuda:2")


def test_auto_matches_this_machine():
    assert resolve_device("auto") == ("cuda:0" if HAS_CUDA else "cpu")


def test_cuda_without_cuda_is_one_clear_line(without_cuda):
    with pytest.raises(ValueError) as e:
        resolve_device("cuda")
    assert str(e.value) == f"device='cuda': {NO_WARP_CUDA}; use device='cpu' or 'auto'"
    with pytest.raises(ValueError) as e:
        resolve_device("cuda:1", flag="--device")
    assert str(e.value) == f"--device cuda:1: {NO_WARP_CUDA}; use --device cpu or auto"
    with pytest.raises(ValueError, match="expected auto, cpu, cuda or cuda:N"):
        resolve_device("tpu")


def test_train_config_device_auto(with_cuda, monkeypatch):
    """TrainConfig's device defaults to auto; the trainer's device (local_device) resolves it."""
    assert TrainConfig().device == "auto"
    assert distributed.local_device("auto") == "cuda:0"
    monkeypatch.setattr(simulator_mod, "cuda_unavailable", lambda: NO_WARP_CUDA)
    assert distributed.local_device("auto") == "cpu"
    assert distributed.local_device("cpu") == "cpu"


@no_gpu_only
def test_simulator_cuda_fails_before_building(monkeypatch):
    def model(*a, **k):
        raise AssertionError("the engine was built although the device is unusable")

    monkeypatch.setattr(simulator_mod, "Model", model)
    with pytest.raises(ValueError, match=r"device='cuda': no CUDA device is visible .*use device='cpu' or 'auto'"):
        Simulator([crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4, road_k=8, partner_k=2), device="cuda")


@no_gpu_only
def test_vector_env_cuda_fails_before_loading_scenes(monkeypatch):
    def load(*a, **k):
        raise AssertionError("scenes were loaded although the device is unusable")

    monkeypatch.setattr(vector, "load_scenes", load)
    with pytest.raises(ValueError, match="device='cuda:0': no CUDA device is visible"):
        vector.TGVectorEnv("procedural:merge", device="cuda:0")


def test_simulator_and_env_default_to_auto():
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, road_k=8, partner_k=2)
    assert Simulator([crossing_scene()], cfg).device == resolve_device("auto")
    env = TGSingleAgentEnv([crossing_scene()], config=cfg)
    assert env.device == env.sim.device == resolve_device("auto")


@no_gpu_only
def test_cli_cuda_without_cuda_exits_2_in_one_line(capsys):
    assert cli.main(["simulate", "--scenes", "procedural:merge", "--worlds", "1", "--steps", "2",
                     "--device", "cuda", "--json"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.strip().splitlines() == [
        f"tg-gpudrive simulate: error: --device cuda: {NO_WARP_CUDA}; use --device cpu or auto"]
    # train reads its device from the config: the same one line, before any process or run directory
    assert cli.main(["train", "--config", str(REPO_CONFIGS / "train" / "small_cpu.yaml"),
                     "--set", "device=cuda", "--out", "/nonexistent/never-written"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"tg-gpudrive train: error: device cuda: {NO_WARP_CUDA}; use device cpu or auto"]


def test_cli_json_reports_the_resolved_device(capsys):
    """simulate and benchmark without --device run on auto and name the device that actually ran."""
    assert cli.main(["simulate", "--scenes", "procedural:merge", "--worlds", "1", "--steps", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["device"] == resolve_device("auto")
    if not HAS_CUDA:
        assert out["device"] == "cpu"
    assert cli.main(["benchmark", "--scenes", "procedural:merge", "--num-scenes", "1", "--worlds", "1",
                     "--steps", "2", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [r["device"] for r in rows] == [resolve_device("auto")]
