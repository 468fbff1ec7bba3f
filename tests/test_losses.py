"""Tests of tg_gpudrive.learn.losses against independent references.

References are hand-computed small cases, direct NumPy/SciPy implementations
and torch.distributions. Every test runs on cpu, and on cuda when present.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from tg_gpudrive.agents.policy import categorical_kl, gaussian_kl
from tg_gpudrive.learn.losses import (
    LagrangeMultiplier,
    cce_mappo_actor_loss,
    cost_quantile_targets,
    cvar_from_quantiles,
    cvar_gae,
    cvar_tail_advantage,
    gae,
    kl_estimate,
    masked_mean,
    normalize,
    ppo_clip_loss,
    quantile_huber_loss,
    quantile_midpoints,
    var_from_quantiles,
)

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no cuda")),
]


def t(x, device, dtype=torch.float32):
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)


def close(a, b, atol=1e-6, rtol=1e-6):
    a = a.detach().cpu().double().numpy() if torch.is_tensor(a) else np.asarray(a, dtype=np.float64)
    b = b.detach().cpu().double().numpy() if torch.is_tensor(b) else np.asarray(b, dtype=np.float64)
    np.testing.assert_allclose(a, b, atol=atol, rtol=rtol)


@pytest.fixture
def single_cpu_thread():
    # Small ops in a 200-step loop: intra-op threads only add contention on a shared, busy host.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# --------------------------------------------------------------------------- helpers


@pytest.mark.parametrize("device", DEVICES)
def test_masked_mean_ignores_nan_padding_and_handles_empty(device):
    x = t([1.0, 2.0, float("nan"), float("inf")], device)
    mask = t([1, 1, 0, 0], device, torch.bool)
    close(masked_mean(x, mask), 1.5)
    close(masked_mean(x, torch.zeros_like(mask)), 0.0)
    close(masked_mean(t([1.0, 3.0], device)), 2.0)
    xn = normalize(t([1.0, 2.0, 3.0, 100.0], device), t([1, 1, 1, 0], device, torch.bool))
    close(xn[:3], (np.array([1, 2, 3]) - 2.0) / np.std([1, 2, 3]), atol=1e-5)


# --------------------------------------------------------------------------- GAE


@pytest.mark.parametrize("device", DEVICES)
def test_gae_hand_computed_three_steps_with_done_in_middle(device):
    # gamma=0.9, lam=0.8; the episode ends after step 1, so V(s_2) is not bootstrapped into step 1.
    # delta_2 = 3 + 0.9*2.0 - 1.5 = 3.3            A_2 = 3.3
    # delta_1 = 2 + 0         - 1.0 = 1.0          A_1 = 1.0            (recursion cut)
    # delta_0 = 1 + 0.9*1.0   - 0.5 = 1.4          A_0 = 1.4 + 0.72*1.0 = 2.12
    rewards = t([[1.0], [2.0], [3.0]], device)
    values = t([[0.5], [1.0], [1.5], [2.0]], device)
    dones = t([[False], [True], [False]], device, torch.bool)
    adv, ret = gae(rewards, values, dones, gamma=0.9, lam=0.8)
    close(adv[:, 0], [2.12, 1.0, 3.3], atol=1e-6)
    close(ret[:, 0], [2.62, 2.0, 4.8], atol=1e-6)


def _gae_numpy(r, v, d, gamma, lam):
    T = r.shape[0]
    adv = np.zeros_like(r)
    for b in np.ndindex(r.shape[1:]):
        last = 0.0
        for s in reversed(range(T)):
            nd = 1.0 - d[(s, *b)]
            delta = r[(s, *b)] + gamma * v[(s + 1, *b)] * nd - v[(s, *b)]
            last = delta + gamma * lam * nd * last
            adv[(s, *b)] = last
    return adv


@pytest.mark.parametrize("device", DEVICES)
def test_gae_matches_numpy_loop_and_limits(device):
    rng = np.random.default_rng(0)
    T, shape = 17, (3, 5)  # extra leading dims (world, agent) are carried through
    r = rng.normal(size=(T, *shape))
    v = rng.normal(size=(T + 1, *shape))
    d = (rng.random((T, *shape)) < 0.15).astype(np.float64)
    for gamma, lam in [(0.99, 0.95), (0.9, 1.0), (0.9, 0.0)]:
        adv, ret = gae(t(r, device, torch.float64), t(v, device, torch.float64), t(d, device, torch.float64), gamma, lam)
        ref = _gae_numpy(r, v, d, gamma, lam)
        close(adv, ref, atol=1e-10)
        close(ret, ref + v[:-1], atol=1e-10)
        if lam == 0.0:  # one-step TD error
            close(adv, r + gamma * v[1:] * (1 - d) - v[:-1], atol=1e-10)
    # lam = 1 with no dones: discounted Monte-Carlo return with bootstrap, minus V
    adv, ret = gae(t(r, device, torch.float64), t(v, device, torch.float64), t(np.zeros_like(d), device), 0.9, 1.0)
    mc = v[-1].copy()
    for s in reversed(range(T)):
        mc = r[s] + 0.9 * mc
        close(ret[s], mc, atol=1e-10)


def test_gae_carries_no_gradient_and_checks_shapes():
    r = torch.zeros(4, 2, requires_grad=True)
    v = torch.zeros(5, 2, requires_grad=True)
    adv, ret = gae(r, v, torch.zeros(4, 2), 0.99, 0.95)
    assert not adv.requires_grad and not ret.requires_grad
    with pytest.raises(ValueError):
        gae(r, torch.zeros(4, 2), torch.zeros(4, 2), 0.99, 0.95)


# --------------------------------------------------------------------------- PPO


@pytest.mark.parametrize("device", DEVICES)
def test_ppo_clip_loss_hand_computed_both_sides_clipped(device):
    # eps = 0.2. ratio, A -> min(rA, clip(r)A):
    #   1.5,  1 -> min(1.5, 1.2)   =  1.2   clipped above (no gradient)
    #   0.5, -1 -> min(-0.5, -0.8) = -0.8   clipped below (no gradient)
    #   1.1,  2 -> 2.2                       inside the band
    #   0.7,  3 -> min(2.1, 2.4)   =  2.1   outside the band, unclipped branch (pessimistic)
    #   1.5, -2 -> min(-3.0, -2.4) = -3.0   outside the band, unclipped branch
    # loss = -(1.2 - 0.8 + 2.2 + 2.1 - 3.0) / 5 = -0.34
    ratio = np.array([1.5, 0.5, 1.1, 0.7, 1.5])
    A = np.array([1.0, -1.0, 2.0, 3.0, -2.0])
    logp_old = t(np.log([0.3, 0.2, 0.1, 0.4, 0.25]), device, torch.float64)
    logp_new = (logp_old + t(np.log(ratio), device, torch.float64)).requires_grad_(True)
    loss, st = ppo_clip_loss(logp_new, logp_old, t(A, device, torch.float64), clip_eps=0.2)
    close(loss, -0.34, atol=1e-12)
    close(st["clip_frac"], 0.8, atol=1e-12)  # all but the 1.1 ratio lie outside [0.8, 1.2]
    close(st["approx_kl"], np.mean((ratio - 1) - np.log(ratio)), atol=1e-12)
    loss.backward()
    # d loss / d logp_new = -r A / n where the unclipped branch is active, else 0
    close(logp_new.grad, [0.0, 0.0, -1.1 * 2 / 5, -0.7 * 3 / 5, -1.5 * -2 / 5], atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_ppo_clip_loss_mask_equals_subset(device):
    g = torch.Generator().manual_seed(1)
    lp_new, lp_old, adv = (torch.randn(6, 8, generator=g, dtype=torch.float64).to(device) * 0.3 for _ in range(3))
    mask = torch.rand(6, 8, generator=g).to(device) < 0.6
    garbage = torch.where(mask, adv, torch.full_like(adv, float("nan")))
    loss, st = ppo_clip_loss(lp_new, lp_old, garbage, 0.2, mask)
    ref, ref_st = ppo_clip_loss(lp_new[mask], lp_old[mask], adv[mask], 0.2)
    close(loss, ref, atol=1e-12)
    close(st["clip_frac"], ref_st["clip_frac"], atol=1e-12)
    close(st["approx_kl"], ref_st["approx_kl"], atol=1e-12)


# --------------------------------------------------------------------------- quantile regression


def _quantile_huber_numpy(pred, target, kappa, mask=None):
    B, N = pred.shape
    M = target.shape[1]
    rows = np.zeros(B)
    for b in range(B):
        for i in range(N):
            tau = (2 * i + 1) / (2 * N)
            acc = 0.0
            for j in range(M):
                u = target[b, j] - pred[b, i]
                if kappa == 0:
                    h = abs(u)
                elif abs(u) <= kappa:
                    h = 0.5 * u * u / kappa
                else:
                    h = (abs(u) - 0.5 * kappa)
                acc += abs(tau - (1.0 if u < 0 else 0.0)) * h
            rows[b] += acc / M
    if mask is None:
        return rows.mean()
    return rows[mask].mean()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kappa", [0.0, 0.5, 1.0, 2.0])
def test_quantile_huber_loss_matches_numpy(device, kappa):
    rng = np.random.default_rng(2)
    pred = np.sort(rng.normal(size=(5, 7)), axis=1)
    target = rng.normal(scale=2.0, size=(5, 11))
    mask = np.array([True, False, True, True, False])
    got = quantile_huber_loss(t(pred, device, torch.float64), t(target, device, torch.float64), kappa)
    close(got, _quantile_huber_numpy(pred, target, kappa), atol=1e-12)
    got_m = quantile_huber_loss(t(pred, device, torch.float64), t(target, device, torch.float64), kappa, t(mask, device, torch.bool))
    close(got_m, _quantile_huber_numpy(pred, target, kappa, mask), atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_cost_quantile_targets_are_the_distributional_bellman_target(device):
    """Hand-computed: gamma 0.5 (support [0, 2]), costs [1, 0, 1, 1], the episode ends after
    step 2, target-network quantiles q(o_t) = [t, 2t]."""
    c, d = t([1.0, 0.0, 1.0, 1.0], device), t([0.0, 0.0, 1.0, 0.0], device)
    q = t([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0], [3.0, 6.0], [4.0, 8.0]], device)
    # one step: c_t + 0.5 (1 - d_t) q_j(o_{t+1}); row 3: 1 + 0.5 [4, 8] = [3, 5] -> clamped to 2
    close(cost_quantile_targets(c, q, d, 0.5, 1), [[1.5, 2.0], [1.0, 2.0], [1.0, 1.0], [2.0, 2.0]])
    # two steps: row 0: 1 + 0.5 * 0 + 0.25 [2, 4]; row 1: 0 + 0.5 * 1, then the episode ends;
    # row 3 reaches the rollout's end after one step and bootstraps there
    close(cost_quantile_targets(c, q, d, 0.5, 2), [[1.5, 2.0], [0.5, 0.5], [1.0, 1.0], [2.0, 2.0]])
    # ten steps: row 0 sums 1 + 0 + 0.25 * 1 and stops at the episode's end
    close(cost_quantile_targets(c, q, d, 0.5, 10), [[1.25, 1.25], [0.5, 0.5], [1.0, 1.0], [2.0, 2.0]])
    # the spread of the next state's distribution is kept, not recentred on a mean return
    got = cost_quantile_targets(t([0.0], device), t([[0.0, 0.0], [1.0, 9.0]], device), t([0.0], device), 0.9)
    close(got, [[0.9, 8.1]])
    with pytest.raises(ValueError):
        cost_quantile_targets(c, q[:-1], d, 0.5)


@pytest.mark.parametrize("device", DEVICES)
def test_cvar_gae_uses_the_cvar_of_the_quantiles(device):
    """Two states with the same mean cost-to-go (2) but different tails: alpha 0 sees no
    difference, alpha 0.5 does. One step, gamma 0.5, lam 1, c_0 = 0, not done:
    A = 0.5 CVaR(o_1) - CVaR(o_0)."""
    q0 = [2.0, 2.0]  # CVaR_0 = CVaR_0.5 = 2
    q1 = [0.0, 4.0]  # CVaR_0 = 2, CVaR_0.5 = 4
    quant = t([[q0], [q1]], device)  # (T+1 = 2, B = 1, N = 2)
    c, d = t([[0.0]], device), t([[0.0]], device)
    adv0, v0 = cvar_gae(c, quant, d, 0.0, 0.5, 1.0)
    adv5, v5 = cvar_gae(c, quant, d, 0.5, 0.5, 1.0)
    close(v0, [[2.0], [2.0]])
    close(v5, [[2.0], [4.0]])
    close(adv0, [[0.5 * 2.0 - 2.0]])
    close(adv5, [[0.5 * 4.0 - 2.0]])


@pytest.mark.parametrize("device", DEVICES)
def test_var_is_the_atom_that_holds_alpha(device):
    q = t([[0.0, 1.0, 2.0, 3.0]], device)  # atoms of width 1/4
    for alpha, want in {0.0: 0.0, 0.3: 1.0, 0.5: 2.0, 0.74: 2.0, 0.99: 3.0, 1.0: 3.0}.items():
        close(var_from_quantiles(q, alpha), [want])
    close(var_from_quantiles(q.expand(2, 4), t([0.3, 0.8], device)), [1.0, 3.0])


@pytest.mark.parametrize("device", DEVICES)
def test_tail_advantage_tells_equal_mean_actions_apart_by_their_tail(device):
    """A one-step game at an even policy: the safe action always costs 0.5; the risky one costs 0 three times
    in four and 2 otherwise, the same mean. Eight columns hold those outcomes in their proportions (4 safe, 3
    risky at 0, 1 risky at 2), and the critic holds the mixture's exact atoms [0 x3, 0.5 x4, 2]. At alpha 0.75
    VaR = 0.5 and CVaR = 1.25, so by hand A = 0.5 + (G - 0.5)^+ / 0.25 - 1.25: -0.75 at G = 0 or 0.5, 5.25 at 2.
    Averaged per action the tail rule charges the risky action 1.5 more than the safe one, and nothing over the
    policy; cvar_gae's c - CVaR gives both actions the same mean, so the gradient cannot tell them apart."""
    costs = t([[0.5] * 4 + [0.0] * 3 + [2.0]], device)
    atoms = t([0.0] * 3 + [0.5] * 4 + [2.0], device)
    quant = atoms.expand(2, 8, 8).contiguous()
    done = torch.ones_like(costs)
    adv, cvar = cvar_tail_advantage(costs, quant, done, 0.75, 0.99, 0.95)
    close(adv, [[-0.75] * 7 + [5.25]])
    close(cvar[0], [1.25] * 8)
    safe, risky = adv[0, :4].mean(), adv[0, 4:].mean()
    assert float(risky - safe) == pytest.approx(1.5) and float(adv.mean()) == pytest.approx(0.0, abs=1e-6)
    plain, _ = cvar_gae(costs, quant, done, 0.75, 0.99, 0.95, presorted=True)
    assert float(plain[0, 4:].mean() - plain[0, :4].mean()) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_tail_advantage_matches_numpy_and_is_gae_at_alpha_0(device):
    """Against a NumPy loop: the lambda-return over the quantiles' mean, cut at episode ends; VaR the atom at
    floor(alpha N); CVaR the exact upper-tail integral. At alpha 0 with costs and atoms >= 0 and a least atom of
    0, it is the GAE of the mean cost-to-go."""
    rng = np.random.default_rng(0)
    T, B, N, gamma, lam = 6, 5, 8, 0.9, 0.8
    c = rng.uniform(0, 1, (T, B)) * (rng.uniform(size=(T, B)) < 0.5)
    d = (rng.uniform(size=(T, B)) < 0.2).astype(float)
    q = np.sort(rng.exponential(1.0, (T + 1, B, N)), -1)
    q[..., 0] = 0.0
    for alpha in (0.0, 0.3, 0.875):
        mean = q.mean(-1)
        ret, nxt = np.zeros((T, B)), mean[T]
        for s in range(T - 1, -1, -1):
            nxt = c[s] + gamma * (1 - d[s]) * ((1 - lam) * mean[s + 1] + lam * nxt)
            ret[s] = nxt
        k = min(int(np.floor(alpha * N)), N - 1)
        var = q[..., k]
        w = np.clip(np.arange(1, N + 1) / N - alpha, 0, 1 / N)
        cv = (q * w).sum(-1) / w.sum()
        want = var[:-1] + np.maximum(ret - var[:-1], 0) / (1 - alpha) - cv[:-1]
        got, got_cvar = cvar_tail_advantage(t(c, device), t(q, device), t(d, device), alpha, gamma, lam)
        close(got, want, atol=1e-5)
        close(got_cvar, cv, atol=1e-5)
        if alpha == 0.0:
            close(got, gae(t(c, device), t(mean, device), t(d, device), gamma, lam)[0], atol=1e-5)


