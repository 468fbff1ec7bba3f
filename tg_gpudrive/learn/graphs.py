"""The update's optimiser steps (StepGraphs) and the rollout's steps (RolloutGraphs) replayed from CUDA graphs
(TrainConfig `cuda_graphs`).

At the learner's sizes a minibatch is a few dozen groups, and its step (the actor, the critic, the losses,
their backward pass: several hundred small kernels) is bound by launching those kernels from Python, not by
their arithmetic: halving the data a rank holds then leaves the update's time where it was, and more GPUs
do not shorten training. Here a step's loss runs over a fixed number of rows (update.minibatch_loss with
`row_weight`): its live rows, padded with fillers of weight 0 up to a capacity a little above the most live rows
of any minibatch (update.padded_rows, StepGraphs.capacity), so the losses and gradients are those of the live
rows and the shapes are fixed while the capacity holds. Its forward and backward pass are captured once and
replayed for every minibatch, which reads its groups and rows through fixed buffers from fixed copies of the
rollout. Finding the live rows costs a host sync an epoch, before its first step. After a replay the ranks'
gradients are averaged eagerly (an all-reduce of one flat buffer, as after a live-row step); the clipping and
the fused Adam that follow (update.make_optimizer: its step counters on the device) are replayed from a graph of
their own, recorded on the first replay after the step's capture, as both read the step's gradient buffers.

A rollout's step is bound the same way (a few hundred small operators around the engine's own Warp graph);
RolloutGraphs captures what comes before and after the engine's step.

On the CPU the same fixed-shape steps run without graphs. A capture that fails (an operation that cannot be
captured, or memory: the padded rows and a graph's own pool need more of it than the live rows) is logged once, its
memory is given back, and training goes on as without graphs, on the live rows.

A replay saves the host its launches, not the device its kernels: at these sizes each of a step's kernels costs
a few microseconds of device time whatever its work. `compile_update` compiles the fixed-shape loss with
torch.compile, so that its forward and backward pass are fewer, fused kernels; the warm-up steps compile it
(once per rollout shape, the rows a step holds a symbolic size; cached on disk), and the capture records the
compiled kernels.
"""

from __future__ import annotations

import dataclasses
import logging

import torch
from torch.profiler import record_function as phase

from tg_gpudrive.agents.policy import BehaviourPrior
from tg_gpudrive.config import TrainConfig
from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn.collector import Networks
from tg_gpudrive.learn.update import (Groups, clip_and_adam, clip_and_step, compiled_loss, eager_steps,
                                      epoch_live_rows, minibatch_loss, padded_rows)

log = logging.getLogger(__name__)
Tensor = torch.Tensor


def on_side_stream(fn, stream: torch.cuda.Stream) -> None:
    """`fn` on `stream`, ordered after the work queued so far and before the work queued next."""
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        fn()
    torch.cuda.current_stream().wait_stream(stream)


def capture(graph: torch.cuda.CUDAGraph, fn, stream: torch.cuda.Stream, pool=None) -> None:
    """Record `fn`'s kernels into `graph` on a side stream (nothing runs). torch.cuda.graph does the same
    after a device synchronisation, emptying the allocator's cache (and, in some versions, a garbage
    collection): a cost per capture that the rollout's tens of captures per batch of scenes would pay."""
    def record():
        # only this thread is held to the capture's rules: NCCL's watchdog thread polls its events meanwhile
        graph.capture_begin(pool=pool, capture_error_mode="thread_local")
        try:
            fn()
        finally:
            graph.capture_end()
    on_side_stream(record, stream)


def try_capture(fn, stream: torch.cuda.Stream, pool=None) -> tuple[torch.cuda.CUDAGraph | None, RuntimeError | None]:
    """`capture` into a new graph: (the graph, None), or (None, the error) where `fn`'s kernels could not be
    recorded (memory, an operation that cannot be captured); the caller decides how to go on without it."""
    graph = torch.cuda.CUDAGraph()
    try:
        capture(graph, fn, stream, pool)
    except RuntimeError as e:
        return None, e
    return graph, None


def release_cached_memory() -> None:
    """Give the caching allocator's free blocks back to the device (after a failed capture's pool is dropped)."""
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def _static(x):
    """A fixed copy of a Groups entry (None, a tensor or a tuple of tensors)."""
    if x is None:
        return None
    return tuple(t.clone() for t in x) if isinstance(x, tuple) else x.clone()


