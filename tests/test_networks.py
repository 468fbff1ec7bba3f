"""The continuous actor's starting exploration: a fifth of each action dimension's range, so early
curvature draws are not mostly clipped to a full turn (one std of 0.61 for both dimensions spanned
twice the default curvature box of 0.3 1/m); the critic's heads evaluated on the live slots alone give
what the full grid gives there, value and gradient; the encoder's masked max-pool against NumPy and
against the -inf-filled amax it replaces, value and gradient."""

from __future__ import annotations

import numpy as np
import torch

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.agents.networks import INIT_STD_FRACTION, Actor, CentralCritic, ObsEncoder


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


def test_critic_heads_on_the_live_slots_equal_the_full_grid_there():
    torch.manual_seed(0)
    critic = CentralCritic(2, 3, quantiles=8, hidden=16)
    obs = torch.randn(6, 4, EGO_DIM + 2 * PARTNER_DIM + 3 * ROAD_DIM)
    mask = torch.rand(6, 4) < 0.5
    mask[5] = False  # a group with no live slot
    g, c = mask.nonzero(as_tuple=True)
    flat = g * 4 + c
    v_full, q_full = critic(obs, mask, flat)
    (v_full[g, c].sum() + q_full[g, c].pow(2).sum()).backward()
    grads = [p.grad.clone() for p in critic.parameters()]
    critic.zero_grad()
    v, q = critic(obs, mask, flat, head_rows=flat)
    assert v.shape == (len(flat),) and q.shape == (len(flat), 8)
    torch.testing.assert_close(v, v_full[g, c].detach())
    torch.testing.assert_close(q, q_full[g, c].detach())
    assert (q[:, 1:] >= q[:, :-1]).all()  # still a sorted quantile function
    (v.sum() + q.pow(2).sum()).backward()
    for a, b in zip(grads, (p.grad for p in critic.parameters())):
        torch.testing.assert_close(a, b)


def test_masked_max_pool_matches_numpy_and_the_amax_it_replaces():
    torch.manual_seed(1)
    x = torch.randn(5, 6, 4, requires_grad=True)
    feat = torch.relu(x)  # >= 0 with ties at 0, as the encoders' last ReLU gives
    mask = torch.rand(5, 6) < 0.5
    mask[2] = False  # no entries: pools to zeros
    mask[3] = True
    pooled = ObsEncoder._pool(feat, mask)
    f, m = feat.detach().numpy(), mask.numpy()
    ref = np.stack([f[i][m[i]].max(0) if m[i].any() else np.zeros(4, np.float32) for i in range(5)])
    np.testing.assert_allclose(pooled.detach().numpy(), ref, rtol=0, atol=0)
    w = torch.randn(5, 4)
    (grad,) = torch.autograd.grad((pooled * w).sum(), x, retain_graph=True)
    old = torch.nan_to_num(feat.masked_fill(~mask[..., None], float("-inf")).amax(dim=-2), neginf=0.0)
    (grad_old,) = torch.autograd.grad((old * w).sum(), x)
    torch.testing.assert_close(grad, grad_old)
    assert (grad[~mask] == 0).all() and (grad[2] == 0).all()
