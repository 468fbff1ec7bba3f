"""The continuous head's distribution: a mixture of factorised Laplace densities over (accel, curvature).

    mix = LaplaceMixture(logits, loc, log_scale)
    mix.log_prob(x)            # (...,) log-density of actions x (..., D)
    mix.sample(gen)            # (..., D)
    mix.sample(gen, temperature=0.1)   # sharper: logits / T, Laplace scales * T (0: mode_loc)
    mix.kl_from((mean, log_std))   # upper bound on KL(N(mean, std) || mix), differentiable in mean and log_std

Fields (K components, D = 2 action dimensions, engine units m/s^2 and 1/m):

    field      shape        meaning
    logits     (..., K)     mixture weights, unnormalised
    loc        (..., K, D)  component locations
    log_scale  (..., K, D)  log of the Laplace scales b (std = sqrt(2) b)

The CCE-MAPPO magnet needs KL(pi || prior) for a diagonal-Gaussian policy pi,
which has no closed form against a Laplace mixture. `kl_from` uses the
variational upper bound of Hershey & Olsen (2007): by Jensen,
E_pi[log sum_k w_k L_k] >= log sum_k w_k exp(E_pi[log L_k]), so

    KL(pi || prior) <= -H(pi) - logsumexp_k(log w_k + E_pi[log L_k])

where E_pi[log L_k] is closed form per dimension (-log 2b - E|x - mu| / b, with
E|x - mu| the folded-normal mean). It is exact for one component, nearly so
while pi sits under one component, and above the true KL when pi straddles
several (which only pushes the policy towards one mode, as the reverse KL
does anyway); it is deterministic, cheap (no samples) and differentiable in
the policy's mean and log_std. It was preferred to a fixed-sample Monte Carlo
estimate, which with few draws is far off when the policy is wider than the
prior's components (BENCHMARKS.md, "World model"); `kl_from(g, samples=S)` still gives that
estimate (antithetic standard-normal draws, seed 0, the same every call;
x = mean + std * eps) for checks.

As a tuple a LaplaceMixture is (mean, log_std) of the moment-matched diagonal
Gaussian, so code that only knows Gaussian priors (`gaussian_kl(p, q[0], q[1])`)
still gets a well-defined, if unimodal, magnet. It must not hold gradients of
the world model: the magnet is a fixed target.
"""

from __future__ import annotations

import math

import torch

_LOG2 = math.log(2.0)
_HALF_LOG_2PI_E = 0.5 * math.log(2.0 * math.pi * math.e)
_SQRT2 = math.sqrt(2.0)
_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)
_EPS_CACHE: dict = {}