def _fill(dst, src) -> None:
    if dst is None:
        return
    for d, s in zip(dst, src) if isinstance(dst, tuple) else [(dst, src)]:
        d.copy_(s)


def _signature(x):
    if x is None:
        return None
    return tuple(_signature(t) for t in x) if isinstance(x, tuple) else (tuple(x.shape), x.dtype)


class StepGraphs:
    """The optimiser steps of every update, one captured forward and backward pass per rollout shape.
    `run` is update.eager_steps's counterpart, with the same minibatch order."""

    WARMUP = 3  # eager steps before a capture: autograd's and the libraries' lazy set-up stays outside it

    def __init__(self, cfg: TrainConfig, nets: Networks, opt: torch.optim.Optimizer):
        self.cfg, self.opt, self.nets = cfg, opt, nets
        self.params = [p for group in opt.param_groups for p in group["params"]]
        # the full minibatches' loss (compiled with compile_update); an epoch's short last one runs it as it is,
        # not to compile a second shape
        self.loss = compiled_loss() if cfg.compile_update else minibatch_loss
        self.key = None
        self.graph: torch.cuda.CUDAGraph | None = None
        self.grads: list[Tensor | None] = []
        self.opt_graph: torch.cuda.CUDAGraph | None = None  # the clipping and Adam after a replay
        self.opt_capturable = bool(opt.defaults.get("capturable"))  # False too after a failed capture of them
        self.capturable = True  # whether to capture (False: the fixed-shape steps run eagerly)
        self.fallen_back = False  # a capture failed: the updates run update.eager_steps
        self.warm = 0
        self.cap = 0  # rows a step holds (capacity)
        self.rows: tuple[Tensor, Tensor, Tensor] = ()  # the step's rows: positions, slots, weights (padded_rows)
        self.captures = 0
        self.opt_captures = 0
        self.stream = None  # the side stream of the warm-up steps and the capture

    @property
    def graphed(self) -> bool:
        return self.graph is not None

    def run(self, b: Groups, lam: Tensor, gen: torch.Generator,
            prior: BehaviourPrior) -> tuple[dict[str, Tensor], Tensor, int]:
        """`epochs` passes of shuffled minibatches, one optimiser step each: (the loss parts summed over the
        minibatches, whether a loss was not finite, the number of minibatches). A new magnet `prior` (a
        continuous one is evaluated inside the step) gets a new capture."""
        if self.fallen_back:
            self.b, self.key = None, None  # the fixed copies go
            return eager_steps(self.cfg, b, lam, self.nets, self.opt, gen, prior)
        n_groups = b.mask.shape[0]
        mb = max(1, n_groups // self.cfg.minibatches)
        self.prior = prior
        # every epoch's order and its minibatches' live rows, found before the first step (a host sync an epoch)
        perms = [torch.randperm(n_groups, generator=gen, device=b.mask.device) for _ in range(self.cfg.epochs)]
        lives = [epoch_live_rows(b.mask[perm], mb) for perm in perms]
        need = max((len(g) for live in lives for g, _ in live[:n_groups // mb]), default=0)
        key = (mb, id(prior), _signature(lam), tuple(_signature(getattr(b, f.name)) for f in dataclasses.fields(b)))
        # the ranks capture together (_capture agrees across them): one capacity on every rank, and new buffers
        # on every rank when one rank's rollout changed shape (their rollouts may hold different slots)
        need, slots, new = dist_util.max_over_ranks([need, mb * b.mask.shape[1], int(key != self.key)], b.mask.device)
        self._load(b, lam, mb, key, bool(new), self.capacity(need, slots))
        for v in self.acc.values():
            v.zero_()
        self.bad.zero_()
        n_mb = 0
        for perm, live in zip(perms, lives):
            for s, rows in zip(range(0, n_groups, mb), live):
                chunk = perm[s:s + mb]
                if len(chunk) == mb:
                    self.idx.copy_(chunk)
                    padded_rows(rows, self.cap, self.rows)
                    self._step()
                else:  # the epoch's short last minibatch: its own shapes, so not replayed
                    self._eager(chunk, rows)
                n_mb += 1
        return self.acc, self.bad, n_mb

    # ------------------------------------------------------------------ internals
    def capacity(self, need: int, slots: int) -> int:
        """Rows a step holds: `need` (the most live rows of a minibatch) rounded up to a sixteenth of the
        minibatch's `slots`, never fewer than it held before, so that a rollout with a few more live rows than
        the last rarely asks for a new capture."""
        q = max(1, -(-slots // 16))
        return min(slots, max(self.cap, -(-max(need, 1) // q) * q))

    def _load(self, b: Groups, lam: Tensor, mb: int, key: tuple, new: bool, cap: int) -> None:
        """The rollout into the fixed buffers; new buffers (and a new capture) when its shapes (`key`) changed
        here or on another rank (`new`), or the rows a step holds (`cap`, from capacity) did."""
        dev = b.mask.device
        if new:
            self._drop_graphs()
            self.key, self.warm, self.cap = key, 0, 0
            self.b = Groups(**{f.name: _static(getattr(b, f.name)) for f in dataclasses.fields(b)})
            self.lam = lam.clone()
            self.idx = torch.zeros(mb, dtype=torch.long, device=dev)
            self.bad = torch.zeros((), dtype=torch.bool, device=dev)
            self.acc: dict[str, Tensor] = {}
        else:
            for f in dataclasses.fields(b):
                _fill(getattr(self.b, f.name), getattr(b, f.name))
            self.lam.copy_(lam)
        if cap != self.cap:  # new row buffers: the capture reads them
            self._drop_graphs()
            self.cap, self.warm = cap, 0
            self.rows = (torch.zeros(cap, dtype=torch.long, device=dev), torch.zeros(cap, dtype=torch.long, device=dev),
                         torch.zeros(cap, device=dev))
            if self.cfg.compile_update:  # the row count a symbolic size: a grown capacity is captured again,
                for t in self.rows:  # not compiled again
                    torch._dynamo.maybe_mark_dynamic(t, 0)

    def _forward_backward(self, idx: Tensor, loss_fn, rows: tuple[Tensor, Tensor] | None = None) -> None:
        """A step's loss and backward pass: over the fixed row buffers, or over the live `rows` given."""
        if rows is None:
            g, c, w = self.rows
            loss, parts = loss_fn(self.cfg, self.b, idx, self.lam, self.nets, self.prior, (g, c), row_weight=w)
        else:
            loss, parts = loss_fn(self.cfg, self.b, idx, self.lam, self.nets, self.prior, rows)
        self.bad |= ~torch.isfinite(loss)
        for k, v in parts.items():
            if k not in self.acc:
                self.acc[k] = torch.zeros((), device=self.bad.device)
            self.acc[k].add_(v.detach())
        loss.backward()

    def _after_backward(self) -> None:
        with phase("update/optimizer"):
            clip_and_step(self.cfg, self.nets, self.opt)

    def _eager(self, idx: Tensor, rows: tuple[Tensor, Tensor] | None = None, loss_fn=minibatch_loss) -> None:
        with phase("update/forward"):
            self.opt.zero_grad(set_to_none=True)
            self._forward_backward(idx, loss_fn, rows)
        self._after_backward()

    def _step(self) -> None:
        cuda = self.idx.is_cuda
        if self.graph is None and cuda and self.capturable and self.warm >= self.WARMUP:
            self._capture()
        if self.graph is not None:
            with phase("update/forward"):
                self.graph.replay()
            for p, g in zip(self.params, self.grads):  # an eager step in between set its own
                p.grad = g
            self._replay_optimiser()
            return
        if cuda:  # warm-up steps on the capture's side stream, as a capture wants
            self.opt.zero_grad(set_to_none=True)
            on_side_stream(lambda: self._forward_backward(self.idx, self.loss), self._side())
            self._after_backward()
        else:
            self._eager(self.idx, loss_fn=self.loss)
        self.warm += 1

    def _replay_optimiser(self) -> None:
        """After a replay: the gradients' average over the ranks, then the clipping and Adam from their graph
        (recorded now if not yet; eagerly where they cannot be)."""
        with phase("update/optimizer"):
            dist_util.average_gradients_(self.params)
            if self.opt_graph is None and self.opt_capturable:
                self.opt_graph, failed = try_capture(lambda: clip_and_adam(self.cfg, self.nets, self.opt),
                                                     self._side())
                if failed is None:
                    self.opt_captures += 1
                else:  # no collective inside: each rank may fall back alone
                    log.warning("the update's clipping and Adam could not be captured as a CUDA graph (%s); they "
                                "go on eagerly", failed)
                    self.opt_capturable = False
            if self.opt_graph is not None:
                self.opt_graph.replay()
            else:
                clip_and_adam(self.cfg, self.nets, self.opt)

    def _drop_graphs(self) -> None:
        self.graph, self.grads, self.opt_graph = None, [], None

    def _side(self) -> torch.cuda.Stream:
        self.stream = self.stream or torch.cuda.Stream(self.idx.device)
        return self.stream

    def _fall_back(self) -> None:
        """After a failed capture: this update's remaining steps run eagerly over the padded rows, the next updates
        on the live rows (eager_steps); the capture's memory is given back now, the fixed copies at the next
        update."""
        self.capturable, self.fallen_back = False, True
        self.opt.zero_grad(set_to_none=True)
        self._drop_graphs()
        release_cached_memory()

    def _capture(self) -> None:
        """Record the forward and backward pass of a step over the fixed buffers (nothing runs yet)."""
        self.opt.zero_grad(set_to_none=True)  # the captured backward allocates the gradients it refills
        self._drop_graphs()
        graph, failed = try_capture(lambda: self._forward_backward(self.idx, self.loss), self._side())
        # the ranks fall back together, so that they go on taking the same steps
        if not dist_util.every_rank(failed is None, self.idx.device):
            log.warning("the update's step could not be captured as a CUDA graph (%s); the updates go on without "
                        "graphs, on the live rows", failed or "on another rank")
            self._fall_back()
            return
        self.graph = graph
        self.grads = [p.grad for p in self.params]
        self.captures += 1


class RolloutGraphs:
    """A rollout's steps replayed from CUDA graphs (the collector's `graphs`): per step t, what comes before
    the engine's step (the magnet's context, the actor, sampling, the buffers) and what comes after it
    (rewards, ends and counters into the buffers), each its own graph; the engine's step between them is
    already a Warp graph. The collector then acts on every slot the policy drives, live or not
    (collector.RolloutCollector._act with `dense`), and draws the rollout's random numbers before its steps,
    so a step's shapes and memory are fixed for a batch of scenes. The first rollout on a batch runs its
    steps eagerly, the next captures each part as it comes to it, the later ones replay them; a new batch of
    scenes, new buffers or a new magnet get new captures. On the CPU the parts run as they are."""

    def __init__(self, device):
        self.cuda = torch.device(device).type == "cuda"
        self.key: tuple | None = None
        self._owners: tuple = ()
        self.graphs: dict = {}
        self.seen: set = set()
        self.pool = None  # one memory pool for the parts: they replay in the order they were captured
        self.stream = None  # the side stream the parts are captured on
        self.capturable = True  # False once a capture failed
        self.captures = 0

    @property
    def graphed(self) -> bool:
        return bool(self.graphs)

    def run(self, owners: tuple, name, fn) -> None:
        """Part `name` of a step: replayed, captured and replayed, or run as it is. `owners`: what a capture
        reads (the engine's model, the buffers, the magnet, the actor); others than last time start afresh
        (they are held, so their ids stay theirs)."""
        key = tuple(id(o) for o in owners)
        if key != self.key:
            self.key, self._owners, self.graphs, self.seen, self.pool = key, owners, {}, set(), None
        graph = self.graphs.get(name)
        if graph is not None:
            graph.replay()
            return
        if name in self.seen and self.capturable and self.cuda:
            self.stream = self.stream or torch.cuda.Stream()
            graph, failed = try_capture(fn, self.stream, self.pool)
            if failed is not None:
                log.warning("a rollout step could not be captured as a CUDA graph (%s); the rollouts go on "
                            "without graphs, on the live rows", failed)
                self.capturable, self.graphs, self.pool = False, {}, None
                release_cached_memory()
                fn()
                return
            self.pool = self.pool if self.pool is not None else graph.pool()
            self.graphs[name] = graph
            self.captures += 1
            graph.replay()
            return
        fn()
        self.seen.add(name)
