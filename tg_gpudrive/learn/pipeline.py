"""Processes in pairs of one that acts and one that learns (`pipeline: true`, `--nproc 2`, 4, ...): `run`.

Without it every process rolls out its share of the worlds and then updates on it, so an update costs a
rollout plus an optimisation, and splitting the worlds over more GPUs leaves most of both (their steps are
bound by latency, not by the number of worlds). Here the processes pair up, neighbours in rank order (so on
one machine under torchrun's numbering): the even ranks are learners that only update (rank 0 logs,
checkpoints and shows the progress bar), the odd ones actors that only roll out, both at once: while learner
2p updates on batch i, its actor 2p + 1 collects batch i + 1 with the weights from before that update.
Each batch is then one update behind the weights it trains (PPO's ratio to the rollout's own
log-probabilities, and its clip, are what bound that), and an update costs the longer of a rollout and an
optimisation rather than their sum. The learners average their gradients, sum their actors'
counters and agree on every stop among themselves (distributed.among), as the ranks of a run without the
pipeline do.

Each actor sends its batches (a header, the Rollout's tensors, its counters and times) to its learner, which
sends back each update's weights with its word on them (finish, save, error), on two communicators per pair,
so neither direction queues behind the other. Sends do not wait for their receiver; a buffer is written again
only once its send has read it.

Exact resume: before each batch an actor keeps its own state (engine, sampler, random streams, motion
windows) with the weights it acts with. A checkpoint after update u holds the learners' states after u and
the actors' from before batch u, so a resumed pipeline collects batch u again, with the same weights and
draws, and goes on as the run would have.
"""

from __future__ import annotations

import dataclasses
import time

import torch
import torch.distributed as dist

from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn.collector import STAT_KEYS, Rollout, TrainingError

WORD = ("finish", "save", "error")  # what the learner says with each update's weights
HEADER = ("slots", "error", "interrupt", "left_to_replay", "scenes_visited", "scene_files_skipped",
          "scenes_unplayable")
TIMES = ("rollout_s", "wait_s")  # the actor's rollout of the batch, and its wait for the weights before it


def run(tr, bar, stop, t_start: float, elapsed0: float) -> dict:
    """This process's part of the pipeline for the Trainer `tr`: a learner's loop (its last metrics row) or an
    actor's ({})."""
    channel = Channel(tr)
    if channel.learning:
        last = learn_loop(tr, channel, bar, stop, t_start, elapsed0)
    else:
        last = act_loop(tr, channel, stop)
    channel.settle()
    return last


def learn_loop(tr, channel: "Channel", bar, stop, t_start: float, elapsed0: float) -> dict:
    """A learner: receive a batch, update on it, send the weights and the word on them, save when due. Its
    clock runs from waiting for a batch to the update's end, so it counts whatever of the rollout the update
    did not hide; with several learners the slowest one's counts."""
    cfg = tr.cfg
    last = {}
    channel.send_weights()  # the weights the actor's second batch is collected with (its first: its own)
    while tr.update < cfg.updates:
        t0 = time.perf_counter()
        batch, stats, head, times = channel.recv_batch()
        t_in = time.perf_counter() - t0
        if head["error"]:
            raise tr._spoilt(f"non-finite policy output during the rollout of update {tr.update}")
        # the actor's worlds are the ones learnt on: their scene keys and the actor's counters stand for the learner's
        tr.pipe_keys, tr.left_to_replay = head["keys"], head["left_to_replay"]
        tr.reported = {k: head[k] for k in HEADER[4:]}
        with dist_util.among(channel.learners):  # the update's collectives, the counters' and the verdict's
            last = learn_one(tr, channel, batch, stats, (t0, t_in, times), elapsed0, t_start)
            interrupted = not dist_util.every_rank(not (stop.mine or head["interrupt"]), tr.device)
            save, end = tr.verdict(bar, last, stats, interrupted)
        finish = end or tr.update >= cfg.updates
        channel.send_weights(finish=finish, save=save)
        if save:
            tr.save()  # the actors hand over their states from before this batch
        tr.keep_policy(last)
        if finish:
            if tr.update < cfg.updates:
                channel.recv_batch()  # the batch the actor collected meanwhile, which nobody learns
            break
    return last