def test_quantile_midpoints():
    close(quantile_midpoints(4), [0.125, 0.375, 0.625, 0.875])


def test_quantile_huber_loss_does_not_backprop_into_targets():
    pred = torch.zeros(2, 3, requires_grad=True)
    target = torch.randn(2, 4, requires_grad=True)
    quantile_huber_loss(pred, target).backward()
    assert target.grad is None and pred.grad is not None


def _fit_atoms(x, init, kappa, lr, steps):
    """Free atoms (starting at `init`) fitted to the samples `x` by Adam on the quantile Huber loss, the step size
    annealed to 0 over `steps`."""
    q = init.clone().requires_grad_(True)
    opt = torch.optim.Adam([q], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=0.0)
    for _ in range(steps):
        opt.zero_grad()
        quantile_huber_loss(q, x, kappa).backward()
        opt.step()
        sched.step()
    return q.detach()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kappa", [0.0, 0.05])
def test_quantile_huber_minimiser_recovers_true_quantiles(device, kappa, single_cpu_thread):
    # Fit N free quantiles to samples of Gamma(2, 1) (skewed, so a mean/median mix-up would show).
    torch.manual_seed(0)
    n = 8
    x = torch.distributions.Gamma(2.0, 1.0).sample((1, 8000)).to(device)
    tau = quantile_midpoints(n, torch.float64)
    true = stats.gamma(2.0).ppf(tau.numpy())
    got = _fit_atoms(x, torch.zeros(1, n, device=device), kappa, lr=0.3, steps=200)[0].double().cpu()
    # sampling error of the 15/16 quantile with 8k samples is ~0.06; interior ones far less
    close(got[:6], true[:6], atol=0.05)
    close(got, true, atol=0.15)
    if kappa == 0.0:  # pure pinball loss: the minimiser is the empirical quantile itself
        close(got, torch.quantile(x[0].double().cpu(), tau), atol=0.01)


