"""Multi-process CCE-MAPPO with torch.distributed: one process per GPU (or CPU process with gloo).

Each rank owns its engine on its own device and its own shard of the scene
source (scene i belongs to rank i % world); the ranks start from rank 0's weights, and every optimiser step
averages their gradients in one all-reduce of a flat buffer (average_gradients_), the same for the live rows'
steps and for steps replayed from CUDA graphs. DistributedDataParallel is not used: it keeps each parameter's
gradient accumulator from its construction, on the stream of that moment, and a backward pass captured on
another stream then invalidated the capture; its overlap of the all-reduce with the backward pass buys
nothing at these networks' size (about a megabyte of gradients);
the constraint estimate behind the Lagrange multiplier and the logged
statistics are all-reduced, so lambda stays identical everywhere; rank 0 alone
logs and writes checkpoints, holding every rank's own state (engine, sampler, random streams), so a
relaunch with as many processes continues exactly. With `pipeline` the processes pair up into actors and
learners instead (learn/pipeline.py), and the learners' collectives run among them (`among`). Launch with
`tg-gpudrive train --nproc N` or with `torchrun --nproc_per_node N -m tg_gpudrive.cli train ...`, on several
machines with torchrun's c10d rendezvous and `--auto-resume` (README, "Several machines"). NCCL's NVLink
multicast setting (NCCL_NVLS_ENABLE) is left as the environment has it.
"""

from __future__ import annotations

import contextlib
import gc
import os
import socket

import numpy as np
import torch
import torch.distributed as dist

from tg_gpudrive.engine.simulator import cuda_available


_SCOPE = None  # the group the collectives below run over (`among`); None: every process


def initialized() -> bool:
    """Whether a process group is up (every process, whatever the scope)."""
    return dist.is_available() and dist.is_initialized()


def is_dist() -> bool:
    """Whether the collectives below reach another process: a process group, with more than this one in scope."""
    if not initialized():
        return False
    return _SCOPE is None or dist.get_world_size(_SCOPE) > 1


@contextlib.contextmanager
def among(group):
    """Inside it the collectives below (means, sums, gradient averages, agreements, gathers of floats) run over
    `group` alone, and rank() and world_size() are this process's within it: a pipeline's learners update among
    themselves while the processes that act do not wait in their collectives. The object group's helpers
    (barrier, gather_to_lead) keep every process."""
    global _SCOPE
    was, _SCOPE = _SCOPE, group
    try:
        yield
    finally:
        _SCOPE = was


def rank() -> int:
    return dist.get_rank(_SCOPE) if is_dist() else 0


def world_size() -> int:
    return dist.get_world_size(_SCOPE) if is_dist() else 1


def all_reduce_mean(x: torch.Tensor) -> torch.Tensor:
    if not is_dist():
        return x
    y = x.detach().clone()
    dist.all_reduce(y, op=dist.ReduceOp.SUM, group=_SCOPE)
    return y / world_size()


def every_rank(ok: bool, device) -> bool:
    """Whether `ok` holds on every rank (a collective: every rank calls it at the same point)."""
    if not is_dist():
        return ok
    flag = torch.tensor(float(ok), device=device)
    dist.all_reduce(flag, op=dist.ReduceOp.MIN, group=_SCOPE)
    return bool(flag > 0)


def max_over_ranks(values: list[int], device) -> list[int]:
    """Each of `values`, the largest over the ranks (a collective: every rank calls it at the same point)."""
    if not is_dist():
        return list(values)
    t = torch.tensor(values, dtype=torch.long, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX, group=_SCOPE)
    return t.tolist()


def all_reduce_sum_(tensors: dict) -> None:
    if is_dist():
        for t in tensors.values():
            dist.all_reduce(t, op=dist.ReduceOp.SUM, group=_SCOPE)


def average_gradients_(params) -> None:
    """The gradients of `params` (any iterable, read only when distributed) averaged over the ranks in place, in
    one all-reduce of a flat copy. A parameter without a gradient on this rank counts as a zero one, so every
    rank's buffer has the same layout."""
    if not is_dist():
        return
    params = list(params)
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    grads = [p.grad for p in params]
    flat = torch._utils._flatten_dense_tensors(grads)
    dist.all_reduce(flat, op=dist.ReduceOp.SUM, group=_SCOPE)
    flat /= world_size()
    torch._foreach_copy_(grads, torch._utils._unflatten_dense_tensors(flat, grads))


def broadcast_from_lead_(modules) -> None:
    """The parameters and buffers of `modules` set to rank 0's on every rank (every process: not scoped)."""
    if is_dist():
        for m in modules:
            for t in (*m.parameters(), *m.buffers()):
                dist.broadcast(t.data, src=0)


