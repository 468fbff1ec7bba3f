"""The hand-made behaviour prior: the "magnet" of CCE-MAPPO built from the logs alone.

The interface (`context(sim)` -> a compact per-step tensor the learner stores,
here the logged expert action; `distribution(context, obs)` -> logits or
(mean, log_std) at update time) is `tg_gpudrive.agents.policy.BehaviourPrior`.

`ExpertPrior` centres the distribution on the inverse-dynamics expert action
of the log at the current step (kernels/dynamics.py), so the magnet is real
without a learned model. By default (`closed_loop=True`) that action is
computed from the agent's current state, so an agent that has drifted off its
log is pulled back towards it (a DAgger-style teacher); `closed_loop=False`
uses the logged actions as they were computed along the log, which say
nothing about how to recover from a drift. Where no expert action exists (the log is invalid at
the next step) the prior is uniform (discrete) or wide (continuous). The
learned world model (worldmodel.WorldModelPrior) implements the same two methods.
"""

from __future__ import annotations

import math

import torch

from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.policy import BehaviourPrior, action_grid
from tg_gpudrive.enums import Dynamics


class ExpertPrior(BehaviourPrior):
    """Discretised Gaussian around the logged action (discrete), or a Gaussian on it (continuous).

    sigma_accel [m/s^2] and sigma_curvature [1/m] set how tightly the magnet
    holds; with the default 7 x 13 grid one bin is 2 m/s^2 and 0.05 1/m.

    `floor` (discrete) mixes that Gaussian with the uniform distribution,
    p = (1 - floor) N + floor / num_actions, so log p >= log(floor / num_actions):
    an agent far from its log, where the teacher asks for a full turn the policy
    will not make, adds a bounded KL instead of one that swamps the batch's
    gradient, and the prior itself keeps some entropy (a magnet with none pulls
    the policy to a deterministic one that stops exploring)."""

    context_dim = 4  # the expert action's 3 values and its validity

    def __init__(self, sim: Simulator, sigma_accel: float = 0.7, sigma_curvature: float = 0.01,
                 closed_loop: bool = True, floor: float = 0.05):
        cfg = sim.cfg
        self.closed_loop = closed_loop
        self.capturable = not closed_loop  # the corrective expert is an engine kernel
        if not 0.0 <= floor < 1.0:
            raise ValueError(f"prior floor must lie in [0, 1), got {floor}")
        self.floor = floor
        self.discrete = cfg.discrete
        self.bicycle = cfg.dynamics == Dynamics.BICYCLE
        self.act_dim = cfg.act_dim
        dev = sim.reward.device
        if self.discrete:
            self.grid = action_grid(cfg, dev)
        sig = [sigma_accel, sigma_curvature] if self.bicycle else [0.5, 0.2, 0.1]
        self.sigma = torch.tensor(sig, device=dev)

    def context(self, sim: Simulator, num_controlled: int) -> torch.Tensor:
        """(W, C, 4): expert action (3 values) and a validity flag, at each world's current step."""
        C = num_controlled
        if self.closed_loop:
            act, idx = sim.corrective_expert()
            return torch.cat([act[:, :C], (idx[:, :C] >= 0).float()[..., None]], dim=-1)
        act = sim.log_at("expert_action", sim.world_step, C)
        valid = (sim.log_at("expert_index", sim.world_step, C) >= 0).float()
        return torch.cat([act, valid[..., None]], dim=-1)

    def distribution(self, context: torch.Tensor, obs: torch.Tensor | None = None):
        act, valid = context[..., :3], context[..., 3:4]
        if self.discrete:
            z = (self.grid - act[..., None, :2]) / self.sigma[:2]
            logits = -0.5 * (z**2).sum(-1)
            if self.floor > 0:
                n = logits.shape[-1]
                logits = torch.logaddexp(torch.log_softmax(logits, -1) + math.log1p(-self.floor),
                                         torch.full_like(logits, math.log(self.floor / n)))
            return logits * valid  # invalid: all zeros = uniform
        k = self.act_dim
        mean = act[..., :k]
        log_std = torch.log(self.sigma[:k]).expand_as(mean) + (1 - valid) * 3.0
        return mean, log_std
