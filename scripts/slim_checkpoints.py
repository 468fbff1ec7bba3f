"""Shrink the policy checkpoints of finished training runs to what evaluation and reports read.

    python scripts/slim_checkpoints.py /tmp/res/quality [more roots ...]

A trainer's checkpoint.pt holds everything `--resume` needs: the engine snapshot, the optimiser,
the sampler and the random states besides the networks, often tens of MB. Every `<root>/*/checkpoint.pt`
that holds a policy is rewritten in place (atomically) with only SLIM_KEYS: the config and the actor
(what `tg-gpudrive evaluate`, `render`, the report and scripts/heldout_eval.py load), the critic (what
`init_policy` also reads), the update reached and the Lagrange multiplier. The result is a few MB, small
enough for the GPU measurement script (scripts/gpu_measure.sh) to bring back; such a run can no longer be
resumed. The kept entries are copied as stored: the file is read with torch.load, not load_checkpoint,
whose defaults for config keys added since would otherwise be written into the config. World-model
checkpoints (their model.pt is what is kept) are left as they are; so are unreadable files, with a note
on stderr. Running it again on slim checkpoints changes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from tg_gpudrive.checkpoint import POLICY, checkpoint_kind, save_atomic
from tg_gpudrive.cli import one_line_errors

# what a policy checkpoint keeps: what loading it for evaluation or as init_policy needs
SLIM_KEYS = ("kind", "config", "actor", "critic", "update", "lagrange")


def slim_policy_checkpoint(path: Path) -> bool:
    """Rewrite the policy checkpoint at `path` with only SLIM_KEYS; False when it holds no policy (a world
    model's) or cannot be read (a note on stderr), leaving it untouched."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for a damaged file
        print(f"left as is: {path} cannot be read ({type(e).__name__})", file=sys.stderr)
        return False
    if not isinstance(ck, dict) or checkpoint_kind(ck) != POLICY:
        return False
    ck["kind"] = POLICY  # checkpoints written before the field existed are policies by their keys
    save_atomic({k: ck[k] for k in SLIM_KEYS if k in ck}, path)
    return True


def slim_runs(root: Path) -> list[Path]:
    """Slim every `root/*/checkpoint.pt` that holds a policy; the files rewritten."""
    return [p for p in sorted(root.glob("*/checkpoint.pt")) if slim_policy_checkpoint(p)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("roots", nargs="+", type=Path, help="directories whose run directories (<root>/*/) are slimmed")
    args = ap.parse_args(argv)
    missing = [str(r) for r in args.roots if not r.is_dir()]
    if missing:  # a mistyped folder would otherwise leave every full checkpoint where it was, silently
        raise FileNotFoundError(f"no such directory: {', '.join(missing)}")
    for root in args.roots:
        slim_runs(root)
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("slim_checkpoints.py", main))