@pytest.mark.parametrize("device", DEVICES)
def test_a_kappa_above_the_cost_scale_crowds_the_quantiles_towards_the_mean(device, single_cpu_thread):
    """A state's discounted cost-to-go is mostly 0 (no close pass ahead) and otherwise a fraction of 1: here 63 %
    zeros, else Exp(mean 0.3). Below kappa the quantile Huber loss is quadratic, whose asymmetric minimiser is an
    expectile, so at kappa 1 the fitted atoms hold no zero and their CVaR_0.875 / CVaR_0.125 is about half the
    sample's: the risk level then hardly matters. kappa 0 (TrainConfig.cost_kappa) fits the quantiles."""
    torch.manual_seed(0)
    x = torch.distributions.Exponential(1 / 0.3).sample((1, 8000))
    x = torch.where(torch.rand(1, 8000) < 0.63, torch.zeros_like(x), x).to(device)
    xs = x.sort(-1).values
    want = cvar_from_quantiles(xs, 0.875, True) / cvar_from_quantiles(xs, 0.125, True)
    spread, zeros = {}, {}
    for kappa in (0.0, 1.0):
        start = torch.full((1, 16), float(x.mean()), device=device)
        qs = _fit_atoms(x, start, kappa, lr=0.05, steps=300).sort(-1).values
        spread[kappa] = float(cvar_from_quantiles(qs, 0.875, True) / cvar_from_quantiles(qs, 0.125, True) / want)
        zeros[kappa] = float((qs < 1e-3).float().mean())
    assert spread[0.0] == pytest.approx(1.0, abs=0.1) and zeros[0.0] == pytest.approx(0.63, abs=0.07)
    assert spread[1.0] < 0.7 and zeros[1.0] == 0.0


