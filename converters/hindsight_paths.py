"""Agent paths from the agent's own recorded future (``--paths hindsight``).

For offline analysis the best available path of an agent is where it actually went: its
recorded positions from this frame on (valid states only; a gap is bridged by a straight
segment), then a straight extension beyond its last valid state along the heading
recorded there, so that the path is at least ``v * horizon_s + margin_m`` long
(:class:`converters.lanegraph.PathSettings`). Unlike ``--paths map`` the recorded part is
never cut: the whole future route is the path.

Each track is simplified once per scene (Ramer-Douglas-Peucker at ``simplify_m``, after
dropping repeated positions): this removes the measurement jitter of standing agents and
the many collinear points of straight driving; every frame then takes the simplified
vertices that lie after it, vectorised over all (frame, agent) queries.
"""

from __future__ import annotations

import numpy as np

from converters.lanegraph import PathRows, PathSettings, arc_length, simplify


class Hindsight:
    """The simplified recorded tracks of one scene.

    ``xy`` ``(T, N, 2)`` m, ``heading`` ``(T, N)`` rad and ``valid`` ``(T, N)`` bool are
    the scene's track arrays (time steps x agents).
    """

    def __init__(
        self,
        xy: np.ndarray,
        heading: np.ndarray,
        valid: np.ndarray,
        settings: PathSettings | None = None,
    ) -> None:
        self.settings = settings or PathSettings()
        n_steps, n_agents = valid.shape
        vertices: list[np.ndarray] = []
        steps: list[np.ndarray] = []
        last_heading = np.zeros(n_agents)
        for n in range(n_agents):  # once per scene, not per frame
            t_valid = np.flatnonzero(valid[:, n])
            pts = xy[t_valid, n]
            if len(pts):
                last_heading[n] = heading[t_valid[-1], n]
                step = np.hypot(*np.diff(pts, axis=0).T)
                distinct = np.concatenate(([True], step > 1e-6))
                pts, t_valid = pts[distinct], t_valid[distinct]
                keep = simplify(pts, self.settings.simplify_m)
                pts, t_valid = pts[keep], t_valid[keep]
            vertices.append(pts)
            steps.append(t_valid)
        width = max(1, max(len(v) for v in vertices))
        self._n_vertices = np.array([len(v) for v in vertices], dtype=np.int64)
        self._vertices = np.zeros((n_agents, width, 2))
        # Padding steps lie after every frame, so "vertices after frame f" counts only real ones.
        self._steps = np.full((n_agents, width), np.iinfo(np.int64).max, dtype=np.int64)
        self._cum = np.zeros((n_agents, width))
        for n, (v, t) in enumerate(zip(vertices, steps, strict=True)):
            if len(v):
                self._vertices[n, : len(v)] = v
                self._vertices[n, len(v) :] = v[-1]
                self._steps[n, : len(v)] = t
                cum = arc_length(v)
                self._cum[n, : len(v)] = cum
                self._cum[n, len(v) :] = cum[-1]
        self._last_heading = last_heading
        self.n_steps = n_steps

    def rows(
        self,
        step: np.ndarray,
        frame: np.ndarray,
        agent: np.ndarray,
        xy: np.ndarray,
        speed: np.ndarray,
    ) -> PathRows:
        """One path per query: agent ``agent`` at time step ``step`` (its state ``xy``
        ``(Q, 2)`` m and ``speed`` ``(Q,)`` m/s), tagged with output frame ``frame``."""
        q = len(step)
        if q == 0:
            return PathRows.empty()
        rows = np.arange(q)
        n_vert = self._n_vertices[agent]
        first = (self._steps[agent] <= step[:, None]).sum(axis=1)  # first vertex after step
        ahead = np.maximum(n_vert - first, 0)
        last_idx = np.maximum(n_vert - 1, 0)
        first_c = np.minimum(first, last_idx)
        recorded = np.where(
            ahead > 0,
            np.hypot(*(self._vertices[agent, first_c] - xy).T)
            + self._cum[agent, last_idx]
            - self._cum[agent, first_c],
            0.0,
        )
        end = np.where((ahead > 0)[:, None], self._vertices[agent, last_idx], xy)
        extension = self.settings.required_length_m(speed) - recorded
        extend = extension > 1e-9
        h = self._last_heading[agent]
        ext_point = end + np.maximum(extension, 0.0)[:, None] * np.stack(
            [np.cos(h), np.sin(h)], axis=1
        )
        width = 2 + int(ahead.max(initial=0))
        out = np.empty((q, width, 2))
        out[:, 0] = xy
        j = np.arange(width - 2)
        rr, jj = np.nonzero(j[None, :] < ahead[:, None])
        out[rr, 1 + jj] = self._vertices[agent[rr], first[rr] + jj]
        count = 1 + ahead
        out[rows, count] = ext_point
        count = count + extend
        last = out[rows, count - 1]
        pad = np.arange(width)[None, :] >= count[:, None]
        out = np.where(pad[:, :, None], last[:, None, :], out)
        paths = PathRows(
            frame.astype(np.int64), agent.astype(np.int64), out, count.astype(np.int64)
        )
        return paths.without_repeats()