def fixed_normals(samples: int, dim: int, device, dtype=torch.float32) -> torch.Tensor:
    """(samples, dim) standard-normal draws, antithetic (rows i and i + samples/2 are negatives), seed 0."""
    key = (samples, dim, str(device), dtype)
    eps = _EPS_CACHE.get(key)
    if eps is None:
        half = torch.randn((samples + 1) // 2, dim, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        eps = torch.cat([half, -half])[:samples].to(device=device, dtype=dtype)
        _EPS_CACHE[key] = eps
    return eps


class LaplaceMixture(tuple):
    """K factorised Laplace components over D-dim actions; as a tuple, the moment-matched (mean, log_std)."""

    kl_samples: int | None = None  # None: the closed-form bound in kl_from

    def __new__(cls, logits: torch.Tensor, loc: torch.Tensor, log_scale: torch.Tensor, kl_samples: int | None = None):
        w = torch.softmax(logits, -1)[..., None]
        mean = (w * loc).sum(-2)
        second = (w * (2.0 * torch.exp(2.0 * log_scale) + loc * loc)).sum(-2)
        log_std = 0.5 * torch.log((second - mean * mean).clamp(min=1e-12))
        self = super().__new__(cls, (mean, log_std))
        self.logits, self.loc, self.log_scale = logits, loc, log_scale
        if kl_samples is not None:
            self.kl_samples = int(kl_samples)
        return self

    @property
    def num_components(self) -> int:
        return self.logits.shape[-1]

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        """log-density (...) of x (..., D); x may carry extra leading dims that broadcast."""
        d = (x[..., None, :] - self.loc).abs() * torch.exp(-self.log_scale)
        comp = -(d + self.log_scale + _LOG2).sum(-1)
        return torch.logsumexp(torch.log_softmax(self.logits, -1) + comp, -1)

    def mode_loc(self) -> torch.Tensor:
        """(..., D) location of the most probable component (a cheap point prediction)."""
        k = self.logits.argmax(-1)
        return torch.gather(self.loc, -2, k[..., None, None].expand(*k.shape, 1, self.loc.shape[-1]))[..., 0, :]

    def top_component(self) -> "LaplaceMixture":
        """The most probable component alone, as a one-component mixture (its KL bound is exact):
        the magnet TrafficGamer pulls the policy towards."""
        k = self.logits.argmax(-1)[..., None, None]
        pick = lambda x: torch.gather(x, -2, k.expand(*k.shape[:-2], 1, x.shape[-1]))  # noqa: E731
        return LaplaceMixture(torch.zeros_like(self.logits[..., :1]), pick(self.loc), pick(self.log_scale),
                              self.kl_samples)

    def sample(self, generator: torch.Generator | None = None, temperature: float = 1.0) -> torch.Tensor:
        """(..., D) draws at `temperature` T: each component is tempered, w_k^(1/T) L_k(x)^(1/T) up to
        normalisation, which for a Laplace is the same Laplace with its scale b times T; so T divides
        the logits and multiplies the scales, T = 1 is the model, T < 1 sharpens both the choice of
        component and the spread around it, and T = 0 is `mode_loc()` (no randomness)."""
        if temperature < 0:
            raise ValueError(f"temperature must be >= 0, got {temperature}")
        if temperature == 0:
            return self.mode_loc()
        lead, K, D = self.logits.shape[:-1], self.logits.shape[-1], self.loc.shape[-1]
        p = torch.softmax(self.logits.reshape(-1, K) / temperature, -1)
        k = torch.multinomial(p, 1, generator=generator).view(*lead, 1, 1).expand(*lead, 1, D)
        loc = torch.gather(self.loc, -2, k)[..., 0, :]
        b = torch.gather(self.log_scale, -2, k)[..., 0, :].exp() * temperature
        u = torch.rand(loc.shape, generator=generator, device=loc.device, dtype=loc.dtype) - 0.5
        # inverse CDF of the Laplace; |u| < 0.5 keeps the log finite
        return loc - b * torch.sign(u) * torch.log1p(-2.0 * u.abs().clamp(max=0.5 - 1e-7))

    def kl_from(self, gaussian, samples: int | None = None) -> torch.Tensor:
        """KL(N(mean, exp(log_std)) || self), summed over D: (...). `samples` None: the variational
        upper bound; an int: the fixed-draw Monte Carlo estimate. See the module docstring."""
        mean, log_std = gaussian
        samples = samples or self.kl_samples
        entropy = (_HALF_LOG_2PI_E + log_std).sum(-1)
        if samples:
            eps = fixed_normals(samples, mean.shape[-1], mean.device, mean.dtype)
            x = mean + torch.exp(log_std) * eps.view(eps.shape[0], *([1] * (mean.dim() - 1)), eps.shape[1])
            return -self.log_prob(x).mean(0) - entropy
        s = torch.exp(log_std)[..., None, :]
        delta = mean[..., None, :] - self.loc
        fold = s * _SQRT_2_OVER_PI * torch.exp(-0.5 * (delta / s) ** 2) + delta * torch.erf(delta / (s * _SQRT2))
        expected = -(self.log_scale + _LOG2 + fold * torch.exp(-self.log_scale)).sum(-1)  # E_pi[log L_k]: (..., K)
        return -torch.logsumexp(torch.log_softmax(self.logits, -1) + expected, -1) - entropy