# --------------------------------------------------------------------------- CVaR


@pytest.mark.parametrize("device", DEVICES)
def test_cvar_atoms_exact_including_partial_atom(device):
    # atoms 0,1,2,3 of width 1/4 on [0,.25),[.25,.5),[.5,.75),[.75,1]
    q = t([[3.0, 0.0, 2.0, 1.0]], device, torch.float64)  # unsorted on purpose
    cases = {
        0.0: 1.5,  # mean
        0.5: 2.5,  # atoms 2 and 3
        0.6: (0.15 * 2 + 0.25 * 3) / 0.4,  # 0.15 of atom 2 + all of atom 3 = 2.625
        0.75: 3.0,
        0.9: 3.0,
        1.0: 3.0,  # limit: the max
    }
    for alpha, ref in cases.items():
        close(cvar_from_quantiles(q, alpha), [ref], atol=1e-12)
        # the same atoms handed over ascending, as the critic outputs them: no sort, the same CVaR
        close(cvar_from_quantiles(q.sort(-1).values, alpha, presorted=True), [ref], atol=1e-12)
    # per-row alpha tensor
    qq = q.expand(3, 4)
    close(cvar_from_quantiles(qq, t([0.0, 0.6, 1.0], device, torch.float64)), [1.5, 2.625, 3.0], atol=1e-12)
    with pytest.raises(ValueError):
        cvar_from_quantiles(q, 1.5)


