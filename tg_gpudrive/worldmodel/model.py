"""The world model: an autoregressive next-action model over the engine's tensors.

In the spirit of TrafficGamer's generative world model (a QCNet-style decoder),
every agent at every step gets a distribution over its next action from

    ego token        the ego block of its observation row
    temporal  CA     cross-attention over its own last `history` states
                     (position, heading, speed and applied action, in its current frame)
    map       CA     cross-attention over the road rows of its observation
    neighbour CA     cross-attention over the partner rows of its observation
    self-attention   one transformer layer over the four tokens, then an MLP

and returns, for `action_space="discrete"`, logits over the engine's (accel,
curvature) grid, or for `"continuous"` a `LaplaceMixture` (mixture.py) of
`mixtures` factorised Laplace components over the 2-D (accel, curvature)
action in engine units. The discrete head's weights are laid out as before
the continuous head existed, so older checkpoints load unchanged. The
observation already holds map and neighbours in the agent's frame, so the only
extra input is the history window, kept by `tg_gpudrive.history.HistoryBuffer`
(W, A, H, F) and updated lazily from the simulator (`sync`). Bicycle dynamics only: a
delta-local config is refused with a clear error.

Observation rows are nearest-first, so the model reads at most `max_partners`
partner rows and `max_roads` road rows: one set of weights works with any
`partner_k` / `road_k` of the engine config.

History features: tg_gpudrive/history.py (HIST_FEATURES).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from tg_gpudrive.history import HIST_DIM, HIST_SCALE
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.enums import ActionSpace, Dynamics
from tg_gpudrive.worldmodel.mixture import LaplaceMixture


_EGO_SCALE = [20.0, 5.0, 2.0, 50.0, 50.0, 1.0, 1.0, 5.0, 5.0, 8.0]
_PARTNER_SCALE = [1.0, 50.0, 50.0, 1.0, 1.0, 20.0, 20.0, 5.0, 2.0, 4.0]
_ROAD_SCALE = [1.0, 50.0, 50.0, 1.0, 1.0, 5.0, 7.0]


# continuous head: log Laplace scale, in units of the action box half-width, squashed into this range.
# The floor (b >= 1.8 % of the box: 0.11 m/s^2, 0.0055 1/m by default, still 10x finer than a grid bin)
# bounds the NLL's 1 / b gradients, which with a lower floor swamp the trunk and stall learning.
_LOG_SCALE_MIN, _LOG_SCALE_MAX = -4.0, 1.0


def require_bicycle(cfg) -> None:
    if cfg.dynamics != Dynamics.BICYCLE:
        raise NotImplementedError(
            "the world model predicts bicycle actions (accel, curvature) only; got dynamics="
            f"{cfg.dynamics} (action_space={cfg.action_space})")


def check_action_space(model: "WorldModel", cfg) -> None:
    """The model's head must match the simulator's action space (and its bicycle dynamics)."""
    require_bicycle(cfg)
    if model.action_space != cfg.action_space:
        raise ValueError(
            f"the world model predicts {model.action_space} actions but the simulator's action_space is "
            f"{cfg.action_space}; train a model for it (train-world-model --set env.action_space="
            f"{cfg.action_space})")


def _mlp(i: int, d: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(i, d), nn.ReLU(), nn.Linear(d, d))


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, pad: torch.Tensor | None, heads: int) -> torch.Tensor:
    """Scaled dot-product attention of a few queries over a few keys, written out: q (N, Q, d),
    k and v (N, L, d), pad (N, L) True where a key is absent -> (N, Q, d). With one to four queries
    per row, the fused attention kernels, which tile queries in blocks of 64 or more, spend most of
    their work on padding; these are a handful of elementwise passes over the keys instead."""
    n, nq, d = q.shape
    hd = d // heads
    q = q.reshape(n, nq, 1, heads, hd) * hd**-0.5
    s = (q * k.reshape(n, 1, -1, heads, hd)).sum(-1)  # (N, Q, L, heads)
    if pad is not None:
        s = s.masked_fill(pad[:, None, :, None], float("-inf"))
    p = torch.softmax(s.to(torch.promote_types(s.dtype, torch.float32)), dim=2).to(v.dtype)
    return (p[..., None] * v.reshape(n, 1, -1, heads, hd)).sum(2).reshape(n, nq, d)


def _mha(attn: nn.MultiheadAttention, q: torch.Tensor, kv: torch.Tensor, pad: torch.Tensor | None) -> torch.Tensor:
    """nn.MultiheadAttention's forward (no dropout, no weights returned) through `_attend`, on its
    own parameters: q (N, Q, d), kv (N, L, d), pad (N, L) or None."""
    d = attn.embed_dim
    w, b = attn.in_proj_weight, attn.in_proj_bias
    if q is kv:
        q, k, v = nn.functional.linear(q, w, b).split(d, dim=-1)
    else:
        q = nn.functional.linear(q, w[:d], b[:d])
        k, v = nn.functional.linear(kv, w[d:], b[d:]).split(d, dim=-1)
    return attn.out_proj(_attend(q, k, v, pad, attn.num_heads))


class _CrossAttention(nn.Module):
    """Query token attends over a masked key set; a learned null key keeps empty sets defined."""

    def __init__(self, d: int, heads: int):
        super().__init__()
        self.null = nn.Parameter(torch.zeros(1, 1, d))
        self.attn = nn.MultiheadAttention(d, heads, batch_first=True)  # holds the weights; see _mha
        self.norm = nn.LayerNorm(d)

    def forward(self, q: torch.Tensor, keys: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        n = keys.shape[0]
        keys = torch.cat([self.null.expand(n, 1, -1).to(keys.dtype), keys], dim=1)
        pad = torch.cat([mask.new_zeros(n, 1), ~mask], dim=1)
        return self.norm(_mha(self.attn, q[:, None], keys, pad)[:, 0])


def _encoder_layer(layer: nn.TransformerEncoderLayer, x: torch.Tensor) -> torch.Tensor:
    """A post-norm nn.TransformerEncoderLayer (ReLU, no dropout, no mask) over a few tokens, its
    attention through `_attend`."""
    x = layer.norm1(x + _mha(layer.self_attn, x, x, None))
    return layer.norm2(x + layer.linear2(torch.relu(layer.linear1(x))))


class WorldModel(nn.Module):
    """(obs rows (N, obs_dim), history (N, H, HIST_DIM)) -> logits (N, num_actions) (discrete)
    or a LaplaceMixture over (N, 2) actions (continuous).

    `partner_k`, `road_k`: the engine layout of the observation rows (set with `set_layout`).
    `max_accel`, `max_curvature` (continuous): the action box; locations and scales are
    predicted in units of its half-widths."""

    def __init__(self, *, num_actions: int = 91, hidden: int = 64, heads: int = 4, history: int = 10,
                 max_partners: int = 8, max_roads: int = 32, partner_k: int = 8, road_k: int = 32,
                 action_space: ActionSpace | str = ActionSpace.DISCRETE, mixtures: int = 4, max_accel: float = 6.0,
                 max_curvature: float = 0.3):
        super().__init__()
        action_space = ActionSpace.parse(action_space, "action_space")
        self.hparams = dict(num_actions=num_actions, hidden=hidden, heads=heads, history=history,
                            max_partners=max_partners, max_roads=max_roads)
        self.action_space, self.mixtures = action_space, mixtures
        if action_space == ActionSpace.CONTINUOUS:  # discrete checkpoints keep their old hparams
            if mixtures < 1:
                raise ValueError(f"mixtures must be >= 1, got {mixtures}")
            self.hparams.update(action_space=str(action_space), mixtures=mixtures, max_accel=max_accel,
                                max_curvature=max_curvature)
        self.register_buffer("action_scale", torch.tensor([max_accel, max_curvature]), persistent=False)
        self.num_actions, self.history = num_actions, history
        self.max_partners, self.max_roads = max_partners, max_roads
        self.set_layout(partner_k, road_k)
        d = hidden
        self.register_buffer("ego_scale", torch.tensor(_EGO_SCALE))
        self.register_buffer("partner_scale", torch.tensor(_PARTNER_SCALE))
        self.register_buffer("road_scale", torch.tensor(_ROAD_SCALE))
        self.register_buffer("hist_scale", torch.tensor(HIST_SCALE))
        self.ego = _mlp(EGO_DIM, d)
        self.temporal_in = _mlp(HIST_DIM + 1, d)  # + cos/sin dyaw replace dyaw, see _hist_tokens
        self.time_emb = nn.Parameter(torch.randn(history, d) * 0.02)
        self.road_in = _mlp(ROAD_DIM, d)
        self.partner_in = _mlp(PARTNER_DIM, d)
        self.ca_time = _CrossAttention(d, heads)
        self.ca_map = _CrossAttention(d, heads)
        self.ca_agent = _CrossAttention(d, heads)
        # holds the weights of the layer over the four tokens; run by _encoder_layer
        self.self_attn = nn.TransformerEncoderLayer(d, heads, dim_feedforward=2 * d, dropout=0.0, batch_first=True)
        out = num_actions if action_space == ActionSpace.DISCRETE else mixtures * 5  # logit, 2 locations, 2 log-scales
        self.head = nn.Sequential(nn.Linear(4 * d, 2 * d), nn.ReLU(), nn.Linear(2 * d, out))

    @property
    def discrete(self) -> bool:
        return self.action_space == ActionSpace.DISCRETE

    @property
    def grad_scale(self) -> float:
        """Typical gradient size of the NLL relative to the discrete head's (gradient clipping)."""
        return 1.0 if self.discrete else math.exp(-_LOG_SCALE_MIN)

    def set_layout(self, partner_k: int, road_k: int) -> None:
        self.partner_k, self.road_k = int(partner_k), int(road_k)

    def _hist_tokens(self, hist: torch.Tensor) -> torch.Tensor:
        h = hist / self.hist_scale
        dyaw = hist[..., 2:3]
        feats = torch.cat([h[..., :2], torch.cos(dyaw), torch.sin(dyaw), h[..., 3:]], dim=-1)
        return self.temporal_in(feats) + self.time_emb[-hist.shape[-2]:]

    def forward(self, obs: torch.Tensor, hist: torch.Tensor) -> torch.Tensor | LaplaceMixture:
        lead = obs.shape[:-1]
        obs = obs.reshape(-1, obs.shape[-1])
        hist = hist.reshape(-1, *hist.shape[-2:])
        k, kr = self.partner_k, self.road_k
        kp, krr = min(k, self.max_partners), min(kr, self.max_roads)
        ego = obs[:, :EGO_DIM] / self.ego_scale
        part = obs[:, EGO_DIM:EGO_DIM + k * PARTNER_DIM].reshape(-1, k, PARTNER_DIM)[:, :kp]
        road = obs[:, EGO_DIM + k * PARTNER_DIM:].reshape(-1, kr, ROAD_DIM)[:, :krr]
        q = self.ego(ego)
        t = self.ca_time(q, self._hist_tokens(hist), hist[..., -1] > 0.5)
        m = self.ca_map(q + t, self.road_in(road / self.road_scale), road[..., 0] > 0.5)
        n = self.ca_agent(q + t + m, self.partner_in(part / self.partner_scale), part[..., 0] > 0.5)
        z = _encoder_layer(self.self_attn, torch.stack([q, t, m, n], dim=1))
        raw = self.head(z.reshape(z.shape[0], -1))
        if self.discrete:
            return raw.reshape(*lead, self.num_actions)
        K = self.mixtures
        rest = raw[:, K:].reshape(-1, K, 4)
        scale = self.action_scale.to(raw.dtype)
        loc = rest[..., :2] * scale
        span = _LOG_SCALE_MAX - _LOG_SCALE_MIN
        log_scale = torch.log(scale) + _LOG_SCALE_MIN + span * torch.sigmoid(rest[..., 2:])
        return LaplaceMixture(raw[:, :K].reshape(*lead, K), loc.reshape(*lead, K, 2), log_scale.reshape(*lead, K, 2))

    def nll(self, out, target: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
        """Per-sample negative log-likelihood (nats; per 2-D action when continuous) of `target`:
        grid indices (N,) or actions (N, 2) in engine units."""
        if self.discrete:
            return nn.functional.cross_entropy(out, target, reduction="none", label_smoothing=label_smoothing)
        return -out.log_prob(target)
