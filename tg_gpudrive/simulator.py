"""Public import path of the `Simulator` (`from tg_gpudrive.simulator import Simulator`, as the README
shows); it lives in `tg_gpudrive/engine/simulator.py`."""

from tg_gpudrive.engine.simulator import Simulator, resolve_device

__all__ = ["Simulator", "resolve_device"]
