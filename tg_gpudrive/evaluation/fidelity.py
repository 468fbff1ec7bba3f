"""Fidelity: how close the generated episodes' kinematics are to the logged ones.

Four per-step features of the policy's agents, each histogrammed on a fixed
physical range with a fixed bin width (values outside the range are clipped
into the edge bins, so no sample is lost):

    feature    range            bin width   unit    samples
    speed      [0, 30]          0.5         m/s     steps the agent is present
    accel      [-8, 8]          0.25        m/s^2   steps present with the two before (path speed change / dt)
    nearest    [0, 50]          0.5         m       steps present; centre distance to the nearest agent
    curvature  [-0.3, 0.3]      0.005       1/m     as accel (path heading change / arc length)

Acceleration and curvature come from the positions by finite differences, for
logs and rollouts alike (evaluation/episodes.py, `path_kinematics`): they
measure the path driven, not the action that produced it, so log replay scores
near 0 and a discrete action grid shows only through the paths it drives.

Divergences between the logged histogram P and the generated one Q (both
normalised to probabilities):

    Hellinger  H(P, Q) = sqrt(1 - sum_i sqrt(p_i q_i))              in [0, 1]
    KL         KL(P || Q) with p, q -> (p + eps) / (1 + n eps), eps = KL_EPS = 1e-6, n bins
    W1         sum_i |F_P(i) - F_Q(i)| * width: Wasserstein-1 between the bin masses placed at
               the bin centres (equal to scipy.stats.wasserstein_distance on those masses), in the
               feature's unit

Realism (ours, *not* the official Waymo Sim Agents metric, only in its
style): per feature, the mean log-likelihood of the logged samples under the
generated histogram (probability mass per bin, add-eps smoothed with
REALISM_EPS = 1e-3 per bin before normalising), mapped to [0, 1] with exp(),
then a weighted mean over features with REALISM_WEIGHTS. The challenge fits
per-object histograms over 32 rollouts and uses many more features; here the
histograms are pooled over the scenario set.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tg_gpudrive.evaluation.episodes import Trajectories


@dataclasses.dataclass(frozen=True)
class Binning:
    lo: float
    hi: float
    width: float
    unit: str

    @property
    def edges(self) -> np.ndarray:
        n = int(round((self.hi - self.lo) / self.width))
        return self.lo + self.width * np.arange(n + 1)

    @property
    def centers(self) -> np.ndarray:
        e = self.edges
        return 0.5 * (e[1:] + e[:-1])

    @property
    def num_bins(self) -> int:
        return len(self.edges) - 1


FEATURES: dict[str, Binning] = {
    "speed": Binning(0.0, 30.0, 0.5, "m/s"),
    "accel": Binning(-8.0, 8.0, 0.25, "m/s^2"),
    "nearest": Binning(0.0, 50.0, 0.5, "m"),
    "curvature": Binning(-0.3, 0.3, 0.005, "1/m"),
}
KL_EPS = 1e-6
REALISM_EPS = 1e-3
REALISM_WEIGHTS = {"speed": 0.3, "accel": 0.2, "nearest": 0.3, "curvature": 0.2}


# ------------------------------------------------------------- primitives
def _bin_index(values: np.ndarray, binning: Binning) -> np.ndarray:
    v = np.clip(np.asarray(values, np.float64).ravel(), binning.lo, binning.hi)
    return np.clip(np.floor((v - binning.lo) / binning.width).astype(np.int64), 0, binning.num_bins - 1)


def histogram(values: np.ndarray, binning: Binning) -> np.ndarray:
    """Counts per bin (float64); values clipped into [lo, hi]."""
    return np.bincount(_bin_index(values, binning), minlength=binning.num_bins).astype(np.float64)


def _normalise(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, np.float64)
    s = p.sum()
    if s <= 0:
        raise ValueError("empty histogram")
    return p / s


def _hellinger(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hellinger distance of the probability vector p (B,) and q (..., B), one per leading index of q."""
    return np.sqrt(np.maximum(0.0, 1.0 - np.sqrt(p * q).sum(-1)))


def hellinger(p: np.ndarray, q: np.ndarray) -> float:
    return float(_hellinger(_normalise(p), _normalise(q)))


def kl_divergence(p: np.ndarray, q: np.ndarray, eps: float = KL_EPS) -> float:
    """KL(P || Q) in nats, both histograms smoothed by `eps` per bin (so empty bins of Q stay finite)."""
    p, q = _normalise(p), _normalise(q)
    n = len(p)
    p = (p + eps) / (1.0 + n * eps)
    q = (q + eps) / (1.0 + n * eps)
    return float((p * np.log(p / q)).sum())


def wasserstein1(p: np.ndarray, q: np.ndarray, width: float) -> float:
    """W1 between two histograms on the same equal-width bins (masses at the bin centres)."""
    p, q = _normalise(p), _normalise(q)
    return float(np.abs(np.cumsum(p - q))[:-1].sum() * width)


def log_likelihood(samples: np.ndarray, q: np.ndarray, binning: Binning, eps: float = REALISM_EPS) -> float:
    """Mean log probability (mass per bin) of `samples` under the histogram counts `q`, add-eps smoothed."""
    q = np.asarray(q, np.float64)
    q = (q / max(q.sum(), 1e-12) + eps)
    q = q / q.sum()
    c = histogram(samples, binning)
    return float((c * np.log(q)).sum() / max(c.sum(), 1.0))


