"""The batched engine: `model` (Model / State / Control and the builder from Scenes), `control` (who
the policy drives), `simulator` (the torch-facing `Simulator`). The kernels live in `kernels/`."""

from tg_gpudrive.engine.model import Control, Model, State
from tg_gpudrive.engine.simulator import Simulator, resolve_device

__all__ = ["Control", "Model", "Simulator", "State", "resolve_device"]
