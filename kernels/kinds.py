"""The integer values of the engine's modes and kinds as Warp constants, declared once.

Every kernel module that branches on a mode or a kind imports its constant from here; the
values come from the IntEnums of tg_gpudrive.enums, so Python and the kernels cannot disagree.
"""

from __future__ import annotations

import warp as wp

from tg_gpudrive.enums import CollisionMode, Dynamics, GoalBehaviour, RoadType

COLLISION_IGNORE = wp.constant(int(CollisionMode.IGNORE))
COLLISION_STOP = wp.constant(int(CollisionMode.STOP))
COLLISION_REMOVE = wp.constant(int(CollisionMode.REMOVE))

GOAL_CONTINUE = wp.constant(int(GoalBehaviour.CONTINUE))
GOAL_STOP = wp.constant(int(GoalBehaviour.STOP))
GOAL_REMOVE = wp.constant(int(GoalBehaviour.REMOVE))

DYNAMICS_BICYCLE = wp.constant(int(Dynamics.BICYCLE))
DYNAMICS_DELTA_LOCAL = wp.constant(int(Dynamics.DELTA_LOCAL))

ROAD_LANE = wp.constant(int(RoadType.LANE))
ROAD_EDGE = wp.constant(int(RoadType.ROAD_EDGE))
