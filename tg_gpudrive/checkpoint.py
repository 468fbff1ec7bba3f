"""Checkpoint files shared by the CCE-MAPPO trainer, the world model and the CLIs.

`save_atomic` writes beside the target and renames, so a run killed mid-write
leaves the previous checkpoint whole; `load_checkpoint` accepts a file, a run
directory (its checkpoint.pt) or the name "shipped" (the policy packaged at
tg_gpudrive/policies/shipped.pt; "shipped_v4" to "shipped_v1" the ones shipped before it, kept for
comparison: SHIPPED_EARLIER) and
names the command-line option in its error.
`policy_engine_config` gives a policy checkpoint's engine config with slots for
every agent of the scenes it is evaluated or rendered on.
"""

from __future__ import annotations

import errno
import functools
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from tg_gpudrive.config import ConfigError, apply_overrides, from_dict, parse_override, to_dict
from tg_gpudrive.engine.model import agents_needed, sized_for

if TYPE_CHECKING:
    from tg_gpudrive.config import EngineConfig, TrainConfig

log = logging.getLogger(__name__)

SHIPPED = "shipped"  # the name that stands for the packaged policy
SHIPPED_POLICY = Path(__file__).resolve().parent / "policies" / "shipped.pt"
# earlier shipped policies by name: a run that fine-tuned from "shipped" before the policy changed names
# its start this way (its config.json), so a report's CCE-gap over training starts from the right policy
SHIPPED_EARLIER = {name: SHIPPED_POLICY.with_name(f"{name}.pt") for name in ("shipped_v1", "shipped_v2", "shipped_v3", "shipped_v4")}  # named as their files, like worldmodel.prior.PACKAGED


class CheckpointError(ValueError):
    """A checkpoint file that exists but cannot be read (truncated, corrupted, not a checkpoint)."""


def previous_path(path: Path) -> Path:
    """Where `save_atomic(..., keep_previous=True)` keeps the checkpoint it replaced."""
    return path.with_name(path.stem + ".prev" + path.suffix)