@pytest.mark.parametrize("device", DEVICES)
def test_cvar_uniform_and_exponential_analytic(device):
    n = 2000
    tau = quantile_midpoints(n, torch.float64).numpy()
    uni = t(stats.uniform.ppf(tau)[None], device, torch.float64)
    expo = t(stats.expon.ppf(tau)[None], device, torch.float64)
    for alpha in [0.0, 0.1, 0.3333, 0.5, 0.77, 0.9, 0.99]:
        close(cvar_from_quantiles(uni, alpha), [(1 + alpha) / 2], atol=1e-3)  # upper-tail mean of U(0,1)
        # upper-tail mean of Exp(1): VaR + 1 = 1 - ln(1 - alpha); the last atom
        # under-represents the unbounded tail by ~(1 - ln 2)/(n (1 - alpha))
        tol = 2e-3 + 0.5 / (n * (1 - alpha))
        close(cvar_from_quantiles(expo, alpha), [1 - math.log(1 - alpha)], atol=tol)


@pytest.mark.parametrize("device", DEVICES)
def test_cvar_monotone_in_alpha_mean_and_max_limits(device):
    g = torch.Generator().manual_seed(3)
    q = (torch.randn(16, 9, generator=g, dtype=torch.float64) * 3).to(device)
    alphas = torch.linspace(0, 1, 201, dtype=torch.float64)
    curves = torch.stack([cvar_from_quantiles(q, float(a)) for a in alphas], dim=0)  # (201, 16)
    assert torch.all(curves[1:] - curves[:-1] >= -1e-12)
    close(curves[0], q.mean(-1), atol=1e-12)
    close(curves[-1], q.max(-1).values, atol=1e-12)
    # continuity in alpha: steps of 1/200 move CVaR by a bounded amount
    assert torch.all((curves[1:] - curves[:-1]).abs() < 2.0)


