"""Learned world model: the behaviour prior (magnet) of CCE-MAPPO and reactive background traffic.

    from tg_gpudrive.worldmodel import load_shipped, WorldModelPrior, WorldModelDriver
    trainer.prior = WorldModelPrior(load_shipped(sim), sim)
    driver = WorldModelDriver(load_shipped(sim))      # driver(sim) writes the background rows

    model.py        the network (a discrete-grid or a mixture-of-Laplace head) and the history window
    mixture.py      the continuous head's distribution and its KL from a Gaussian policy
    prior.py        its uses (the magnet, the driver) and its checkpoints
    data.py         teacher-forced samples of the logged expert
    closed_loop.py  corrective labels of closed-loop (DAgger) fine-tuning
    metrics.py      NLL and baselines, minADE / minFDE, closed-loop collision / off-road
    train.py        `train_world_model`: fitting, DAgger rounds, logging, checkpoints
    cli.py          `tg-gpudrive train-world-model`

It depends on the engine and tg_gpudrive.agents.policy (the BehaviourPrior interface), never on the
learner (tg_gpudrive.learn), which imports it for the magnet.
"""

from tg_gpudrive.history import HistoryBuffer
from tg_gpudrive.worldmodel.mixture import LaplaceMixture
from tg_gpudrive.worldmodel.model import WorldModel
from tg_gpudrive.worldmodel.prior import (WorldModelDriver, WorldModelPrior, load_shipped, load_world_model,
                                          save_world_model)

__all__ = ["HistoryBuffer", "LaplaceMixture", "WorldModel", "WorldModelDriver", "WorldModelPrior", "load_shipped",
           "load_world_model", "save_world_model"]