def save_atomic(obj, path: str | Path, keep_previous: bool = False) -> Path:
    """Write `obj` beside `path`, fsync it, rename it over `path` and fsync the directory, so a
    crash or power loss leaves either the old or the new file whole. `keep_previous`: the file
    replaced stays as `<stem>.prev<suffix>`, the fallback `load_checkpoint` uses when the newest is
    damaged."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
    except (OSError, RuntimeError) as e:  # a full disk, a quota: torch.save may wrap the OSError
        tmp.unlink(missing_ok=True)
        kept = f"; {path} is the last good one" if path.exists() else ""
        raise OSError(getattr(e, "errno", None) or errno.EIO,
                      f"could not save {path} ({getattr(e, 'strerror', None) or e}){kept}") from None
    if keep_previous and path.exists():
        os.replace(path, previous_path(path))
    os.replace(tmp, path)
    try:  # the renames themselves must reach the disk
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:  # some filesystems do not fsync directories
        pass
    return path


def checkpoint_path(path: str | Path, option: str = "--resume") -> Path:
    """`path` itself, `path/checkpoint.pt` for a run directory, SHIPPED_POLICY for the name "shipped" or an
    earlier packaged policy for its name in SHIPPED_EARLIER (a local file or directory of such a name:
    ./shipped); FileNotFoundError naming `option`."""
    packaged = {SHIPPED: SHIPPED_POLICY, **SHIPPED_EARLIER}.get(path) if isinstance(path, str) else None
    if packaged is not None:
        if not packaged.is_file():
            raise FileNotFoundError(f"{option} {path}: the packaged policy {packaged} is missing "
                                    "(this install ships none); give a checkpoint file or run directory")
        return packaged
    path = Path(path)
    path = path / "checkpoint.pt" if path.is_dir() else path
    if not path.exists():
        raise FileNotFoundError(f"{option}: no checkpoint at {path}")
    return path


def _read(path: Path, option: str, map_location) -> dict:
    try:
        ck = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for a damaged file
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{option}: {path} is damaged or not a checkpoint ({type(e).__name__}: {first})") \
            from None
    if not isinstance(ck, dict):
        raise CheckpointError(f"{option}: {path} is not a checkpoint (it holds a {type(ck).__name__})")
    return ck


POLICY, WORLD_MODEL = "policy", "world model"
KIND_USE = {POLICY: "--checkpoint, --policy, --resume or init_policy",
            WORLD_MODEL: "--background-model, prior_model or init_model"}


def checkpoint_kind(ck: dict) -> str | None:
    """What a checkpoint holds: its `kind` field, or (files written before it existed) what its keys show:
    a CCE-MAPPO policy (an actor and its training config) or a world model (its hyper-parameters, alone
    or inside a world-model training checkpoint); None for neither."""
    if ck.get("kind") in KIND_USE:
        return ck["kind"]
    if "actor" in ck and "config" in ck:
        return POLICY
    if "hparams" in ck or isinstance(ck.get("model"), dict) and "hparams" in ck["model"]:
        return WORLD_MODEL
    return None


def check_kind(ck: dict, want: str, path, option: str) -> dict:
    """`ck` itself when it holds a `want`; else a one-line CheckpointError naming both kinds and where the
    one it holds goes."""
    have = checkpoint_kind(ck)
    if have != want:
        what = f"a {have} checkpoint" if have else "not a tg_gpudrive checkpoint"
        where = f" (a {have} goes to {KIND_USE[have]})" if have else ""
        raise CheckpointError(f"{option}: {path} is {what}, expected a {want} checkpoint{where}")
    return ck


def usable_checkpoint(path: str | Path, option: str) -> Path:
    """The file to read for the checkpoint `path` names: checkpoint.pt itself, or, when it is damaged and
    the previous one kept beside it (checkpoint.prev.pt) reads, that one, with a warning naming both.
    How evaluate and render read a run, as `--resume` does."""
    path = checkpoint_path(path, option)
    try:
        _read(path, option, "cpu")
        return path
    except CheckpointError as e:
        prev = previous_path(path)
        if not prev.is_file():
            raise
        _read(prev, option, "cpu")
        log.warning("%s; using the previous checkpoint %s instead", e, prev)
        return prev


def load_checkpoint(path: str | Path, option: str = "--resume", map_location="cpu", fallback: bool = False,
                    kind: str = POLICY) -> dict:
    """The `kind` checkpoint at `path` (see checkpoint_path); CheckpointError naming the file if it is
    damaged or holds another kind. `fallback`: a damaged checkpoint.pt falls back, with a warning, to
    the previous one kept beside it (checkpoint.prev.pt), as `--resume` wants."""
    path = checkpoint_path(path, option)
    try:
        return check_kind(_read(path, option, map_location), kind, path, option)
    except CheckpointError as e:
        prev = previous_path(path)
        if not (fallback and prev.is_file()) or "expected a" in str(e):
            raise
        log.warning("%s; using the previous checkpoint %s instead", e, prev)
        return check_kind(_read(prev, option, map_location), kind, prev, option)


POLICY_DIR = "policies"  # a run's kept policies (TrainConfig.keep_policy_every), update_NNNNNN.pt


def kept_policies(run: str | Path) -> list[tuple[int, Path]]:
    """(update, file) of the policies a training run kept, oldest first (none: an empty list)."""
    d = Path(run) / POLICY_DIR
    out = []
    for f in sorted(d.glob("update_*.pt")) if d.is_dir() else []:
        try:
            out.append((int(f.stem.split("_", 1)[1]), f))
        except ValueError:  # not one of ours
            continue
    return out


def policy_engine_config(cfg: TrainConfig, scenes) -> EngineConfig:
    """The engine config of a policy trained with `cfg` (a TrainConfig), sized for `scenes`.

    max_agents = max(cfg.env.max_agents, the most agents any scene needs (engine.agents_needed)), so
    evaluating or rendering on denser scenes than the training ones drops no agent: the actor is per
    agent (heads = 1, the slot index unused) and works at any slot count. A checkpoint with per-slot
    heads (heads > 1) keeps its max_agents, with a warning that agents beyond it are dropped."""
    env = cfg.env
    if cfg.heads > 1:
        need = max((agents_needed(s) for s in scenes), default=0)
        if need > env.max_agents:
            log.warning("the policy has per-slot heads (heads=%d): keeping its max_agents=%d; agents beyond it "
                        "are dropped (scenes need up to %d slots)", cfg.heads, env.max_agents, need)
        return env
    return sized_for(env, scenes)


# what a trained network fixes: the shapes of its networks, its observation sizes and its action space
# (the meaning of its outputs). Every other key may change: when a policy is evaluated (collision mode,
# control, max_agents, radii, view), resumed or fine-tuned from (init_policy).
NETWORK_KEYS = ("hidden", "heads", "actor_history", "actor_history_partners", "quantiles", "env.dynamics", "env.action_space",
                "env.accel_bins", "env.curvature_bins", "env.max_accel", "env.max_curvature", "env.delta_max",
                "env.partner_k", "env.road_k")
FIXED_ENGINE_KEYS = tuple(k.removeprefix("env.") for k in NETWORK_KEYS if k.startswith("env."))
# ... of which the weights do not depend on these: partner and road rows go through one shared encoder
# and are max-pooled, so a fine-tune (init_policy) may observe more or fewer of them
POOLED_KEYS = ("env.partner_k", "env.road_k")
# ... and these a fine-tune may add to a policy trained without them (networks.grown_actor_state): per-slot
# heads to one shared head, a motion window (with partners) to none
GROWN_KEYS = ("heads", "actor_history", "actor_history_partners")


def grows(old: TrainConfig, key: str, was) -> bool:
    """Whether a run that changes network key `key` can start from a policy trained with `old` (`was` there) by
    growing it: per-slot heads from one head, a motion window from none."""
    if key == "heads":
        return was == 1
    return key in GROWN_KEYS and old.actor_history == 0


def network_differences(old: TrainConfig, new: TrainConfig) -> list[tuple[str, object, object]]:
    """(key, old value, new value) of every NETWORK_KEYS key where two training configs differ."""
    def get(cfg, key):  # "env.road_k" -> cfg.env.road_k
        return functools.reduce(getattr, key.split("."), cfg)

    return [(k, get(old, k), get(new, k)) for k in NETWORK_KEYS if get(old, k) != get(new, k)]


def _fixed_change(key: str, was, now, path, where: str) -> ConfigError:
    return ConfigError(f"--set {key}={now}: fixed by the network trained in {path} ({key}={was} there); "
                       f"{where}")


def evaluation_engine(env: EngineConfig, overrides: list[str], path) -> EngineConfig:
    """`env` (a checkpoint's engine, sized for the scenes) with the --set overrides of an evaluation:
    an unknown key is an error, as without a checkpoint, and so is a change of a key the network fixes
    (FIXED_ENGINE_KEYS); every other key is applied."""
    if not overrides:
        return env
    current = to_dict(env)
    for text in overrides:  # a fixed key first, before it can fail in combination with others
        path_, value = parse_override(text)
        key, was = path_[0], current.get(path_[0])
        if len(path_) == 1 and key in FIXED_ENGINE_KEYS and not (
                list(was) == list(value) if isinstance(value, (list, tuple)) else was == value):
            raise _fixed_change(key, was, value, path, "train a new policy to change it")
    new = from_dict(type(env), apply_overrides(current, overrides), "--set")
    for key in FIXED_ENGINE_KEYS:
        if getattr(new, key) != getattr(env, key):
            raise _fixed_change(key, getattr(env, key), getattr(new, key), path,
                                "train a new policy to change it")
    return new


def check_resume_config(old: TrainConfig, new: TrainConfig, path) -> None:
    """A --resume's config (the run's, with new --set overrides) keeps what the saved networks fix."""
    for key, was, now in network_differences(old, new):
        raise _fixed_change(key, was, now, path, "a new run (without --resume) can change it")

