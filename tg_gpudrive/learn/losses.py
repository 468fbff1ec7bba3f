"""The tested math of the CCE-MAPPO learner: GAE, PPO / quantile / Lagrangian losses, CVaR, KLs.

Everything here is a pure function of torch tensors (plus one tiny ``nn.Module``
for the Lagrange multiplier), works on whatever device its inputs live on, and
is batched: agents and worlds are flattened or carried as leading dimensions,
never looped over in Python. The only Python loop is GAE's reverse scan over
time.

This module must not know about networks, rollouts, the engine or configs; the
training loop builds the tensors and reads the returned stats. Stats are
returned as detached tensors (not floats) so that a GPU step never syncs; call
``.item()`` when logging.

Shapes used below:

    ==========  =====================================================
    T           rollout steps
    B           flattened batch of agents (any extra leading dims are
                allowed wherever a docstring writes ``...``)
    N           number of predicted quantiles of the cost critic
    M           number of target samples per quantile regression row
    A           action dimension (continuous actions)
    K           number of discrete actions
    ==========  =====================================================

Masks: a mask is ``1``/``True`` for a valid entry and
``0``/``False`` for padding; masked entries are excluded from every mean and
may hold any finite or non-finite garbage without affecting the result.

CVaR convention (TrafficGamer's risk level ``alpha``), see ``cvar_from_quantiles``:

    CVaR_alpha(C) = 1/(1 - alpha) * integral_{alpha}^{1} F_C^{-1}(tau) dtau
                  = E[C | C >= VaR_alpha(C)]          (continuous C)

i.e. the mean of the *upper* (1 - alpha) tail of the cost C. ``alpha = 0`` is
the plain expected cost (risk-neutral, the most aggressive setting) and
``alpha -> 1`` is the worst-case cost (the most conservative setting). So a
lower ``alpha`` gives more aggressive driving, as in the TrafficGamer paper.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "masked_mean",
    "normalize",
    "gae",
    "ppo_clip_loss",
    "quantile_midpoints",
    "quantile_huber_loss",
    "cvar_from_quantiles",
    "var_from_quantiles",
    "cvar_gae",
    "cvar_tail_advantage",
    "cost_quantile_targets",
    "LagrangeMultiplier",
    "kl_estimate",
    "cce_mappo_actor_loss",
]


# --------------------------------------------------------------------------- helpers


def masked_mean(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of ``x`` over all entries where ``mask`` is non-zero (scalar tensor).

    ``mask`` broadcasts to ``x`` and may be bool or 0/1 float (fractional
    weights act as weights). Masked entries are replaced by zero *before* the
    product, so NaN/inf padding does not leak. An all-masked batch gives 0.
    """
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype).expand_as(x)
    num = (torch.where(m != 0, x, torch.zeros_like(x)) * m).sum()
    return num / m.sum().clamp_min(torch.finfo(x.dtype).tiny)


def normalize(x: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-8) -> torch.Tensor:
    """Standardise ``x`` to zero mean, unit (population) std over the valid entries."""
    mean = masked_mean(x, mask)
    var = masked_mean((x - mean) ** 2, mask)
    return (x - mean) / (var.sqrt() + eps)


# --------------------------------------------------------------------------- GAE