def gather_floats(values: list[float], device) -> list[list[float]]:
    """Every rank's `values`, in rank order, on every rank (one row when not distributed)."""
    if not is_dist():
        return [list(values)]
    t = torch.tensor(values, dtype=torch.float64, device=device)
    out = [torch.empty_like(t) for _ in range(world_size())]
    dist.all_gather(out, t, group=_SCOPE)
    return [o.tolist() for o in out]


_OBJECT_GROUP = None  # a gloo group beside an NCCL one, for Python objects (pickled on the host)


def object_group():
    """The group that carries Python objects: the default one under gloo; under another backend a gloo
    group over the same ranks, made on first use (every rank reaches that use together), so objects
    travel over the host and never need a current CUDA device or device buffers."""
    global _OBJECT_GROUP
    if dist.get_backend() == "gloo":
        return None
    if _OBJECT_GROUP is None:
        _OBJECT_GROUP = dist.new_group(backend="gloo")
    return _OBJECT_GROUP


def barrier() -> None:
    """Wait until every rank is here, over the host (the object group); nothing when not distributed."""
    if initialized():
        dist.barrier(group=object_group())


def gather_to_lead(obj) -> list | None:
    """Every rank's picklable `obj`, in rank order, on rank 0 (None on the others); [obj] when not
    distributed."""
    if not initialized():
        return [obj]
    out = [None] * dist.get_world_size() if dist.get_rank() == 0 else None
    dist.gather_object(obj, out, dst=0, group=object_group())
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _kind(device: str) -> str:
    """A config's device with "auto" made concrete: "cuda" when CUDA is usable, else "cpu"."""
    if device != "auto":
        return device
    return "cuda" if cuda_available() else "cpu"


def init_from_env(device: str) -> bool:
    """Join the group torchrun describes in the environment; False when not launched that way."""
    if is_dist() or int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return is_dist()
    dist.init_process_group("nccl" if _kind(device).startswith("cuda") else "gloo")
    return True


def init(rank_: int, world: int, port: int, device: str) -> None:
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ["MASTER_PORT"] = str(port)
    dist.init_process_group("nccl" if _kind(device).startswith("cuda") else "gloo", rank=rank_, world_size=world)


def local_device(device: str) -> str:
    """cuda -> cuda:<local rank> under a process group; cpu stays cpu; auto is one of them."""
    device = _kind(device)
    if device.startswith("cuda") and is_dist():
        local = int(os.environ.get("LOCAL_RANK", rank()))
        return f"cuda:{local}"
    return "cuda:0" if device == "cuda" else device


class ShardSource:
    """Rank `r` of `w` sees every w-th scene of a fixed shuffle of `source` (the same on all ranks).

    Disjoint shards whose union is the source. The shuffle keeps them alike: sources are often
    ordered by kind (procedural:all cycles six scene types, so plain r, r + w, ... gives rank 0 of 2
    only three of them, with their own agent counts, and the other rank waits for it at every
    gradient all-reduce)."""

    SHUFFLE_SEED = 20_240_601

    def __init__(self, source, rank_: int, world: int):
        self.source, self.rank, self.world = source, rank_, world
        self.name = f"{getattr(source, 'name', 'scenes')}[shard {rank_}/{world}]"
        order = np.random.default_rng(self.SHUFFLE_SEED).permutation(len(source))
        self.indices = order[rank_::world]

    def __len__(self) -> int:
        return len(self.indices)

    def get(self, i: int):
        return self.source.get(int(self.indices[int(i)]))

    def get_many(self, indices):
        idx = [int(self.indices[int(i)]) for i in indices]
        if hasattr(self.source, "get_many"):
            return self.source.get_many(idx)
        return [self.source.get(i) for i in idx]


def cleanup(together: bool = True) -> None:
    """Tear the group down together: every rank waits at a barrier first, and what still holds the group
    is collected before it goes. A rank that destroyed its gloo
    group while rank 0 was still writing the final checkpoint could abort at exit (seen once in CI
    as SIGABRT, "terminate called without an active exception"). A rank leaving on an error
    passes together=False: its peers may never reach the barrier."""
    global _OBJECT_GROUP
    if is_dist():
        gc.collect()
        if together:
            dist.barrier()
        dist.destroy_process_group()  # every group, the object group too
    _OBJECT_GROUP = None


@contextlib.contextmanager
def process_group(rank_: int, world: int, port: int, device: str):
    """`with process_group(r, w, port, device):` one spawned rank's group, torn down together on
    success and at once on an error (so a failing rank never waits at the barrier for its peers)."""
    init(rank_, world, port, device)
    try:
        yield
    except BaseException:
        cleanup(together=False)
        raise
    cleanup()