def test_cvar_gradient_flows_to_quantiles():
    q = torch.tensor([[0.0, 1.0, 2.0, 3.0]], requires_grad=True)
    cvar_from_quantiles(q, 0.6).sum().backward()
    close(q.grad, [[0.0, 0.0, 0.15 / 0.4, 0.25 / 0.4]], atol=1e-6)


# --------------------------------------------------------------------------- Lagrange multiplier


@pytest.mark.parametrize("device", DEVICES)
def test_lagrange_multiplier_is_projected_gradient_ascent(device):
    lm = LagrangeMultiplier(init_value=1.0, lr=0.05).to(device)
    close(lm.value, 1.0)
    close(lm.update(torch.tensor(3.0, device=device), 1.0), 1.1)  # 1 + 0.05 * (3 - 1)
    close(lm.update(torch.tensor(11.0, device=device), 1.0), 1.6)  # the step grows with the violation
    close(lm.update(0.0, 1.0), 1.55)  # satisfied: falls by lr * slack
    for _ in range(100):
        lm.update(0.0, 1.0)
    close(lm.value, 0.0)  # projected at 0, never negative
    with pytest.raises(ValueError):
        LagrangeMultiplier(init_value=-1.0)
    capped = LagrangeMultiplier(init_value=1.0, lr=0.5, upper=2.0).to(device)
    close(capped.update(2.0, 1.0), 1.5)  # 1 + 0.5 * (2 - 1): inside the bound, the plain step
    close(capped.update(5.0, 1.0), 2.0)  # 1.5 + 2 = 3.5, projected onto [0, 2]
    close(capped.update(0.0, 1.0), 1.5)  # and it falls from the bound at once
    with pytest.raises(ValueError, match="upper"):
        LagrangeMultiplier(init_value=3.0, upper=2.0)


@pytest.mark.parametrize("device", DEVICES)
def test_lagrange_multiplier_per_agent(device):
    lm = LagrangeMultiplier(init_value=2.0, lr=0.1, shape=(3,)).to(device)
    constraint = torch.tensor([5.0, 1.0, 0.0], device=device, requires_grad=True)
    close(lm.update(constraint, 1.0), [2.4, 2.0, 1.9])  # each agent by its own violation
    assert constraint.grad is None
    with pytest.raises(ValueError):
        lm.update(torch.zeros(8, 3, device=device), 1.0)
    # lambda is state that checkpoints carry
    other = LagrangeMultiplier(shape=(3,))
    other.load_state_dict(lm.state_dict())
    close(other.value, [2.4, 2.0, 1.9])


# --------------------------------------------------------------------------- KL divergences


@pytest.mark.parametrize("device", DEVICES)
def test_categorical_kl_vs_closed_form_and_torch_distributions(device):
    g = torch.Generator().manual_seed(4)
    lp = (torch.randn(4, 6, 5, generator=g, dtype=torch.float64) * 2).to(device)
    lq = (torch.randn(4, 6, 5, generator=g, dtype=torch.float64) * 2).to(device)
    got = categorical_kl(lp, lq)
    ref = torch.distributions.kl_divergence(
        torch.distributions.Categorical(logits=lp), torch.distributions.Categorical(logits=lq)
    )
    close(got, ref, atol=1e-12)
    p = np.exp(lp.cpu().numpy()); p /= p.sum(-1, keepdims=True)
    q = np.exp(lq.cpu().numpy()); q /= q.sum(-1, keepdims=True)
    close(got, (p * np.log(p / q)).sum(-1), atol=1e-12)
    close(categorical_kl(lp, lp), torch.zeros(4, 6), atol=1e-12)
    # masked (-inf) actions in p contribute nothing; support mismatch in q is +inf
    lp_m = lp.clone(); lp_m[..., 0] = -math.inf
    assert torch.isfinite(categorical_kl(lp_m, lq)).all()
    close(categorical_kl(lp_m, lq), stats.entropy(
        np.exp(lp_m.cpu().numpy()) / np.exp(lp_m.cpu().numpy()).sum(-1, keepdims=True),
        q, axis=-1), atol=1e-12)
    assert torch.isinf(categorical_kl(lq, lp_m)).all()


