"""Frame builders shared by the tests: random frames for property and oracle tests.

- :func:`wander`: a wandering polyline (the paths of the random frames);
- :func:`random_frame`: a few agents anywhere, bodies and path candidates optional;
- :func:`mixed_frame`: leaders on the ego path, crossing agents, forks, invalid tracks;
- :func:`scattered_frame`: many agents on straight paths over a 120 m square.

Each keeps the draws its tests were written with, so that seeds mean what they meant.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from risk import Frame

KINDS = ("vehicle", "pedestrian", "cyclist", "other")


def wander(
    rng: np.random.Generator,
    start: Sequence[float] | np.ndarray,
    heading: float,
    max_points: int = 8,
    *,
    turn_sd: float = 0.5,
    step_m: tuple[float, float] = (0.5, 15.0),
) -> np.ndarray:
    """A wandering polyline ``(P, 2)`` from ``start``: up to ``max_points - 1`` more points,
    each turning by a normal angle (sd ``turn_sd`` rad) and ``step_m`` metres apart."""
    pts = [np.asarray(start, float)]
    h = heading
    for _ in range(int(rng.integers(0, max_points))):
        h += rng.normal(0.0, turn_sd)
        pts.append(pts[-1] + rng.uniform(*step_m) * np.array([math.cos(h), math.sin(h)]))
    return np.array(pts)


def random_frame(
    rng: np.random.Generator, n: int | None = None, *, bodies: bool = True, candidates: bool = True
) -> Frame:
    """2-6 agents (or ``n``) anywhere in an 80 m square on wandering paths (a quarter with
    two candidates), a fifth standing still, all kinds; ``bodies=False``: point agents."""
    n = int(rng.integers(2, 7)) if n is None else n
    xy = rng.uniform(-40, 40, (n, 2))
    heading = rng.uniform(-math.pi, math.pi, n)
    paths = []
    for i in range(n):
        k = int(rng.integers(1, 3)) if candidates and rng.random() < 0.25 else 1
        cands = [wander(rng, xy[i], heading[i]) for _ in range(k)]
        paths.append(cands[0] if k == 1 else cands)
    speed = rng.uniform(0, 15, n)
    speed[rng.random(n) < 0.2] = 0.0
    length = rng.uniform(0, 6, n) if bodies else np.zeros(n)
    width = rng.uniform(0, 2.5, n) if bodies else np.zeros(n)
    kinds = [KINDS[j] for j in rng.integers(0, 4, n)]
    return Frame.from_arrays(xy, heading, speed, length, width, paths, ego=0, kinds=kinds)


def mixed_frame(rng: np.random.Generator) -> Frame:
    """Mixed situations: wandering paths, leaders on the ego path, crossing agents,
    standing agents, forks, invalid tracks, all kinds."""
    n = int(rng.integers(2, 7))
    ego_path = wander(rng, [0.0, 0.0], 0.0, max_points=6, turn_sd=0.6, step_m=(0.3, 12.0))
    if len(ego_path) < 2:
        ego_path = np.array([[0.0, 0.0], [40.0, 5.0]])
    xy, heading, paths = [np.zeros(2)], [0.0], [ego_path]
    for _ in range(n - 1):
        kind = rng.integers(0, 3)
        if kind == 0:  # anywhere
            start = rng.uniform(-30, 30, 2)
            h = rng.uniform(-math.pi, math.pi)
        elif kind == 1:  # on (or near) the ego path
            j = int(rng.integers(0, len(ego_path) - 1))
            f = rng.random()
            start = ego_path[j] + f * (ego_path[j + 1] - ego_path[j]) + rng.normal(0, 0.8, 2)
            d = ego_path[j + 1] - ego_path[j]
            h = math.atan2(d[1], d[0]) + rng.choice([0.0, math.pi])
        else:  # heading across the ego path
            j = int(rng.integers(0, len(ego_path)))
            h = rng.uniform(-math.pi, math.pi)
            start = ego_path[j] - rng.uniform(3, 25) * np.array([math.cos(h), math.sin(h)])
        cands = [wander(rng, start, h, max_points=7, turn_sd=0.6, step_m=(0.3, 12.0))]
        if rng.random() < 0.2:
            cands.append(
                wander(
                    rng, start, h + rng.normal(0, 1), max_points=7, turn_sd=0.6, step_m=(0.3, 12.0)
                )
            )
        xy.append(start)
        heading.append(h)
        paths.append(cands[0] if len(cands) == 1 else cands)
    speed = rng.uniform(0, 14, n)
    speed[rng.random(n) < 0.25] = 0.0
    valid = rng.random(n) > 0.1
    valid[0] = True
    return Frame.from_arrays(
        np.array(xy),
        np.array(heading),
        speed,
        rng.uniform(0, 6, n),
        rng.uniform(0, 2.5, n),
        paths,
        ego=0,
        kinds=[KINDS[k] for k in rng.integers(0, 4, n)],
        valid=valid,
    )


def scattered_frame(seed: int, n: int = 40) -> Frame:
    """Agents scattered over a 120 m square, straight paths of 40 m to 120 m."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-60, 60, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    reach = rng.uniform(40, 120, n)
    steps = np.linspace(0, 1, 12)[None, :, None]
    direction = np.c_[np.cos(heading), np.sin(heading)][:, None, :]
    paths = xy[:, None, :] + steps * reach[:, None, None] * direction
    kinds = rng.choice(["vehicle", "pedestrian", "cyclist"], n, p=[0.7, 0.2, 0.1])
    valid = rng.random(n) > 0.1
    valid[0] = True
    return Frame.from_arrays(
        xy, heading, rng.uniform(0, 12, n), np.full(n, 4.5), np.full(n, 1.8), list(paths), 0,
        kinds=kinds, valid=valid,
    )  # fmt: skip
