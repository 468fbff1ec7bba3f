"""Checkpoint files shared by the CCE-MAPPO trainer, the world model and the CLIs.

`save_atomic` writes beside the target and renames, so a run killed mid-write
leaves the previous checkpoint whole; `load_checkpoint` accepts a file or a run
directory (its checkpoint.pt) and names the command-line option in its error.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch


def save_atomic(obj, path: str | Path) -> Path:
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)
    return path


def checkpoint_path(path: str | Path, option: str = "--resume") -> Path:
    """`path` itself, or `path/checkpoint.pt` for a run directory; FileNotFoundError naming `option`."""
    path = Path(path)
    path = path / "checkpoint.pt" if path.is_dir() else path
    if not path.exists():
        raise FileNotFoundError(f"{option}: no checkpoint at {path}")
    return path


def load_checkpoint(path: str | Path, option: str = "--resume", map_location="cpu") -> dict:
    return torch.load(checkpoint_path(path, option), map_location=map_location, weights_only=False)
