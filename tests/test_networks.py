"""The continuous actor's starting exploration: a fifth of each action dimension's range, so early
curvature draws are not mostly clipped to a full turn (one std of 0.61 for both dimensions spanned
twice the default curvature box of 0.3 1/m)."""

from __future__ import annotations

import torch

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.agents.networks import INIT_STD_FRACTION, Actor


def test_initial_std_is_a_fifth_of_each_dimensions_range():
    high = EngineConfig().act_high  # (6 m/s^2, 0.3 1/m) by default
    actor = Actor(2, 3, discrete=False, act_scale=list(high), hidden=16)
    obs = torch.zeros(5, EGO_DIM + 2 * PARTNER_DIM + 3 * ROAD_DIM)
    mean, log_std = actor(obs)
    assert torch.allclose(log_std.exp()[0], torch.tensor([INIT_STD_FRACTION * h for h in high]))
    assert torch.allclose(log_std.exp()[0], torch.tensor([1.2, 0.06]))  # by hand: 0.2 x (6, 0.3)
    # draws around a centred mean stay inside the box: |z| > 5 sigma is about 6e-7 of them
    draws = torch.distributions.Normal(mean, log_std.exp()).sample((2000,))
    inside = (draws.abs() <= torch.tensor(high)).float().mean()
    assert inside > 0.999
