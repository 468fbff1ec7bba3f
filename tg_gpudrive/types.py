"""Integer kinds shared by loaders, kernels and the learner.

The values are stored in scene files and in kernel arrays, so they must never
be renumbered: add new members at the end.
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


class CollisionMode(enum.IntEnum):
    """What happens to a controlled agent after it collides or leaves the road."""

    IGNORE = 0  # event counted, agent keeps driving
    STOP = 1  # agent frozen in place and done
    REMOVE = 2  # agent taken out of the scene and of later collision checks, done


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