@torch.no_grad()
def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimation (Schulman et al. 2016) by a reverse scan over T.

    ===========  ===========  ============  ==========================================
    name         shape        dtype         meaning
    ===========  ===========  ============  ==========================================
    rewards      (T, ...)     float         r_t, received after acting at step t
    values       (T+1, ...)   float         V(s_t); row T is the bootstrap V(s_T)
    dones        (T, ...)     bool / 0-1    the episode ended after step t
    advantages   (T, ...)     float         returned
    returns      (T, ...)     float         returned, advantages + values[:T]
    ===========  ===========  ============  ==========================================

    ``dones[t]`` cuts both the bootstrap ``V(s_{t+1})`` (it belongs to the next
    episode after an auto-reset) and the advantage recursion. A time-limit
    truncation is treated as a termination; pass ``dones`` = terminations only
    and fold the bootstrap into ``rewards`` if truncations must bootstrap.
    Outputs carry no gradient (they are regression/policy targets).
    """
    T = rewards.shape[0]
    if values.shape[0] != T + 1 or values.shape[1:] != rewards.shape[1:]:
        raise ValueError(f"values must have shape (T+1, ...) = {(T + 1, *rewards.shape[1:])}, got {tuple(values.shape)}")
    if dones.shape != rewards.shape:
        raise ValueError(f"dones must have the shape of rewards {tuple(rewards.shape)}, got {tuple(dones.shape)}")
    not_done = 1.0 - dones.to(rewards.dtype)
    deltas = rewards + gamma * values[1:] * not_done - values[:-1]
    discount = gamma * lam * not_done
    advantages = torch.empty_like(rewards)
    last = torch.zeros_like(rewards[0])
    for t in range(T - 1, -1, -1):
        last = deltas[t] + discount[t] * last
        advantages[t] = last
    return advantages, advantages + values[:-1]


# --------------------------------------------------------------------------- PPO


def clipped_surrogate(ratio: torch.Tensor, advantages: torch.Tensor, clip_eps: float) -> torch.Tensor:
    """PPO's clipped objective per sample: min(r A, clip(r, 1 - eps, 1 + eps) A) (to maximise)."""
    return torch.minimum(ratio * advantages, ratio.clamp(1.0 - clip_eps, 1.0 + clip_eps) * advantages)