@pytest.mark.parametrize("device", DEVICES)
def test_gaussian_kl_vs_closed_form_and_torch_distributions(device):
    g = torch.Generator().manual_seed(5)
    mu_p, mu_q = (torch.randn(7, 2, generator=g, dtype=torch.float64).to(device) for _ in range(2))
    ls_p, ls_q = ((torch.randn(7, 2, generator=g, dtype=torch.float64) * 0.5).to(device) for _ in range(2))
    got = gaussian_kl(mu_p, ls_p, mu_q, ls_q)
    Normal, Ind = torch.distributions.Normal, torch.distributions.Independent
    ref = torch.distributions.kl_divergence(Ind(Normal(mu_p, ls_p.exp()), 1), Ind(Normal(mu_q, ls_q.exp()), 1))
    close(got, ref, atol=1e-12)
    sp, sq = ls_p.exp().cpu().numpy(), ls_q.exp().cpu().numpy()
    d = (mu_p - mu_q).cpu().numpy()
    close(got, (np.log(sq / sp) + (sp**2 + d**2) / (2 * sq**2) - 0.5).sum(-1), atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_k3_estimator_unbiased_nonnegative_matches_exact_gaussian_kl(device):
    torch.manual_seed(6)
    # q narrower than p, so r = q/p is bounded and k3 has finite variance (see the docstring)
    mu_p, ls_p = torch.tensor([0.2, -0.1], device=device), torch.tensor([0.2, -0.1], device=device)
    mu_q, ls_q = torch.tensor([0.5, 0.1], device=device), torch.tensor([0.0, -0.3], device=device)
    p = torch.distributions.Independent(torch.distributions.Normal(mu_p, ls_p.exp()), 1)
    q = torch.distributions.Independent(torch.distributions.Normal(mu_q, ls_q.exp()), 1)
    x = p.sample((400_000,))
    exact = gaussian_kl(mu_p, ls_p, mu_q, ls_q).item()
    k3 = kl_estimate(p.log_prob(x), q.log_prob(x))
    assert (k3 >= 0).all()
    assert abs(k3.mean().item() - exact) < 5e-3 + 4 * k3.std().item() / math.sqrt(x.shape[0])
    k1 = kl_estimate(p.log_prob(x), q.log_prob(x), "k1")
    assert abs(k1.mean().item() - exact) < 5 * k1.std().item() / math.sqrt(x.shape[0])
    with pytest.raises(ValueError):
        kl_estimate(k3, k3, "k4")


def test_kl_estimator_gradients_with_fixed_on_policy_samples():
    # Documented behaviour: with samples x ~ p held fixed, E[grad k2] = grad KL(p||q)
    # and E[grad k3] = grad KL(q||p) w.r.t. p's parameters.
    torch.manual_seed(7)
    mu_q, ls_q = torch.tensor([0.6]), torch.tensor([-0.2])  # q narrower than p: bounded q/p
    mu_p = torch.tensor([0.0], requires_grad=True)
    ls_p = torch.tensor([0.3], requires_grad=True)
    with torch.no_grad():
        x = mu_p + ls_p.exp() * torch.randn(400_000, 1, dtype=torch.float32)

    def logn(x, mu, ls):
        return (-0.5 * ((x - mu) / ls.exp()) ** 2 - ls - 0.5 * math.log(2 * math.pi)).sum(-1)

    def grads(f):
        gm, gl = torch.autograd.grad(f, (mu_p, ls_p))
        return torch.cat([gm, gl])

    g_k2 = grads(kl_estimate(logn(x, mu_p, ls_p), logn(x, mu_q, ls_q), "k2").mean())
    g_k3 = grads(kl_estimate(logn(x, mu_p, ls_p), logn(x, mu_q, ls_q), "k3").mean())
    g_fwd = grads(gaussian_kl(mu_p, ls_p, mu_q, ls_q))
    g_rev = grads(gaussian_kl(mu_q, ls_q, mu_p, ls_p))
    close(g_k2, g_fwd, atol=2e-2)
    close(g_k3, g_rev, atol=2e-2)
    assert (g_fwd - g_rev).abs().max() > 0.1  # the two really differ here


# --------------------------------------------------------------------------- CCE-MAPPO actor loss


def _actor_inputs(device, shape=(5, 12), seed=8):
    g = torch.Generator().manual_seed(seed)
    r = lambda s=1.0: (torch.randn(*shape, generator=g, dtype=torch.float64) * s).to(device)  # noqa: E731
    logp_old = r(0.5) - 1.0
    logp_new = (logp_old + r(0.2)).requires_grad_(True)
    return dict(
        logp_new=logp_new,
        logp_old=logp_old,
        adv_reward=r(2.0),
        adv_cost=r(1.5) + 0.7,
        entropy=r().abs(),
        kl_prior=r().abs(),
        kl_prev=r().abs(),
    )


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("norm", [False, True])
def test_actor_loss_reduces_to_ppo(device, norm):
    inp = _actor_inputs(device)
    inp["entropy"] = torch.zeros_like(inp["entropy"])
    loss, st = cce_mappo_actor_loss(
        **inp, lagrange=0.0, clip_eps=0.2, entropy_coef=0.01, eta1=0.0, eta2=math.inf, normalize_advantages=norm
    )
    adv = normalize(inp["adv_reward"]) if norm else inp["adv_reward"]
    ref, ref_st = ppo_clip_loss(inp["logp_new"], inp["logp_old"], adv, 0.2)
    close(loss, ref, atol=1e-12)
    close(st["pg_loss"], ref, atol=1e-12)
    close(st["clip_frac"], ref_st["clip_frac"], atol=1e-12)
    if norm:
        close(adv.mean(), 0.0, atol=1e-12)
        close(adv.std(unbiased=False), 1.0, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_actor_loss_lambda_pushes_policy_along_minus_cost_advantage(device):
    inp = _actor_inputs(device)
    # ratio 1 everywhere: no clipping, so the policy gradient is exactly -A / n
    inp["logp_new"] = inp["logp_old"].clone().requires_grad_(True)
    n = inp["logp_new"].numel()
    kw = dict(clip_eps=0.2, entropy_coef=0.0, eta1=0.0, eta2=math.inf, normalize_advantages=False)

    def grad_and_loss(lam):
        lp = inp["logp_new"].detach().clone().requires_grad_(True)
        loss, _ = cce_mappo_actor_loss(**{**inp, "logp_new": lp}, lagrange=lam, **kw)
        (g,) = torch.autograd.grad(loss, lp)
        return g, loss

    g0, l0 = grad_and_loss(0.0)
    g1, l1 = grad_and_loss(0.5)
    # descent step -grad changes by -lambda * A_c / n: probability moves away from costly actions
    close(g1 - g0, 0.5 * inp["adv_cost"] / n, atol=1e-12)
    close(l1 - l0, 0.5 * inp["adv_cost"].mean(), atol=1e-12)

    # with normalisation, growing lambda turns the update direction towards -A_c
    kw["normalize_advantages"] = True
    cos = []
    for lam in [0.0, 1.0, 10.0, 1000.0]:
        g, _ = grad_and_loss(lam)
        centred_cost = inp["adv_cost"] - inp["adv_cost"].mean()  # normalisation removes the mean
        cos.append(torch.nn.functional.cosine_similarity(-g.flatten(), -centred_cost.flatten(), dim=0).item())
    assert all(b > a for a, b in zip(cos, cos[1:])) and cos[-1] > 0.999

    # per-agent lambda broadcasts over time; lambda gets no gradient from the actor loss
    lam_vec = torch.full((inp["adv_reward"].shape[-1],), 0.5, device=device, dtype=torch.float64, requires_grad=True)
    loss, st = cce_mappo_actor_loss(**inp, lagrange=lam_vec, **{**kw, "normalize_advantages": False})
    close(loss, l1, atol=1e-12)
    close(st["lagrange"], 0.5, atol=1e-12)
    assert not loss.requires_grad or torch.autograd.grad(loss, lam_vec, allow_unused=True)[0] is None


@pytest.mark.parametrize("device", DEVICES)
def test_actor_loss_kl_and_entropy_terms_add_exactly(device):
    inp = _actor_inputs(device)
    mask = (torch.rand(5, 12, generator=torch.Generator().manual_seed(9)) < 0.7).to(device)
    base, _ = cce_mappo_actor_loss(**inp, lagrange=0.3, mask=mask)
    eta1, eta2, ent = 0.7, 4.0, 0.05
    loss, st = cce_mappo_actor_loss(**inp, lagrange=0.3, entropy_coef=ent, eta1=eta1, eta2=eta2, mask=mask)
    m = mask
    expected = (
        base
        + eta1 * inp["kl_prior"][m].mean()
        + inp["kl_prev"][m].mean() / eta2
        - ent * inp["entropy"][m].mean()
    )
    close(loss, expected, atol=1e-12)
    close(st["kl_prior_term"], eta1 * inp["kl_prior"][m].mean(), atol=1e-12)
    close(st["kl_prev_term"], inp["kl_prev"][m].mean() / eta2, atol=1e-12)
    close(st["entropy_term"], -ent * inp["entropy"][m].mean(), atol=1e-12)
    close(st["loss"], loss, atol=1e-12)
    close(st["pg_loss"] + st["entropy_term"] + st["kl_prior_term"] + st["kl_prev_term"], loss, atol=1e-12)
    # gradients reach the KL and entropy inputs with the right weights
    kl_prior = inp["kl_prior"].clone().requires_grad_(True)
    kl_prev = inp["kl_prev"].clone().requires_grad_(True)
    loss, _ = cce_mappo_actor_loss(**{**inp, "kl_prior": kl_prior, "kl_prev": kl_prev}, lagrange=0.3,
                                   eta1=eta1, eta2=eta2, mask=mask)
    ga, gb = torch.autograd.grad(loss, (kl_prior, kl_prev))
    close(ga, eta1 * m.double() / m.sum(), atol=1e-12)
    close(gb, m.double() / m.sum() / eta2, atol=1e-12)
    with pytest.raises(ValueError):
        cce_mappo_actor_loss(**inp, lagrange=0.0, eta2=0.0)
