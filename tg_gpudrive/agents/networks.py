"""Networks of CCE-MAPPO: a decentralised actor, a centralised reward critic and a
distributional (quantile) cost critic
(two heads of one centralised trunk).

All three read the engine's observation rows (kernels/observation.py layout):
the ego block, `partner_k` partner rows and `road_k` road rows, each row led by
a 0/1 mask. `ObsEncoder` embeds partner and road rows with shared MLPs and
max-pools them over their masks (permutation invariant, cheap), then fuses
with the ego features. Inputs are scaled by fixed constants (metres / 50,
speeds / 20), so no running statistics have to be synchronised.

The actor sees its own row and, with `history` > 0, its own last `history` states
(tg_gpudrive.history: positions, headings, speeds and actions in its current frame), the
paper's pi(a | o, h). The critics see every controlled agent of
the world: each agent's embedding attends over the embeddings of the others
(masked multi-head attention), which is the centralised part.
"""

from __future__ import annotations

import torch
from torch import nn

from tg_gpudrive.history import hist_dim, hist_scale
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM

# per-feature scales of the observation blocks (see kernels/observation.py)
_EGO_SCALE = [20.0, 5.0, 2.0, 50.0, 50.0, 1.0, 1.0, 5.0, 5.0, 8.0]
_PARTNER_SCALE = [1.0, 50.0, 50.0, 1.0, 1.0, 20.0, 20.0, 5.0, 2.0, 4.0]
_ROAD_SCALE = [1.0, 50.0, 50.0, 1.0, 1.0, 5.0, 7.0]
INIT_STD_FRACTION = 0.2  # continuous head: initial exploration std per action dimension / its range


