"""Learned world model: the behaviour prior (magnet) of CCE-MAPPO and reactive background traffic.

    from tg_gpudrive.worldmodel import load_shipped, WorldModelPrior, WorldModelDriver
    trainer.prior = WorldModelPrior(load_shipped(sim), sim)
    driver = WorldModelDriver(load_shipped(sim))      # driver(sim) writes the background rows

model.py holds the network and the history window, prior.py its uses and
checkpoints, train.py `train_world_model` / `main` and the evaluation helpers.
"""

from tg_gpudrive.worldmodel.model import HistoryBuffer, WorldModel
from tg_gpudrive.worldmodel.prior import (WorldModelDriver, WorldModelPrior, load_shipped, load_world_model,
                                          save_world_model)

__all__ = ["HistoryBuffer", "WorldModel", "WorldModelDriver", "WorldModelPrior", "load_shipped",
           "load_world_model", "save_world_model"]
