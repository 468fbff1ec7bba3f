"""Training on several machines: two torchrun "nodes" on this host, one gloo process each, meet through a
c10d rendezvous on the loopback address. A run that loses a node and is relaunched with the same command
(`--auto-resume`) ends exactly where the same run without the loss ends: every rank's engine state,
sampler and random streams are in the checkpoint."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.config import REPO_CONFIGS
from tg_gpudrive.learn.distributed import free_port

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"
SETTINGS = ["num_worlds=2", "rollout_steps=8", "hidden=16", "quantiles=4", "num_scenes=8", "checkpoint_every=1",
            "resample_every=3", "device=cpu"]
ENDLESS = 100_000  # updates of the run that loses a node: it cannot end before the loss, however slow the host



def launch_nodes(run, rdzv_id: str, updates: int) -> list[subprocess.Popen]:
    """The two nodes of one job: the same torchrun command twice, as on two machines."""
    port = free_port()
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
           "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{port}", "--rdzv-id", rdzv_id,
           "-m", "tg_gpudrive.cli", "train", "--config", str(SMALL), "--out", str(run), "--auto-resume", "--json"]
    for kv in [*SETTINGS, f"updates={updates}"]:
        cmd += ["--set", kv]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                             start_new_session=True) for _ in range(2)]


def finish(nodes, timeout=300) -> list[str]:
    """Both nodes' output, once both ended well."""
    outs = [p.communicate(timeout=timeout)[0] for p in nodes]
    assert [p.returncode for p in nodes] == [0, 0], "\n".join(o[-3000:] for o in outs)
    return outs


def descendants(pid: int) -> list[int]:
    """Every process below `pid` (torchrun starts its workers in sessions of their own, so a process
    group does not hold them), from /proc."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def kill(p: subprocess.Popen) -> None:
    """The node is gone: its torchrun agent and every trainer under it, at once."""
    for pid in [*descendants(p.pid), p.pid]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    p.wait()


def saved_update(run) -> int:
    try:
        return int(torch.load(run / "checkpoint.pt", weights_only=False, map_location="cpu")["update"])
    except (FileNotFoundError, EOFError, RuntimeError, KeyError):  # not written yet
        return 0


def learnt(run) -> dict:
    """The weights, the optimiser's moments and the Lagrange multiplier the run ended with."""
    ck = load_checkpoint(run / "checkpoint.pt")
    moments = {f"opt.{i}.{k}": v for i, st in ck["opt"]["state"].items() for k, v in st.items()}
    return {**{f"actor.{k}": v for k, v in ck["actor"].items()}, **{f"critic.{k}": v for k, v in ck["critic"].items()},
            **moments, **{f"lagrange.{k}": v for k, v in ck["lagrange"].items()}}


@pytest.mark.slow
def test_two_nodes_lose_one_and_resume_exactly(tmp_path):
    """The job that loses a node runs without an end in sight; once it has lost one at update k, the
    reference (the same job, never interrupted) runs to k + 3, and so does the relaunched job: no race
    between the loss and the end of the run."""
    ref, lossy = tmp_path / "ref", tmp_path / "lossy"
    nodes = launch_nodes(lossy, "lossy", ENDLESS)
    deadline = time.monotonic() + 240
    while saved_update(lossy) < 2:
        assert time.monotonic() < deadline and nodes[1].poll() is None, "no checkpoint before the deadline"
        time.sleep(0.02)
    kill(nodes[1])  # a node is lost mid-run ...
    try:  # ... the survivor's collective fails on the closed connection and its job ends
        nodes[0].wait(timeout=120)
    except subprocess.TimeoutExpired:
        kill(nodes[0])
    assert nodes[0].returncode != 0
    lost_at = saved_update(lossy)
    assert lost_at >= 2
    end = lost_at + 3

    finish(launch_nodes(ref, "ref", end))
    ck = load_checkpoint(ref / "checkpoint.pt")
    assert ck["update"] == end and ck["world_size"] == 2 and len(ck["other_ranks"]) == 1
    finish(launch_nodes(lossy, "lossy-again", end))  # the same command, relaunched
    ck = load_checkpoint(lossy / "checkpoint.pt")
    assert ck["update"] == end and ck["world_size"] == 2
    a, b = learnt(ref), learnt(lossy)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), f"{k} differs after resuming from update {lost_at}"


@pytest.mark.parametrize("extra", [[], ["--out", "x", "--resume", "x"]])
def test_auto_resume_needs_the_run_directory_alone(extra, capsys):
    from tg_gpudrive import cli

    assert cli.main(["train", "--config", str(SMALL), "--auto-resume", *extra]) != 0
    assert "--auto-resume: give the run directory as --out" in capsys.readouterr().err