def learn_one(tr, channel: "Channel", batch, stats: dict, clock: tuple, elapsed0: float, t_start: float) -> dict:
    """One update on `batch`, then the learners' counters summed (`stats`, in place), their clocks and their
    actors' gathered (timing.csv: a row per process, in rank order), and the update counted: its row."""
    t0, t_in, times = clock
    try:
        row = tr.learn(batch)
    except Exception:
        channel.send_weights(error=True)  # the actor stops too rather than wait for weights
        raise
    tr._sync()
    dt = time.perf_counter() - t0
    dist_util.all_reduce_sum_(stats)  # every actor's episodes and steps
    each = dist_util.gather_floats([0.0, t_in, dt - t_in, times["rollout_s"], times["wait_s"], 0.0], tr.device)
    phases = [row for e in each for row in (e[:3], e[3:])]  # learner 2p, then its actor 2p + 1
    span = max(sum(e[:3]) for e in each)  # the slowest learner's
    row.update({"time/rollout_s": times["rollout_s"], "time/rollout_slowest_s": max(e[3] for e in each),
                "time/wait_s": t_in, "time/update_s": dt - t_in})
    tr.wall += span
    return tr.count(row, batch, stats, phases, span, times["rollout_s"], elapsed0, t_start)


def act_loop(tr, channel: "Channel", stop) -> dict:
    """The actor: collect a batch with the weights it has, send it, take the next weights (an update behind),
    and hand its state over whenever the learner saves."""
    cfg = tr.cfg
    start = tr.update
    kept = None
    for i in range(start, cfg.updates + 2):
        wait = 0.0
        if i > start:
            t0 = time.perf_counter()
            word = channel.recv_weights()  # the weights after update i - 1, and the learner's word on them
            wait = time.perf_counter() - t0
            if word["save"]:
                dist_util.gather_to_lead(kept)  # the checkpoint after update i - 1: this process before batch i - 1
            if word["error"]:
                raise RuntimeError("the learning process stopped on an error (its message says which)")
            if word["finish"]:
                break
        tr.update = i
        kept = {**tr.rank_state(), "acting": {"actor": clone(tr.actor.state_dict()),
                                              "critic": clone(tr.critic.state_dict())}}
        if i < cfg.updates:
            if cfg.resample_every and i > 0 and i % cfg.resample_every == 0:
                tr._resample()
            collect(tr, channel, stop, wait)
    return {}


def collect(tr, channel: "Channel", stop, wait: float) -> None:
    """One batch collected and sent; a non-finite rollout is sent with its error flag (so that the learner
    stops rather than waits) and then raised."""
    channel.settle()  # the last batch's sends have read the buffers this rollout overwrites
    t0 = time.perf_counter()
    error = None
    try:
        batch, stats = tr.collect()
    except TrainingError as e:  # a non-finite policy output: the trainer's error names the update
        error, batch, stats = e, tr.collector._buf, tr.collector._stats
    tr._sync()
    channel.send_batch(batch, stats, error is not None, stop.mine, (time.perf_counter() - t0, wait))
    if error is not None:
        channel.settle()
        raise error


def clone(state: dict) -> dict:
    return {k: v.detach().clone() for k, v in state.items()}


