"""Integer kinds and modes shared by loaders, kernels, configs and the learner.

The values are stored in scene files, kernel arrays and checkpoints, so they must never be
renumbered: add new members at the end. Modes (`NamedMode` subclasses) are spelled in YAML,
on the command line and in JSON reports by their lowercase names (`str(CollisionMode.STOP)
== "stop"`, `CollisionMode("stop") is CollisionMode.STOP`); the kernels see their integer
values through `wp.constant`s declared once in kernels/kinds.py. Python code compares
members, never the strings.
"""

from __future__ import annotations

import enum


class AgentType(enum.IntEnum):
    NONE = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    CYCLIST = 3
    OTHER = 4


class RoadType(enum.IntEnum):
    """Road polyline kinds; names follow GPUDrive's processed WOMD JSON."""

    NONE = 0
    LANE = 1
    ROAD_LINE = 2
    ROAD_EDGE = 3
    STOP_SIGN = 4
    CROSSWALK = 5
    SPEED_BUMP = 6
    DRIVEWAY = 7


POLYGON_ROAD_TYPES = (RoadType.CROSSWALK, RoadType.SPEED_BUMP, RoadType.DRIVEWAY)
"""Road kinds stored as closed shapes (an implied edge from the last point back to the first)."""


class NamedMode(enum.IntEnum):
    """An IntEnum that parses from and prints as its lowercase member name (the YAML / CLI spelling)."""

    @classmethod
    def _missing_(cls, value):
        if isinstance(value, str):
            return cls.__members__.get(value.strip().upper())
        return None

    @classmethod
    def parse(cls, value, what: str | None = None, allowed: tuple[NamedMode, ...] | None = None) -> NamedMode:
        """`value` (a member, its name in any case, or its integer) as a member of `allowed` (default:
        all); anything else is a ValueError naming `what` and the accepted names."""
        allowed = tuple(cls) if allowed is None else allowed
        try:
            member = cls(value) if not isinstance(value, bool) else None
        except ValueError:
            member = None
        if member not in allowed:
            choices = ", ".join(str(m) for m in allowed)
            raise ValueError(f"{what or cls.__name__}: expected one of {choices}, got {value!r}")
        return member

    def __str__(self) -> str:
        return self.name.lower()

    def __format__(self, spec: str) -> str:
        return format(str(self), spec)


class CollisionMode(NamedMode):
    """What happens to a controlled agent after it collides or leaves the road."""

    IGNORE = 0  # event counted, agent keeps driving
    STOP = 1  # agent frozen in place and done
    REMOVE = 2  # agent taken out of the scene and of later collision checks, done


class GoalBehaviour(NamedMode):
    """What happens to a controlled agent when it reaches its goal."""

    CONTINUE = 0  # counted, the agent keeps driving
    STOP = 1  # frozen in place and done
    REMOVE = 2  # taken out of the scene, done (GPUDrive's default)


class Dynamics(NamedMode):
    BICYCLE = 0  # action (accel m/s^2, curvature 1/m)
    DELTA_LOCAL = 1  # action (dx m, dy m, dyaw rad) in the agent's frame


class ActionSpace(NamedMode):
    DISCRETE = 0  # an index into the accel x curvature grid (bicycle only)
    CONTINUOUS = 1  # the action values themselves


class ControlMode(NamedMode):
    """Which agents the policy drives (tg_gpudrive.engine.control decides the masks).

    The engine config's `control` takes NONE, VEHICLES or ALL_AGENTS (`ENGINE_CONTROL`); a training
    run's `control` takes VEHICLES, NEAREST_CONFLICT or IDS (`SELECT_CONTROL`)."""

    NONE = 0  # nobody: every agent replays its log
    VEHICLES = 1  # every vehicle present at init_step and away from its goal
    ALL_AGENTS = 2  # every agent present at init_step and away from its goal
    NEAREST_CONFLICT = 3  # the k eligible vehicles nearest the scene's conflict point
    IDS = 4  # the agents whose source track ids are listed


ENGINE_CONTROL = (ControlMode.VEHICLES, ControlMode.ALL_AGENTS, ControlMode.NONE)
SELECT_CONTROL = (ControlMode.VEHICLES, ControlMode.NEAREST_CONFLICT, ControlMode.IDS)


class TrafficLightState(enum.IntEnum):
    """WOMD TrafficSignalLaneState.State values, kept verbatim."""

    UNKNOWN = 0
    ARROW_STOP = 1
    ARROW_CAUTION = 2
    ARROW_GO = 3
    STOP = 4
    CAUTION = 5
    GO = 6
    FLASHING_STOP = 7
    FLASHING_CAUTION = 8


def parse_enum(enum_cls: type[enum.IntEnum], name: str | int, what: str) -> enum.IntEnum:
    """Look up an enum member by case-insensitive name (or value); error names `what`."""
    if isinstance(name, int):
        return enum_cls(name)
    try:
        return enum_cls[str(name).upper()]
    except KeyError:
        choices = ", ".join(m.name.lower() for m in enum_cls if m.name != "NONE")
        raise ValueError(f"{what}: unknown value {name!r}; expected one of {choices}") from None
