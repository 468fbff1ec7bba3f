"""What a training run writes beside its checkpoints: metrics.csv (one row per update), timing.csv (one row
per rank and update), heldout.csv (the held-out checks), TensorBoard events when the extra is installed,
and curves.png. Only the lead rank writes; `trim` cuts rows written after the checkpoint a run resumes."""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

from tg_gpudrive.learn.plots import plot_curves

log = logging.getLogger(__name__)


def append_csv(path: Path, rows: list[dict]) -> None:
    """Append `rows` (dicts with the same keys) to the CSV file `path`, with a header when it is new."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        if new:
            w.writeheader()
        w.writerows(rows)


class RunLog:
    """The run directory's logs (see the module docstring); every method does nothing off the lead rank."""

    def __init__(self, out: Path, lead: bool):
        self.out, self.lead = Path(out), lead
        self.metrics_path = self.out / "metrics.csv"
        self._tb = None
        self._tb_tried = False

    def metrics(self, row: dict) -> None:
        """One update's row: metrics.csv, and TensorBoard under the same names (reward/<term>, kl/prior, ...)."""
        if not self.lead:
            return
        append_csv(self.metrics_path, [row])
        tb = self._tensorboard(int(row["update"]))
        if tb is not None:
            for k, v in row.items():
                if isinstance(v, (int, float)) and k != "update" and math.isfinite(v):
                    tb.add_scalar(k, v, row["update"])
            tb.flush()

    def timing(self, update: int, phases: list[list[float]]) -> None:
        """timing.csv: one row per rank (rollout, wait for the slowest rollout, update, s), long format so a
        run resumed on another number of ranks appends cleanly."""
        if self.lead:
            append_csv(self.out / "timing.csv", [{"update": update, "rank": r, "rollout_s": f"{own:.6f}",
                                                  "wait_s": f"{wait:.6f}", "update_s": f"{upd:.6f}"}
                                                 for r, (own, wait, upd) in enumerate(phases)])

    def heldout(self, row: dict) -> None:
        if self.lead:
            append_csv(self.out / "heldout.csv", [row])

    def _tensorboard(self, update: int):
        """A SummaryWriter into the run directory when `tensorboard` is installed (the optional extra
        `pip install tg_gpudrive[tensorboard]`), else None; metrics.csv is written either way."""
        if not self._tb_tried:
            self._tb_tried = True
            try:
                # optional (the tensorboard extra), and slow to import: only when a run logs
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:
                return None
            self._tb = SummaryWriter(log_dir=str(self.out), purge_step=update or None)
        return self._tb

    def plot(self) -> Path | None:
        """PNG of the training curves (metrics.csv -> curves.png)."""
        if not (self.lead and self.metrics_path.exists()):
            return None
        try:
            return plot_curves(self.metrics_path, self.out / "curves.png")
        except ModuleNotFoundError as e:  # the render extra: a finished run's files stand without it
            if e.name != "matplotlib":
                raise
            log.warning("%s: curves.png not drawn, matplotlib is not installed (pip install 'tg_gpudrive[render]'); "
                        "metrics.csv holds the curves", self.out)
            return None

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()

    def trim(self, update: int) -> None:
        """metrics.csv and timing.csv may hold rows written after the checkpoint of `update` a run resumes:
        keep only those up to it (a row cut short by a kill is dropped with the rest)."""
        for path in (self.metrics_path, self.out / "timing.csv"):
            if not (self.lead and path.exists()):
                continue
            rows = list(csv.DictReader(path.open()))
            whole = [r for r in rows if None not in r.values() and str(r.get("update", "")).isdigit()]
            if len(whole) != len(rows):
                log.warning("%s: %d damaged row(s) dropped", path, len(rows) - len(whole))
            keep = [r for r in whole if int(r["update"]) <= update]
            if len(keep) != len(rows):
                with path.open("w", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
                    w.writeheader()
                    w.writerows(keep)
