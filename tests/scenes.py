"""Hand-made scenes shared by the engine and env tests."""

from __future__ import annotations

import numpy as np

from tg_gpudrive.scene import make_scene


def crossing_scene(T: int = 40):
    """A drives +x towards (20, 0), B crosses it driving +y, C follows A 15 m behind.

    At constant velocity (the no-op action) A and B first overlap at log step 18."""
    t = np.arange(T) * 0.1
    pos = np.zeros((3, T, 2))
    pos[0, :, 0] = 10 * t
    pos[1, :, 0] = 20.0
    pos[1, :, 1] = -20 + 10 * t
    pos[2, :, 0] = -15 + 10 * t
    pos[:, -1] += np.array([[500, 0], [0, 500], [500, 0]])  # goals far away
    yaw = np.zeros((3, T))
    yaw[1] = np.pi / 2
    vel = np.zeros((3, T, 2))
    vel[:, :, 0] = [[10], [0], [10]]
    vel[1, :, 1] = 10
    return make_scene(pos, yaw, log_vel=vel, length=4.0, width=2.0)
