"""Hand-made scenes with known planner answers (issue 32's test scene).

A straight two-lane road along +x: the ego's lane centred on y = 0 (driving towards +x)
and an oncoming lane centred on y = 3.5 (towards -x), road edges at y = -1.75 and 5.25.
The ego (id 0) starts at the origin at 10 m/s. The other agents, by id:

- 1 ``STOPPED``: a car standing in the ego's lane 40 m ahead (the planners must brake or
  swerve for it);
- 2 ``ONCOMING``: a car in the oncoming lane 300 m ahead at 10 m/s, towards the ego (far
  off: it never comes within 180 m of the ego within a 5 s horizon);
- 3 ``BEHIND``: a slower car (3 m/s) 40 m behind the ego in its lane (slow enough that,
  replayed without reacting, it does not reach an ego that stops behind ``STOPPED``
  within 20 s: a closed loop of that length has no rear-end collision it could not avoid);
- 4 ``PARKED_OFF_ROAD``: a car parked 30 m ahead, 6 m to the right of the ego's lane centre
  (4.25 m beyond the road edge).

:func:`road_frame` builds a frame with any subset of them, :func:`road_map` the map,
:func:`road_scene` a 2 s scene at 10 Hz (every agent at constant speed along its lane) and
:func:`write_road_scene` writes it as an MCAP scene file for ``replay plan``.
"""

from __future__ import annotations

import pathlib
from collections.abc import Iterable

import numpy as np

from risk import Frame, Lane, LaneMap, MapLine, Scene

EGO, STOPPED, ONCOMING, BEHIND, PARKED_OFF_ROAD = 0, 1, 2, 3, 4
OTHERS = (STOPPED, ONCOMING, BEHIND, PARKED_OFF_ROAD)
LANE_WIDTH_M = 3.5
EGO_SPEED_MPS = 10.0
ROAD_X = (-100.0, 600.0)

# id: (x, y, heading, speed, length, width)
_AGENTS: dict[int, tuple[float, float, float, float, float, float]] = {
    EGO: (0.0, 0.0, 0.0, EGO_SPEED_MPS, 4.5, 1.8),
    STOPPED: (40.0, 0.0, 0.0, 0.0, 4.5, 1.8),
    ONCOMING: (300.0, LANE_WIDTH_M, np.pi, 10.0, 4.5, 1.8),
    BEHIND: (-40.0, 0.0, 0.0, 3.0, 4.5, 1.8),
    PARKED_OFF_ROAD: (30.0, -6.0, 0.0, 0.0, 4.5, 1.8),
}


def road_map() -> LaneMap:
    """The two lanes (ids 10: ego direction, 11: oncoming), edges and the centre line."""
    x = np.linspace(*ROAD_X, 71)
    ego_lane = np.stack([x, np.zeros_like(x)], axis=1)
    oncoming = np.stack([x[::-1], np.full_like(x, LANE_WIDTH_M)], axis=1)
    half = LANE_WIDTH_M / 2

    def line(y: float) -> np.ndarray:
        return np.array([[ROAD_X[0], y], [ROAD_X[1], y]])

    return LaneMap(
        lanes=(Lane(10, ego_lane), Lane(11, oncoming)),
        lines=(
            MapLine(20, "road_edge", line(-half)),
            MapLine(21, "lane_boundary", line(half), style="dashed_yellow"),
            MapLine(22, "road_edge", line(LANE_WIDTH_M + half)),
        ),
    )


def _path(x: float, y: float, heading: float) -> np.ndarray:
    """The agent's lane ahead of it, to the end of the road."""
    end = ROAD_X[1] if np.cos(heading) > 0 else ROAD_X[0]
    return np.array([[x, y], [end, y]])


def road_frame(agents: Iterable[int] = OTHERS, *, t: float = 0.0) -> Frame:
    """The frame at time ``t`` (every agent moved at its speed along its lane) with the
    ego and ``agents`` (ids from OTHERS)."""
    ids = [EGO, *sorted(set(agents))]
    rows = np.array([_AGENTS[i] for i in ids])
    x = rows[:, 0] + np.cos(rows[:, 2]) * rows[:, 3] * t
    y = rows[:, 1]
    kinds = ["vehicle"] * len(ids)
    paths = [_path(float(a), float(b), float(h)) for a, b, h in zip(x, y, rows[:, 2], strict=True)]
    # The parked car off the road has no lane: a one-point path.
    paths = [p[:1] if i == PARKED_OFF_ROAD else p for i, p in zip(ids, paths, strict=True)]
    return Frame.from_arrays(
        xy=np.stack([x, y], axis=1),
        heading=rows[:, 2],
        speed=rows[:, 3],
        length=rows[:, 4],
        width=rows[:, 5],
        paths=paths,
        ego=0,
        ids=ids,
        kinds=kinds,
        t=t,
    )


def road_scene(agents: Iterable[int] = OTHERS, *, duration_s: float = 2.0) -> Scene:
    """A scene of ``duration_s`` at 10 Hz (constant speeds along the lanes)."""
    chosen = tuple(agents)
    times = np.round(np.arange(0.0, duration_s + 1e-9, 0.1), 6)
    return Scene(
        map=road_map(),
        frames=tuple(road_frame(chosen, t=float(t)) for t in times),
        frame_period_s=0.1,
        metadata={"dataset": "hand-made", "scenario_id": "two-lane-road", "converter": "tests"},
        ego_id=EGO,
    )


def write_road_scene(path: str | pathlib.Path, agents: Iterable[int] = OTHERS) -> pathlib.Path:
    """Write :func:`road_scene` to an MCAP scene file; returns its path."""
    from converters.scene.writer import write_scene  # tests only: keeps this module import light

    return write_scene(path, road_scene(agents))