# ---------------------------------------------------------------- features
def _feature_steps(tr: Trajectories, who: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per feature: its (E, A, K) values and the (E, A, K) mask of the steps that count for the agents `who`."""
    present = tr.valid & who[..., None]
    kin = tr.kin_valid & who[..., None]
    return {"speed": (tr.speed, present), "accel": (tr.accel, kin),
            "nearest": (tr.nearest, present & np.isfinite(tr.nearest)), "curvature": (tr.curvature, kin)}


def feature_samples(tr: Trajectories, agents: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """1-D samples per feature over the policy's agents (or the (E, A) mask `agents`)."""
    steps = _feature_steps(tr, tr.policy if agents is None else agents)
    return {name: v[m] for name, (v, m) in steps.items()}


def episode_histograms(tr: Trajectories, agents: np.ndarray) -> np.ndarray:
    """(U, D) counts: one row per agent-episode of the (E, A) mask `agents` (row-major order), the
    features' histograms side by side in FEATURES order (D = their bins together): what a bootstrap
    over agent-episodes resamples (`hellinger_of_sums`)."""
    n = int(agents.sum())
    width = sum(b.num_bins for b in FEATURES.values())
    unit = np.full(agents.shape, -1, np.int64)
    unit[agents] = np.arange(n)
    rows = np.zeros(n * width, np.float64)
    offset = 0
    for name, (v, m) in _feature_steps(tr, agents).items():
        b = FEATURES[name]
        u = np.broadcast_to(unit[..., None], m.shape)[m]
        rows += np.bincount(u * width + offset + _bin_index(v[m], b), minlength=n * width)
        offset += b.num_bins
    return rows.reshape(n, width)


def hellinger_of_sums(logged: dict[str, np.ndarray], sums: np.ndarray) -> np.ndarray:
    """Mean over the features of the Hellinger distance between the `logged` histograms and
    generated counts `sums` (..., D) laid out as `episode_histograms`' rows (NaN-free features only)."""
    out, k, offset = [], 0, 0
    for name, b in FEATURES.items():
        q = sums[..., offset:offset + b.num_bins]
        offset += b.num_bins
        if logged[name].sum() == 0:
            continue
        tot = q.sum(-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            h = _hellinger(_normalise(logged[name]), q / tot)
        out.append(np.where(tot[..., 0] > 0, h, np.nan))
    return np.nanmean(np.stack(out), axis=0)


def histograms(tr: Trajectories, agents: np.ndarray | None = None) -> dict[str, np.ndarray]:
    return {k: histogram(v, FEATURES[k]) for k, v in feature_samples(tr, agents).items()}


def compare(logged: Trajectories, generated: Trajectories) -> dict:
    """Per feature: hellinger, kl (logged || generated), w1, realism likelihood; plus the weighted realism.

    Both sides count the policy's agents of their own episodes (the same agents when `generated` was
    recorded in the simulator `logged` came from)."""
    ls, gs = feature_samples(logged), feature_samples(generated)
    out: dict = {"per_feature": {}}
    total, wsum = 0.0, 0.0
    for name, b in FEATURES.items():
        p, q = histogram(ls[name], b), histogram(gs[name], b)
        if p.sum() == 0 or q.sum() == 0:
            out["per_feature"][name] = {"hellinger": float("nan"), "kl": float("nan"), "w1": float("nan"),
                                        "likelihood": float("nan"), "n_logged": int(p.sum()),
                                        "n_generated": int(q.sum())}
            continue
        lik = float(np.exp(log_likelihood(ls[name], q, b)))
        out["per_feature"][name] = {
            "hellinger": hellinger(p, q), "kl": kl_divergence(p, q), "w1": wasserstein1(p, q, b.width),
            "likelihood": lik, "n_logged": int(p.sum()), "n_generated": int(q.sum()),
            "mean_logged": float(np.mean(ls[name])), "mean_generated": float(np.mean(gs[name])),
        }
        total += REALISM_WEIGHTS[name] * lik
        wsum += REALISM_WEIGHTS[name]
    out["realism_ours"] = total / wsum if wsum else float("nan")
    return out


def plot_histograms(logged: Trajectories, generated: dict[str, Trajectories], path) -> None:
    """One panel per feature: the logged histogram and each generated set's, as probabilities."""
    # matplotlib is the optional render extra: the metrics above work without it
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    ls = histograms(logged)
    gens = {k: histograms(v) for k, v in generated.items()}
    for i, (name, b) in enumerate(FEATURES.items()):
        ax = fig.add_subplot(1, 4, i + 1)
        c = b.centers
        if ls[name].sum():
            ax.fill_between(c, _normalise(ls[name]), step="mid", color="0.75", label="logged")
        for label, h in gens.items():
            if h[name].sum():
                ax.step(c, _normalise(h[name]), where="mid", lw=1.0, label=label)
        ax.set_title(f"{name} [{b.unit}]", fontsize=9)
        ax.tick_params(labelsize=7)
        if i == 0:
            ax.set_ylabel("probability per bin", fontsize=8)
    fig.axes[0].legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