def mlp(sizes: list[int], last_act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_act:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class ObsEncoder(nn.Module):
    """(..., obs_dim) -> (..., hidden)."""

    def __init__(self, partner_k: int, road_k: int, hidden: int = 128, embed: int = 64):
        super().__init__()
        self.partner_k, self.road_k = partner_k, road_k
        self.register_buffer("ego_scale", torch.tensor(_EGO_SCALE))
        self.register_buffer("partner_scale", torch.tensor(_PARTNER_SCALE))
        self.register_buffer("road_scale", torch.tensor(_ROAD_SCALE))
        self.ego = mlp([EGO_DIM, embed])
        self.partner = mlp([PARTNER_DIM, embed, embed])
        self.road = mlp([ROAD_DIM, embed, embed])
        self.fuse = mlp([3 * embed, hidden, hidden])

    @staticmethod
    def _pool(feat: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Masked max-pool over the entries (dim -2) of features that are >= 0 (the encoders end in a
        ReLU): absent entries become 0, so they never beat a present one and a row with no entries
        pools to zeros. `max` rather than `amax`: its backward scatters to one index instead of
        comparing the whole tensor against the result, the update's costliest backward op."""
        return (feat * mask[..., None]).max(dim=-2).values

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        lead = obs.shape[:-1]
        k, kr = self.partner_k, self.road_k
        ego = obs[..., :EGO_DIM] / self.ego_scale
        part = obs[..., EGO_DIM:EGO_DIM + k * PARTNER_DIM].reshape(*lead, k, PARTNER_DIM)
        road = obs[..., EGO_DIM + k * PARTNER_DIM:].reshape(*lead, kr, ROAD_DIM)
        p = self._pool(self.partner(part / self.partner_scale), part[..., 0] > 0.5)
        r = self._pool(self.road(road / self.road_scale), road[..., 0] > 0.5)
        return self.fuse(torch.cat([self.ego(ego), p, r], dim=-1))


class Actor(nn.Module):
    """Policy over the engine's action space.

    discrete: `forward` returns logits (..., num_actions);
    continuous: returns (mean, log_std), each (..., act_dim), actions in the engine's units.
    `heads > 1` gives per-slot heads (slot index modulo heads), for few-agent studies.
    `history > 0`: `forward` also takes `hist` (..., history, hist_dim(history_partners)), the motion
    window of the agent and of its `history_partners` nearest partners
    (tg_gpudrive.history.HistoryBuffer.features), embedded and added to the observation's encoding."""

    def __init__(self, partner_k: int, road_k: int, *, discrete: bool, num_actions: int = 91,
                 act_dim: int = 2, act_scale: list[float] | None = None, hidden: int = 128, heads: int = 1,
                 history: int = 0, history_partners: int = 0):
        super().__init__()
        self.discrete, self.heads, self.history = discrete, heads, history
        self.history_partners = history_partners
        self.encoder = ObsEncoder(partner_k, road_k, hidden, embed=max(hidden // 2, 16))
        if history:
            self.register_buffer("hist_scale", torch.tensor(hist_scale(history_partners)))
            self.hist_encoder = mlp([history * hist_dim(history_partners), hidden, hidden])
        out = num_actions if discrete else act_dim
        self.head_w = nn.Parameter(torch.randn(heads, hidden, out) * (0.01 / hidden**0.5))
        self.head_b = nn.Parameter(torch.zeros(heads, out))
        if not discrete:
            scale = torch.tensor(act_scale or [1.0] * act_dim)
            # exploration starts at a fifth of each dimension's range (1.2 m/s^2, 0.06 1/m by default):
            # one std of 0.61 for both, as before, spanned twice the curvature box, so most early
            # curvature draws were clipped to a full turn
            self.log_std = nn.Parameter(torch.log(INIT_STD_FRACTION * scale))
            self.register_buffer("act_scale", scale)

    def forward(self, obs: torch.Tensor, slot: torch.Tensor | None = None, hist: torch.Tensor | None = None):
        h = self.encoder(obs)
        if self.history:
            dim = hist_dim(self.history_partners)
            if hist is None or hist.shape[-2:] != (self.history, dim):
                raise ValueError(f"this actor sees a motion history: pass hist of shape (..., {self.history}, "
                                 f"{dim}) (tg_gpudrive.history.HistoryBuffer), got "
                                 f"{None if hist is None else tuple(hist.shape)}")
            h = h + self.hist_encoder((hist / self.hist_scale).flatten(-2).to(h.dtype))
        if self.heads == 1:
            out = h @ self.head_w[0] + self.head_b[0]
        else:
            idx = (slot % self.heads).expand(h.shape[:-1])
            out = torch.einsum("...h,...ho->...o", h, self.head_w[idx]) + self.head_b[idx]
        if self.discrete:
            return out
        return torch.tanh(out) * self.act_scale, self.log_std.expand_as(out)


# the grown motion window's encoder starts with its last layer at this fraction of a fresh one's weights: the grown
# actor acts almost as the policy it grew from, and the window still gets gradients through its active units
GROWN_HISTORY_SCALE = 0.01


def grown_actor_state(state: dict, actor: Actor) -> dict:
    """`state` (the state_dict of an actor with one shared head and no motion window, e.g. the shipped policy's)
    laid out for `actor`, which may add per-slot heads and a motion window: each head a copy of the shared
    one, and the window's encoder `actor`'s own fresh weights with the last layer's scaled by
    GROWN_HISTORY_SCALE and no bias, so a fine-tune starts from the policy `state` holds. Anything else of
    `state` is taken as it is (a layout `actor` cannot take is load_state_dict's error)."""
    own, out = actor.state_dict(), dict(state)
    if state["head_w"].shape[0] == 1 and own["head_w"].shape[0] > 1:
        for k in ("head_w", "head_b"):
            out[k] = state[k].expand_as(own[k]).clone()
    if actor.history and not any(k.startswith("hist_encoder.") for k in state):
        out.update({k: v.clone() for k, v in own.items() if k.startswith("hist_encoder.") or k == "hist_scale"})
        last = max(i for i, m in enumerate(actor.hist_encoder) if isinstance(m, nn.Linear))
        out[f"hist_encoder.{last}.weight"] = out[f"hist_encoder.{last}.weight"] * GROWN_HISTORY_SCALE
        out[f"hist_encoder.{last}.bias"] = torch.zeros_like(out[f"hist_encoder.{last}.bias"])
    return out


class CentralCritic(nn.Module):
    """Centralised critic with two heads on one trunk: reward value and cost quantiles.

    (W, C, obs_dim) + mask (W, C) -> value (W, C) and cost quantiles (W, C, N). Each
    agent's embedding attends over the embeddings of the world's controlled agents."""

    def __init__(self, partner_k: int, road_k: int, quantiles: int = 64, hidden: int = 128, heads: int = 4):
        super().__init__()
        self.encoder = ObsEncoder(partner_k, road_k, hidden, embed=max(hidden // 2, 16))
        self.attn = nn.MultiheadAttention(hidden, heads, batch_first=True)
        self.value_head = mlp([2 * hidden, hidden, 1], last_act=False)
        self.cost_head = mlp([2 * hidden, hidden, quantiles], last_act=False)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor, rows: torch.Tensor | None = None,
                head_rows: torch.Tensor | None = None,
                row_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`rows`: the flat indices of mask's True entries, when the caller has them already
        (finding them costs a host-device synchronisation). `head_rows`: flat slot indices at which
        to evaluate the heads alone (value (R,), quantiles (R, N)), as a learner that reads only
        the live slots needs: the padded slots' heads are then never computed. `row_weight` (R,): rows
        of a fixed count, the live ones weighted 1 and fillers 0 (they may repeat an index and read
        anything): the fillers are encoded as zero observations and add nothing."""
        lead = obs.shape[:-2]
        C = obs.shape[-2]
        m = mask.reshape(-1, C)
        # encode only the agents that are there; padded slots stay zero and are masked as keys
        flat = obs.reshape(-1, obs.shape[-1])
        if rows is None:
            rows = m.reshape(-1).nonzero(as_tuple=True)[0]
        x = flat[rows]
        if row_weight is not None:
            x = torch.where(row_weight[:, None] > 0, x, 0)
        enc = self.encoder(x)
        h = enc.new_zeros(flat.shape[0], self.attn.embed_dim)
        if row_weight is None:
            h = h.index_copy(0, rows, enc)
        else:  # a sum, so that fillers repeating a live row's index add their zero to it
            h = h.index_add(0, rows, enc * row_weight[:, None].to(enc.dtype))
        h = h.reshape(-1, C, self.attn.embed_dim)
        # a world with no valid agent still needs one key to attend to
        key_pad = ~m & m.any(dim=1, keepdim=True)
        pooled, _ = self.attn(h, h, h, key_padding_mask=key_pad, need_weights=False)
        z = torch.cat([h, pooled], dim=-1)
        if head_rows is not None:
            z = z.reshape(-1, z.shape[-1])[head_rows]
            # sorted quantiles: a monotone quantile function, so CVaR reads the right tail
            return self.value_head(z).squeeze(-1), torch.sort(self.cost_head(z), dim=-1).values
        value = self.value_head(z).reshape(*lead, C)
        quant = torch.sort(self.cost_head(z), dim=-1).values.reshape(*lead, C, -1)
        return value, quant