class Channel:
    """The two directions between a learner and its actor: batches from the actor, weights from the learner,
    each on a communicator of its own; and the learners' group. The learner receives into its own rollout
    buffers (the collector's, of the batch's shape), the actor into its networks' parameters (in place, so
    CUDA graphs that read them stay valid)."""

    def __init__(self, tr):
        self.tr = tr
        self.learning = tr.learns
        self.learner, self.actor = 2 * tr.stream, 2 * tr.stream + 1  # this process's pair
        # every process makes every group, in one order
        self.learners = dist.new_group(list(range(0, tr.world, 2)))
        pairs = [(dist.new_group([2 * p, 2 * p + 1]), dist.new_group([2 * p, 2 * p + 1])) for p in range(tr.streams)]
        self.batches, self.weights = pairs[tr.stream]
        # NCCL makes a communicator on a group's first send or receive, a step both processes take together: one
        # token each way, in the same order in both, so that neither makes one while the other waits in another
        token = torch.zeros(1, device=tr.device)
        for group, src, dst in ((self.batches, self.actor, self.learner), (self.weights, self.learner, self.actor)):
            if tr.rank == src:
                dist.send(token, dst, group=group)
            else:
                dist.recv(token, src, group=group)
        self._sending: list = []  # (work, tensor) of sends not yet known to have read their buffers
        self._nets = [*tr.actor.parameters(), *tr.actor.buffers(), *tr.critic.parameters(), *tr.critic.buffers()]
        if len({t.dtype for t in self._nets}) != 1:
            raise TypeError("pipeline: the networks' tensors must share one dtype to travel as one buffer")
        self._terms = len(tr.sim.reward_term_names)
        self._worlds = tr.sim.num_worlds

    def settle(self) -> None:
        """Wait until this process's sends have read their buffers (on the GPU: the stream waits, not the host)."""
        for work, _ in self._sending:
            work.wait()
        self._sending = []

    def _send(self, tensors: list, group, dst: int) -> None:
        self.settle()
        self._sending = [(dist.isend(t, dst, group=group), t) for t in tensors]

    @staticmethod
    def _recv(tensors: list, group, src: int) -> None:
        for t in tensors:
            dist.irecv(t, src, group=group).wait()

    # ------------------------------------------------------------ weights, learner -> actor
    def send_weights(self, finish: bool = False, save: bool = False, error: bool = False) -> None:
        word = torch.tensor([finish, save, error], dtype=torch.long, device=self.tr.device)
        flat = torch._utils._flatten_dense_tensors([t.detach() for t in self._nets])
        self._send([word, flat], self.weights, self.actor)

    def recv_weights(self) -> dict:
        word = torch.zeros(len(WORD), dtype=torch.long, device=self.tr.device)
        flat = torch.empty(sum(t.numel() for t in self._nets), dtype=self._nets[0].dtype, device=self.tr.device)
        self._recv([word, flat], self.weights, self.learner)
        with torch.no_grad():
            torch._foreach_copy_(self._nets, torch._utils._unflatten_dense_tensors(flat, self._nets))
        return dict(zip(WORD, (bool(x) for x in word.tolist())))

    # ------------------------------------------------------------ batches, actor -> learner
    def send_batch(self, batch: Rollout, stats: dict, error: bool, interrupt: bool, times: tuple) -> None:
        tr = self.tr
        counts = tr.source_counts()
        head = [batch.mask.shape[2], int(error), int(interrupt), tr.left_to_replay]
        head += [int(counts[k]) for k in HEADER[4:]]
        keys = tr.world_keys().to(torch.long)
        header = torch.cat([torch.tensor(head, dtype=torch.long, device=tr.device), keys])
        flat = torch.cat([stats["terms"].double(), torch.stack([stats[k].double() for k in STAT_KEYS]),
                          torch.tensor(times, dtype=torch.float64, device=tr.device)])
        self._send([header, *rollout_tensors(batch), flat], self.batches, self.learner)

    def recv_batch(self) -> tuple[Rollout, dict, dict, dict]:
        """(the batch, its counters, its header with the worlds' scene `keys`, the actor's times)."""
        tr = self.tr
        header = torch.zeros(len(HEADER) + self._worlds, dtype=torch.long, device=tr.device)
        self._recv([header], self.batches, self.actor)
        values = header.tolist()
        head = {**dict(zip(HEADER, values)), "keys": header[len(HEADER):]}
        T = tr.cfg.rollout_steps
        buf = tr.collector._buffers(T, self._worlds, head["slots"])
        flat = torch.zeros(self._terms + len(STAT_KEYS) + len(TIMES), dtype=torch.float64, device=tr.device)
        self._recv([*rollout_tensors(buf), flat], self.batches, self.actor)
        stats = {"terms": flat[:self._terms].float(),
                 **{k: flat[self._terms + j].float() for j, k in enumerate(STAT_KEYS)}}
        times = dict(zip(TIMES, flat[-len(TIMES):].tolist()))
        return dataclasses.replace(buf, stats=stats), stats, head, times


def rollout_tensors(batch: Rollout) -> list[torch.Tensor]:
    """The tensors of a Rollout in field order (a pair for a continuous policy's output), booleans as bytes:
    the same list on both processes, which build their buffers from one config."""
    out = []
    for f in dataclasses.fields(Rollout):
        value = getattr(batch, f.name)
        if f.name == "stats" or value is None:
            continue
        for t in value if isinstance(value, tuple) else (value,):
            out.append(t.view(torch.uint8) if t.dtype == torch.bool else t)
    return out
