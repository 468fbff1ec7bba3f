"""Ctrl-C during training: end the update under way, save it, then stop (stop.StopRequest)."""

from __future__ import annotations

import signal
import sys
import threading

import torch

from tg_gpudrive.learn import distributed as dist_util


class StopRequest:
    """Ctrl-C during training: the first SIGINT asks the loop to end the update under way and save it
    (a checkpoint at the last finished update, so --resume continues exactly); a second one stops at
    once. Outside the main thread (where no handler can be installed) Ctrl-C keeps its default."""

    def __init__(self):
        self._flag = False
        self._old = None

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)

    def _handle(self, signum, frame) -> None:
        if self._flag:
            raise KeyboardInterrupt
        self._flag = True
        print("\ntg-gpudrive train: Ctrl-C: finishing this update, then saving a checkpoint "
              "(Ctrl-C again stops at once, keeping the last saved one)", file=sys.stderr)

    @property
    def mine(self) -> bool:
        """Whether this process was asked to stop (no collective)."""
        return self._flag

    def requested(self, device) -> bool:
        """Whether a stop was asked for, on any rank (every rank must leave at the same update)."""
        if dist_util.world_size() == 1:
            return self._flag
        return bool(dist_util.all_reduce_mean(torch.tensor(float(self._flag), device=device)) > 0)