def ppo_clip_loss(
    logp_new: torch.Tensor,
    logp_old: torch.Tensor,
    advantages: torch.Tensor,
    clip_eps: float,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """PPO clipped surrogate, returned as a loss to minimise (the negated objective).

    ==========  ======  =====================================================
    name        shape   meaning
    ==========  ======  =====================================================
    logp_new    (...)   log pi_theta(a|s) of the taken action, with gradient
    logp_old    (...)   log pi_old(a|s) recorded at rollout time (detached here)
    advantages  (...)   advantage estimates (detached here)
    mask        (...)   optional validity mask
    ==========  ======  =====================================================

    loss = -mean( min(r A, clip(r, 1-eps, 1+eps) A) ),  r = exp(logp_new - logp_old).

    Stats (detached scalars): ``clip_frac`` = fraction with |r - 1| > eps (CleanRL's
    definition; it counts ratios outside the band even where the min picks the
    unclipped branch), ``approx_kl`` = mean((r - 1) - log r), the k3 estimate of
    KL(pi_old || pi_theta).
    """
    log_ratio = logp_new - logp_old.detach()
    ratio = log_ratio.exp()
    adv = advantages.detach()
    loss = -masked_mean(clipped_surrogate(ratio, adv, clip_eps), mask)
    with torch.no_grad():
        stats = {
            "clip_frac": masked_mean(((ratio - 1.0).abs() > clip_eps).to(ratio.dtype), mask),
            "approx_kl": masked_mean(torch.expm1(log_ratio) - log_ratio, mask),
        }
    return loss, stats


# --------------------------------------------------------------------------- distributional cost critic


def quantile_midpoints(n: int, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """tau_i = (2i + 1) / (2N), i = 0..N-1: the quantile levels QR-DQN regresses."""
    return (2.0 * torch.arange(n, dtype=dtype, device=device) + 1.0) / (2.0 * n)


def quantile_huber_loss(
    pred_quantiles: torch.Tensor,
    target_samples: torch.Tensor,
    kappa: float = 1.0,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """QR-DQN quantile Huber loss (Dabney et al. 2018, eq. 10), a scalar to minimise.

    ==============  ========  =================================================
    name            shape     meaning
    ==============  ========  =================================================
    pred_quantiles  (..., N)  predicted quantiles at tau_i = (2i+1)/(2N)
    target_samples  (..., M)  samples / atoms of the target distribution
                              (e.g. c + gamma * next quantiles); detached here
    mask            (...)     optional validity mask over rows
    ==============  ========  =================================================

    With u_ij = target_j - pred_i:

        rho_i(u) = |tau_i - 1{u < 0}| * L_kappa(u) / kappa,
        L_kappa(u) = u^2 / 2 if |u| <= kappa else kappa (|u| - kappa / 2),
        loss_row = sum_i mean_j rho_i(u_ij),  loss = masked mean over rows.

    ``kappa = 0`` gives the plain quantile-regression (pinball) loss
    |tau - 1{u<0}| |u|, whose minimiser is exactly the tau-quantile; for
    ``kappa > 0`` the minimiser is within O(kappa) of it.
    """
    if kappa < 0:
        raise ValueError(f"kappa must be >= 0, got {kappa}")
    n = pred_quantiles.shape[-1]
    tau = quantile_midpoints(n, pred_quantiles.dtype, pred_quantiles.device)
    u = target_samples.detach().unsqueeze(-2) - pred_quantiles.unsqueeze(-1)  # (..., N, M)
    abs_u = u.abs()
    if kappa > 0:
        huber = torch.where(abs_u <= kappa, 0.5 * u * u, kappa * (abs_u - 0.5 * kappa)) / kappa
    else:
        huber = abs_u
    weight = (tau.unsqueeze(-1) - (u.detach() < 0).to(u.dtype)).abs()
    per_row = (weight * huber).mean(-1).sum(-1)
    return masked_mean(per_row, mask)


def cost_to_go_bound(gamma: float, max_cost: float = 1.0) -> float:
    """Largest discounted cost-to-go of a per-step cost in [0, max_cost]: max_cost / (1 - gamma)."""
    return max_cost / (1.0 - gamma)


def cost_quantile_targets(
    cost: torch.Tensor,
    quant: torch.Tensor,
    done: torch.Tensor,
    gamma: float,
    nstep: int = 1,
    max_cost: float = 1.0,
) -> torch.Tensor:
    """Distributional Bellman targets of the cost critic's quantiles (QR-DQN; n-step as in Rainbow).

    ==========  ============  ================================================
    name        shape         meaning
    ==========  ============  ================================================
    cost        (T, ...)      c_t, the cost received after acting at step t
    quant       (T+1, ..., N) quantiles q_j(o_t) of the target network (the critic as
                              it was when the rollout was collected); row T: o_T
    done        (T, ...)      1 where the episode ended after step t
    returns     (T, ..., N)   target atoms z_j for every step t
    ==========  ============  ================================================

    nstep = 1 is the one-step target z_j = c_t + gamma (1 - d_t) q_j(o_{t+1}). With n
    steps, z_j = sum_{k<m} gamma^k c_{t+k} + gamma^m q_j(o_{t+m}), m = min(n, T - t),
    and the sum and the bootstrap stop at the first episode end: the same distributional
    Bellman operator applied m times with the sampled costs, which moves cost information
    n steps per update instead of one. Every predicted quantile regresses on all N atoms
    (quantile_huber_loss), so the critic learns the distribution of the discounted
    cost-to-go, spread included. Atoms are clamped to the support [0, max_cost / (1 - gamma)]
    of a discounted sum of per-step costs in [0, max_cost] (the engine's cost is an
    indicator: max_cost = 1), so an early critic's overshoot cannot feed on itself.
    """
    T = cost.shape[0]
    if quant.shape[0] != T + 1:
        raise ValueError(f"quant must have T+1 = {T + 1} rows, got {quant.shape[0]}")
    if nstep < 1:
        raise ValueError(f"nstep must be >= 1, got {nstep}")
    not_done = 1.0 - done.to(cost.dtype)
    acc = torch.zeros_like(cost)  # sum of discounted costs so far
    disc = torch.ones_like(cost)  # gamma^k while the episode goes on, 0 after it ended
    target = torch.zeros_like(quant[:-1])
    for k in range(min(nstep, T)):  # an offset of T or more reaches no step of the rollout
        t_k = torch.arange(T, device=cost.device) + k  # step consumed by row t at offset k
        inside = t_k < T
        tk = t_k.clamp(max=T - 1)
        shape = (T,) + (1,) * (cost.dim() - 1)
        inside_f = inside.to(cost.dtype).reshape(shape)
        acc = acc + inside_f * disc * cost[tk]
        disc_next = disc * gamma * not_done[tk]
        # rows whose window ends here bootstrap from o_{t+k+1}: the last offset, or the rollout's end
        ends = inside & ((t_k == T - 1) | torch.full_like(inside, k == nstep - 1))
        e = ends.to(cost.dtype).reshape(shape)
        target = target + e[..., None] * (acc[..., None] + disc_next[..., None] * quant[tk + 1])
        disc = torch.where(inside.reshape(shape), disc_next, disc)
    return target.clamp(0.0, cost_to_go_bound(gamma, max_cost))


def cvar_from_quantiles(quantiles: torch.Tensor, alpha: float | torch.Tensor, presorted: bool = False) -> torch.Tensor:
    """CVaR at risk level ``alpha`` of a COST distribution given by N quantiles.

    ==========  ========  ======================================================
    name        shape     meaning
    ==========  ========  ======================================================
    quantiles   (..., N)  cost quantiles at tau_i = (2i+1)/(2N); need not be sorted
    alpha       () / (...)  risk level in [0, 1], float or tensor broadcasting
                          to the leading dims (one level per agent is fine)
    returns     (...)     CVaR_alpha of the cost
    ==========  ========  ======================================================

    Convention (upper tail; lower alpha = less risk-averse = more aggressive):

        CVaR_alpha(C) = 1/(1 - alpha) * integral_{alpha}^{1} F^{-1}(tau) dtau.

    alpha = 0 is the mean cost, alpha -> 1 the largest cost; CVaR is
    non-decreasing in alpha. The N quantiles are read as equally weighted atoms
    of width 1/N: the quantile function is piecewise constant, the i-th sorted
    value on [i/N, (i+1)/N). The integral is taken exactly, including the
    partial atom that straddles alpha, so CVaR is continuous and piecewise
    smooth in alpha. Quantiles are sorted first (quantile crossing of a learned
    critic would otherwise make the tail ill-defined); the gradient flows to
    the quantile values through the sort. ``alpha = 1`` returns the max.
    ``presorted``: the quantiles are ascending already (a critic that sorts its
    output), so the sort, the largest cost of a big batch's CVaR, is skipped.
    """
    q = quantiles if presorted else quantiles.sort(dim=-1).values
    n = q.shape[-1]
    if isinstance(alpha, (int, float)) and not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    a = torch.as_tensor(alpha, dtype=q.dtype, device=q.device).clamp(0.0, 1.0).unsqueeze(-1)
    upper_edges = torch.arange(1, n + 1, dtype=q.dtype, device=q.device) / n
    # Width of [alpha, 1] that falls inside each atom's [i/N, (i+1)/N).
    weights = (upper_edges - a).clamp(0.0, 1.0 / n)
    tail = weights.sum(-1)
    cvar = (weights * q).sum(-1) / tail.clamp_min(torch.finfo(q.dtype).tiny)
    return torch.where(tail > 0, cvar, q[..., -1])


@torch.no_grad()
def cvar_gae(
    costs: torch.Tensor,
    quantiles: torch.Tensor,
    dones: torch.Tensor,
    alpha: float | torch.Tensor,
    gamma: float,
    lam: float,
    presorted: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost advantages from CVaR_alpha of the quantile critic, so the risk level reaches the actor
    (``presorted``: see cvar_from_quantiles).

    ==========  ============  ================================================
    name        shape         meaning
    ==========  ============  ================================================
    costs       (T, ...)      c_t
    quantiles   (T+1, ..., N) cost quantiles of o_t; row T is the bootstrap o_T
    dones       (T, ...)      the episode ended after step t
    advantages  (T, ...)      returned: GAE over the CVaR values
    cvar        (T+1, ...)    returned: CVaR_alpha(Z(o_t)), the constraint's per-state value
    ==========  ============  ================================================

        delta_t = c_t + gamma (1 - d_t) CVaR_alpha(Z(o_{t+1})) - CVaR_alpha(Z(o_t)),
        A_t     = sum_k (gamma lam)^k delta_{t+k}   (cut at episode ends)

    With alpha = 0 this is the ordinary GAE of the mean cost-to-go; a higher alpha
    weighs states by their cost tail, so two actions with the same expected cost but a
    riskier outcome get different advantages.
    """
    cvar = cvar_from_quantiles(quantiles, alpha, presorted)
    adv, _ = gae(costs, cvar, dones, gamma, lam)
    return adv, cvar


def var_from_quantiles(quantiles: torch.Tensor, alpha: float | torch.Tensor) -> torch.Tensor:
    """VaR_alpha, the alpha-quantile of a cost given by N ascending quantiles read as atoms of width 1/N (as in
    cvar_from_quantiles): the atom that holds tau = alpha, the last one at alpha = 1. (...) from (..., N)."""
    n = quantiles.shape[-1]
    a = torch.as_tensor(alpha, dtype=quantiles.dtype, device=quantiles.device).clamp(0.0, 1.0).unsqueeze(-1)
    idx = (a * n).floor().clamp(max=n - 1).long().expand(*quantiles.shape[:-1], 1)
    return quantiles.gather(-1, idx).squeeze(-1)


@torch.no_grad()
def cvar_tail_advantage(
    costs: torch.Tensor,
    quantiles: torch.Tensor,
    dones: torch.Tensor,
    alpha: float | torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost advantages that weigh each sampled cost-to-go by whether it falls in its state's upper tail, so the
    risk level reaches the actor through the costs the policy met, not only through the critic's bootstraps.

    ==========  ============  ================================================
    name        shape         meaning
    ==========  ============  ================================================
    costs       (T, ...)      c_t
    quantiles   (T+1, ..., N) ascending cost quantiles of o_t; row T is the bootstrap o_T
    dones       (T, ...)      the episode ended after step t
    alpha       float         risk level in [0, 1)
    advantages  (T, ...)      returned
    cvar        (T+1, ...)    returned: CVaR_alpha(Z(o_t)), the constraint's per-state value
    ==========  ============  ================================================

        G_t = the lambda-return of the costs over the critic's mean cost-to-go (GAE's return)
        v_t = VaR_alpha(Z(o_t))
        A_t = v_t + (G_t - v_t)^+ / (1 - alpha) - CVaR_alpha(Z(o_t))

    CVaR_alpha(Z) = min_v v + E[(Z - v)^+] / (1 - alpha), attained at v = VaR_alpha(Z) (Rockafellar and
    Uryasev), so under an exact critic A_t has mean 0 at each state and its expectation over the actions has the
    gradient of CVaR_alpha(Z(o_t)) (Tamar et al.'s CVaR policy gradient): a sampled future counts only by how far
    its cost-to-go rises above the state's VaR, times 1 / (1 - alpha). cvar_gae's advantage is the sampled cost
    minus a CVaR baseline, which moves no action's expectation relative to another's; alpha reaches it only
    through the bootstraps, which gae lambda near 1 makes small. At alpha = 0 (returns at or above the least
    quantile) this is the ordinary GAE of the mean cost-to-go.
    """
    if isinstance(alpha, (int, float)) and not 0.0 <= alpha < 1.0:
        raise ValueError(f"alpha must be in [0, 1) for the tail advantage, got {alpha}")
    mean = quantiles.mean(-1)
    _, ret = gae(costs, mean, dones, gamma, lam)
    var = var_from_quantiles(quantiles, alpha)
    cvar = cvar_from_quantiles(quantiles, alpha, presorted=True)
    a = torch.as_tensor(alpha, dtype=costs.dtype, device=costs.device)
    adv = var[:-1] + (ret - var[:-1]).clamp_min(0.0) / (1.0 - a) - cvar[:-1]
    return adv, cvar


# --------------------------------------------------------------------------- Lagrangian


class LagrangeMultiplier(torch.nn.Module):
    """Non-negative Lagrange multiplier(s) of a cost constraint, raised by plain gradient ascent.

    The constrained problem max R s.t. g <= budget has Lagrangian
    R - lambda (g - budget); its dual step is projected gradient ascent,

        lambda <- min(upper, max(0, lambda + lr * (g - budget))),

    so the step grows with the violation (an Adam step would not: it normalises the
    gradient away) and lambda falls back to 0 once the constraint holds with room.
    ``shape`` gives one multiplier per entry (e.g. ``(num_agents,)``: TrafficGamer's
    lambda_i per agent); ``constraint_value`` must broadcast to that shape (one
    estimate per multiplier, e.g. each agent's mean CVaR over its states), never to a
    larger batch. lambda lives in a buffer: it is state, not a parameter of any loss.
    ``upper`` bounds the projection from above too (lambda in [0, upper]): how far the cost may outweigh the
    reward in the actor's advantage, however long the constraint stays violated.
    """

    def __init__(self, init_value: float = 0.0, lr: float = 1e-2, shape: tuple[int, ...] = (),
                 upper: float = math.inf):
        super().__init__()
        if not 0 <= init_value <= upper:
            raise ValueError(f"init_value must lie in [0, upper = {upper}], got {init_value}")
        if not lr >= 0:
            raise ValueError(f"lr must be >= 0, got {lr}")
        self.register_buffer("lam", torch.full(tuple(shape), float(init_value)))
        self.lr, self.upper = lr, float(upper)

    @property
    def value(self) -> torch.Tensor:
        """lambda >= 0, shape ``shape``."""
        return self.lam

    def forward(self) -> torch.Tensor:
        return self.lam

    @torch.no_grad()
    def update(self, constraint_value: torch.Tensor | float, budget: torch.Tensor | float) -> torch.Tensor:
        """One projected ascent step; returns the new lambda."""
        violation = (torch.as_tensor(constraint_value, dtype=self.lam.dtype, device=self.lam.device)
                     - torch.as_tensor(budget, dtype=self.lam.dtype, device=self.lam.device))
        if torch.broadcast_shapes(violation.shape, self.lam.shape) != self.lam.shape:
            raise ValueError(
                f"constraint_value - budget has shape {tuple(violation.shape)}, which does not broadcast "
                f"to the multiplier shape {tuple(self.lam.shape)}; reduce over the batch first"
            )
        self.lam.add_(self.lr * violation).clamp_(min=0.0, max=self.upper)
        return self.lam.clone()


# --------------------------------------------------------------------------- KL divergences
# the exact KLs of the policy head's distributions live with it (agents.policy: categorical_kl, gaussian_kl)


def kl_estimate(
    logp_p_of_samples: torch.Tensor, logq_of_samples: torch.Tensor, estimator: str = "k3"
) -> torch.Tensor:
    """Per-sample estimate of KL(p || q) from samples x ~ p (shape (...) -> (...); take the mean).

    For priors without a closed-form KL (e.g. a non-Gaussian behaviour prior).
    With log r = log q(x) - log p(x):

        k3 (default, Schulman 2020): (r - 1) - log r   unbiased, every sample >= 0
        k2: (log r)^2 / 2                               biased, >= 0
        k1: -log r                                      unbiased, can be negative

    Gradients (samples held fixed, no score-function term): the expected
    gradient of k2 w.r.t. p's parameters is the true grad KL(p || q); that of
    k3 is grad KL(q || p) (the reverse KL); that of k1 is 0. Both of these only
    hold while the samples really come from the current p (first PPO epoch).

    Variance: k3 contains r, so its variance is finite only if E_p[r^2] < inf.
    For Gaussians that means s_q^2 < 2 s_p^2 in every dimension; a prior q much
    wider than the policy p makes k3 (and its gradient) heavy-tailed and, in
    practice, biased low over a finite batch. Prefer the exact ``gaussian_kl``
    / ``categorical_kl`` whenever the prior has a closed form.
    """
    log_r = logq_of_samples - logp_p_of_samples
    if estimator == "k3":
        return torch.expm1(log_r) - log_r
    if estimator == "k2":
        return 0.5 * log_r * log_r
    if estimator == "k1":
        return -log_r
    raise ValueError(f"unknown KL estimator {estimator!r}; expected 'k1', 'k2' or 'k3'")


# --------------------------------------------------------------------------- CCE-MAPPO actor


def cce_mappo_actor_loss(
    logp_new: torch.Tensor,
    logp_old: torch.Tensor,
    adv_reward: torch.Tensor,
    adv_cost: torch.Tensor,
    lagrange: torch.Tensor | float,
    entropy: torch.Tensor,
    kl_prior: torch.Tensor,
    kl_prev: torch.Tensor,
    *,
    clip_eps: float = 0.2,
    entropy_coef: float = 0.0,
    eta1: float = 0.0,
    eta2: float = math.inf,
    normalize_advantages: bool = True,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """CCE-MAPPO actor loss: Lagrangian PPO + entropy + magnetic mirror descent KL terms.

    ============  ======  ============================================================
    name          shape   meaning
    ============  ======  ============================================================
    logp_new      (...)   log pi_theta(a|s), with gradient
    logp_old      (...)   log pi_old(a|s) from the rollout
    adv_reward    (...)   reward advantage A_r
    adv_cost      (...)   cost advantage A_c (from the CVaR cost critic)
    lagrange      () / (...)  lambda >= 0, scalar or per agent; detached here
    entropy       (...)   policy entropy at s (with gradient)
    kl_prior      (...)   KL(pi_theta || pi_prior) per sample (magnet), with gradient
    kl_prev       (...)   KL(pi_theta || pi_prev) per sample (proximal), with gradient
    mask          (...)   optional validity mask; every mean below is masked
    ============  ======  ============================================================

        A    = A_r - lambda * A_c            (then standardised over the batch
                                              if normalize_advantages)
        loss = ppo_clip_loss(logp_new, logp_old, A, clip_eps)
               - entropy_coef * mean(entropy)
               + eta1 * mean(kl_prior)
               + (1 / eta2) * mean(kl_prev)

    ``eta2 = inf`` switches the proximal term off. The Lagrangian advantage is
    normalised as a whole (not A_r and A_c separately), so lambda keeps its
    meaning as an exchange rate between reward and cost units and the
    normalisation only rescales the step. Stats are detached scalar tensors.
    """
    if not eta2 > 0:
        raise ValueError(f"eta2 must be > 0 (use math.inf to disable the proximal term), got {eta2}")
    lam = torch.as_tensor(lagrange, dtype=adv_reward.dtype, device=adv_reward.device).detach()
    adv = adv_reward.detach() - lam * adv_cost.detach()
    if normalize_advantages:
        adv = normalize(adv, mask)
    pg_loss, ppo_stats = ppo_clip_loss(logp_new, logp_old, adv, clip_eps, mask)
    entropy_mean = masked_mean(entropy, mask)
    kl_prior_mean = masked_mean(kl_prior, mask)
    kl_prev_mean = masked_mean(kl_prev, mask)
    entropy_term = -entropy_coef * entropy_mean
    kl_prior_term = eta1 * kl_prior_mean
    kl_prev_term = (1.0 / eta2) * kl_prev_mean
    loss = pg_loss + entropy_term + kl_prior_term + kl_prev_term
    stats = {
        "loss": loss.detach(),
        "pg_loss": pg_loss.detach(),
        "entropy": entropy_mean.detach(),
        "entropy_term": entropy_term.detach(),
        "kl_prior": kl_prior_mean.detach(),
        "kl_prior_term": kl_prior_term.detach(),
        "kl_prev": kl_prev_mean.detach(),
        "kl_prev_term": kl_prev_term.detach(),
        "lagrange": masked_mean(lam.expand_as(adv), mask),
        **ppo_stats,
    }
    return loss, stats
