"""Learned world model: the behaviour prior (magnet) of CCE-MAPPO and reactive background traffic.

    from tg_gpudrive.worldmodel import load_shipped, WorldModelPrior, WorldModelDriver
    trainer.prior = WorldModelPrior(load_shipped(sim), sim)
    driver = WorldModelDriver(load_shipped(sim))      # driver(sim) writes the background rows

model.py holds the network (a discrete-grid or a mixture-of-Laplace head) and the
history window, mixture.py the continuous head's distribution and its KL from a
Gaussian policy, prior.py its uses and checkpoints, closed_loop.py the corrective
labels of closed-loop (DAgger) fine-tuning, train.py `train_world_model` / `main`
and the evaluation helpers.
"""

from tg_gpudrive.worldmodel.mixture import LaplaceMixture
from tg_gpudrive.worldmodel.model import HistoryBuffer, WorldModel
from tg_gpudrive.worldmodel.prior import (WorldModelDriver, WorldModelPrior, load_shipped, load_world_model,
                                          save_world_model)

__all__ = ["HistoryBuffer", "LaplaceMixture", "WorldModel", "WorldModelDriver", "WorldModelPrior", "load_shipped",
           "load_world_model", "save_world_model"]
