"""Where everything lives in a replay recording: entity paths, colours, shapes, blueprint.

The recorder (:mod:`recordings.recorder`) decides *what* to log; this module decides
*where* and *how it looks*, so that the layout can be read (and changed) in one place.
``docs/recording.md`` describes what a reviewer sees.

Coordinates: the scene is logged in map metres (x east, y north) under :data:`SCENE`; a
static ``Transform3D(scale=[1, -1, 1])`` on :data:`SCENE` flips it for display, because
Rerun's 2D view draws y downwards. The data keep their true map coordinates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

# ---------------------------------------------------------------------- entity paths
TIMELINE = "time"  # duration timeline, seconds of the log (Frame.t)
FRAME_TIMELINE = "frame"  # sequence timeline, frame index in the scene

SCENE = "/scene"
MAP = "/scene/map"
MAP_LANES = "/scene/map/lanes"  # lane centre lines
# Map lines of format version 2, one entity per kind (MapLine.kind -> entity).
MAP_LINES = {
    "lane_boundary": "/scene/map/lane_boundaries",
    "road_edge": "/scene/map/road_edges",
    "crosswalk": "/scene/map/crosswalks",
    "stop_line": "/scene/map/stop_lines",
    "other": "/scene/map/other_lines",
}
EGO_BODY = "/scene/ego/body"  # capsule + heading nose, label "ego <id>"
EGO_PATH = "/scene/ego/path"
PLAN_ALL = "/scene/ego/plan_all_agents"  # a planner's plan with every agent
PLAN_FILTERED = "/scene/ego/plan_filtered"  # and with the agents the cascade kept
# The ego's pose over time (translation and a turn that puts its heading up, its left to
# the left): no drawing of its own; the ego view takes it as its origin, so the whole
# scene is shown from the ego, driving up the view.
EGO_FRAME = "/scene/ego_frame"
AGENTS = "/scene/agents"  # one subtree per other agent: /scene/agents/<id>/...
LINKS = "/scene/links"  # optional: one child per stage, ego -> every agent kept after it

# Children of an agent's subtree.
BODY = "body"  # capsule, heading nose and marker (tier outline / miss ring); miss log rows
PATH = "path"  # forward path candidates (deeper-tier survivors only)
RISK = "risk"  # risk/<model>: raw risk in the model's units
RISK_LOG10 = "risk_log10"  # risk_log10/<model>, for models whose values span many decades
THRESHOLDS = "/thresholds"  # /thresholds/<model>: a stage threshold in its model's view
THRESHOLDS_LOG10 = "/thresholds_log10"
FUNNEL = "/funnel"  # agents left after each step of the cascade
FALSE_NEGATIVES = "/false_negatives"  # per frame: baseline agents dropped by stage k or earlier
TIMING = "/timing_ms"  # compute time per stage, milliseconds
SUMMARY = "/summary"  # markdown: scene, cascade settings, legend

THRESHOLD_SERIES = "threshold"  # child of a risk view: the stage threshold, if any


def stage_key(index: int, model: str) -> str:
    """Entity name of stage ``index`` (0-based): ``"1_path_distance"`` (1-based, ordered)."""
    return f"{index + 1}_{model}"


def link_path(index: int, model: str) -> str:
    return f"{LINKS}/{stage_key(index, model)}"


def agent_path(agent_id: int) -> str:
    """The root of one agent's subtree: body, path and risk timelines together."""
    return f"{AGENTS}/{agent_id}"


def body_path(agent_id: int) -> str:
    return f"{AGENTS}/{agent_id}/{BODY}"


def agent_paths_path(agent_id: int) -> str:
    return f"{AGENTS}/{agent_id}/{PATH}"


def risk_path(model: str, agent_id: int, *, log10: bool = False) -> str:
    return f"{AGENTS}/{agent_id}/{RISK_LOG10 if log10 else RISK}/{model}"


def threshold_path(model: str, *, log10: bool = False) -> str:
    return f"{THRESHOLDS_LOG10 if log10 else THRESHOLDS}/{model}"


# ---------------------------------------------------------------------- colours (RGB)
BACKGROUND = (18, 18, 20)
LANE = (88, 88, 94)
LANE_OTHER = (70, 90, 110)  # lanes whose kind is not "vehicle" (crosswalks, bike lanes)
# Map lines (version 2): muted, below the lanes' contrast, so that agents stay on top.
MAP_LINE_COLORS = {
    "lane_boundary": (62, 62, 68),
    "road_edge": (120, 110, 90),
    "crosswalk": (70, 95, 120),
    "stop_line": (110, 70, 70),
    "other": (60, 60, 60),
}
MAP_LINE_WIDTHS_UI = {
    "lane_boundary": 0.7,
    "road_edge": 1.3,
    "crosswalk": 1.0,
    "stop_line": 1.0,
    "other": 0.7,
}
EGO = (40, 200, 90)
PLAN_ALL_COLOR = (250, 250, 250)  # white: the reference plan
PLAN_FILTERED_COLOR = (255, 150, 30)  # orange: the plan with the filtered agents
DROPPED = (150, 150, 158)  # lighter than every map line: agents stay on top
RISK_LOW = (255, 200, 200)  # survivor with the lowest survival risk on the scale
RISK_HIGH = (215, 25, 25)  # survivor with survival risk >= 1
MISSED = (255, 225, 0)  # a miss: dropped although the baseline or hindsight marks it important
HINDSIGHT = (255, 140, 0)  # ring around a kept agent that really came close (hindsight)
NOSE = (20, 20, 20)  # heading mark on every body
OTHERS_SERIES = (230, 230, 230)
QUIET_SERIES = (75, 75, 80)  # risk lines of agents the cascade never kept

# Stage colours (links, funnel, timing); cycled when a cascade has more stages.
STAGE_COLORS = ((70, 140, 255), (255, 150, 40), (190, 110, 255), (40, 200, 200), (230, 90, 160))
STAGE_COLOR_NAMES = ("blue", "orange", "violet", "teal", "pink")
# Tier outlines: behavior, interactive, cooperative, ...; deeper tiers stand out more.
TIER_COLORS = ((235, 235, 235), (0, 220, 255), (255, 60, 255), (120, 255, 120))
TIER_COLOR_NAMES = ("white", "cyan", "magenta", "green")
# Stage links get thinner with each stage so that nested sets read as nested bands.
LINK_WIDTHS_UI = (2.6, 1.7, 0.9, 0.7, 0.5)

OUTLINE_WIDTHS_UI = (1.0, 2.0, 2.6, 3.0)  # per tier: deeper tiers stand out more
LINK_ALPHA = 110
PATH_ALPHA = 140
LANE_WIDTH_UI = 1.0
PATH_WIDTH_UI = 1.2
OUTLINE_WIDTH_UI = 1.5
NOSE_WIDTH_UI = 1.5
LABEL_SPACING_M = 7.0
"""Two labels closer than this (map metres) would overlap at the opening zoom (~10 px/m):
the less important one gives way (its id still shows on hover)."""
FOCUS_AGENTS_MAX = 12
"""At most this many agents open in the risk views (misses first, then deeper tiers): more
lines than that no longer read as separate agents."""

# Draw order in the 2D view (higher on top).
ORDER_MAP_LINES = 0.5
ORDER_MAP = 1.0
ORDER_LINKS = 5.0
ORDER_PATHS = 6.0
ORDER_AGENTS = 11.0  # every agent's body (capsule, nose, marker)
ORDER_EGO = 14.0


def stage_color(index: int) -> tuple[int, int, int]:
    return STAGE_COLORS[index % len(STAGE_COLORS)]


def stage_color_name(index: int) -> str:
    return STAGE_COLOR_NAMES[index % len(STAGE_COLOR_NAMES)]


def tier_color(index: int) -> tuple[int, int, int]:
    return TIER_COLORS[min(index, len(TIER_COLORS) - 1)]


def tier_color_name(index: int) -> str:
    return TIER_COLOR_NAMES[min(index, len(TIER_COLOR_NAMES) - 1)]


def outline_width_ui(tier: np.ndarray) -> np.ndarray:
    """UI-point width of each survivor's tier outline, ``(K,)`` tier index -> ``(K,)``."""
    widths = np.array(OUTLINE_WIDTHS_UI)
    return widths[np.clip(tier, 0, widths.size - 1)]


def link_width_ui(index: int) -> float:
    return LINK_WIDTHS_UI[min(index, len(LINK_WIDTHS_UI) - 1)]


def risk_colors(survival: np.ndarray, floor: float) -> np.ndarray:
    """Red of each survivor, saturated by survival risk on a log scale (the paper's Fig. 3).

    ``survival``: ``(K,)`` survival risk R_S (unitless); ``floor``: the R_S drawn palest
    (the baseline threshold, 1e-25 by default). R_S spans some 25 decades between the
    baseline threshold and a near-certain collision, so only a log scale tells survivors
    apart; R_S >= 1 is fully saturated. NaN (no value) is drawn palest.
    Returns ``(K, 3)`` uint8 RGB.
    """
    lo = math.log10(floor) if floor > 0 else -25.0
    with np.errstate(divide="ignore", invalid="ignore"):
        level = (np.log10(survival) - lo) / (0.0 - lo)
    level = np.clip(np.nan_to_num(level, nan=0.0, neginf=0.0, posinf=1.0), 0.0, 1.0)
    low = np.array(RISK_LOW, dtype=np.float64)
    high = np.array(RISK_HIGH, dtype=np.float64)
    return np.rint(low + level[:, None] * (high - low)).astype(np.uint8)


def agent_series_colors(ids: np.ndarray) -> np.ndarray:
    """A stable, distinct colour per agent id for the risk timelines: ``(K,)`` -> ``(K, 3)``.

    Hues step by the golden angle so that neighbouring ids differ; the same agent has the
    same colour in every model's view.
    """
    hue = (np.asarray(ids, dtype=np.float64) * 0.618033988749895) % 1.0
    return _hsv_to_rgb(hue, 0.65, 0.95)


def _hsv_to_rgb(hue: np.ndarray, sat: float, val: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0])[None, :] + hue[:, None] * 6.0) % 6.0
    rgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.rint(rgb * 255.0).astype(np.uint8)


# ---------------------------------------------------------------------- shapes
def capsules(
    xy: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Agent bodies as filled capsules: one 2-point line strip per agent, radius = half width.

    A thick line with round caps covers an oriented ``length x width`` stadium when its
    segment is ``length - width`` long; a filled shape reads far better from above than a
    thin box outline, and it needs no per-agent rotation. Agents wider than long (or
    points) become discs. Shapes: ``(K, 2)``, ``(K,)`` x3 -> strips ``(K, 2, 2)`` m,
    radii ``(K,)`` m.
    """
    radius = np.maximum(width, 0.2) / 2.0  # a point-sized agent still shows
    half = np.maximum((length - 2.0 * radius) / 2.0, 1e-3)  # zero-length strips vanish
    forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * half[:, None]
    return np.stack([xy - forward, xy + forward], axis=1), radius


def outlines(
    xy: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray, margin_m: float
) -> np.ndarray:
    """Closed oriented rectangles around agents, ``margin_m`` outside the body.

    Shapes: ``(K, 2)``, ``(K,)`` x3 -> ``(K, 5, 2)`` m (first corner repeated to close).
    """
    half_l = np.maximum(length, 0.2) / 2.0 + margin_m
    half_w = np.maximum(width, 0.2) / 2.0 + margin_m
    corners = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0], [1.0, 1.0]])
    local = corners[None, :, :] * np.stack([half_l, half_w], axis=-1)[:, None, :]
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y], axis=-1) + xy[:, None, :]


def rings(xy: np.ndarray, length: np.ndarray, width: np.ndarray, margin_m: float) -> np.ndarray:
    """Circles around agents (the miss marker), ``margin_m`` outside the body's corners.

    A round marker stands apart from the rectangular tier outlines at any zoom.
    Shapes: ``(K, 2)``, ``(K,)`` x2 -> ``(K, 17, 2)`` m (closed).
    """
    radius = np.hypot(np.maximum(length, 0.2), np.maximum(width, 0.2)) / 2.0 + margin_m
    angle = np.linspace(0.0, 2.0 * math.pi, 17)
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    return xy[:, None, :] + radius[:, None, None] * unit[None, :, :]


def noses(xy: np.ndarray, heading: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Heading marks: a strip from the body centre to its front, ``(K, 2, 2)`` m."""
    front = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * (length / 2.0)[:, None]
    return np.stack([xy, xy + front], axis=1)


# ---------------------------------------------------------------------- view bounds
# Width / height of the scene view in the blueprint (3/5 of the width, 2.4/3.7 of the
# height of the viewport); on a 1920 x 1080 screen that is about 1150 x 640 pixels.
SCENE_ASPECT = 1.8


def scene_bounds(
    points: np.ndarray,
    anchor: np.ndarray | None = None,
    *,
    margin_m: float = 15.0,
    min_size_m: float = 60.0,
    max_size_m: float = 130.0,
    aspect: float = SCENE_ASPECT,
):
    """Visual bounds of the 2D view around ``points`` (``(K, 2)`` map metres).

    When the points spread wider than ``max_size_m``, the view keeps ``max_size_m``
    (or the ``anchor`` points' own extent, if larger) centred on the ``anchor`` (the ego's
    positions): a survivor 150 m down the road must not shrink the intersection to a dot.
    The box is widened to ``aspect`` (width / height of the scene view in the
    blueprint's layout) so that the viewer, which fits the x range to the view's width,
    crops nothing. Returns ``(x_range, y_range)`` in *view* coordinates (y flipped, see
    the module docstring), each at least ``min_size_m`` wide.
    """
    pts = _finite(points)
    lo, hi = pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m
    centre, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, min_size_m / 2.0)
    if anchor is not None and np.any(half > max_size_m / 2.0):
        a = _finite(anchor)
        a_lo, a_hi = a.min(axis=0) - margin_m, a.max(axis=0) + margin_m
        a_centre, a_half = (a_lo + a_hi) / 2.0, (a_hi - a_lo) / 2.0
        wide = half > max_size_m / 2.0
        centre = np.where(wide, a_centre, centre)
        half = np.where(wide, np.maximum(max_size_m / 2.0, a_half), half)
    half = np.array([max(half[0], aspect * half[1]), max(half[1], half[0] / aspect)])
    x_range = (float(centre[0] - half[0]), float(centre[0] + half[0]))
    y_range = (float(-centre[1] - half[1]), float(-centre[1] + half[1]))
    return x_range, y_range


def ego_bounds(
    ego_xy: np.ndarray,
    *,
    size_m: float = 120.0,
    margin_m: float = 20.0,
    aspect: float = SCENE_ASPECT,
):
    """Visual bounds that open the scene view on the ego: ``size_m`` wide around its drive.

    The box is centred on the ego's positions over the scene (``(K, 2)`` map metres), is
    ``size_m`` wide (``size_m / aspect`` tall), or larger when the ego's drive plus
    ``margin_m`` on each side needs more, and has the scene view's ``aspect``. Returns
    ``(x_range, y_range)`` in view coordinates (y flipped).
    """
    pts = _finite(ego_xy)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2.0
    need = (hi - lo) / 2.0 + margin_m
    half_x = max(size_m / 2.0, need[0], aspect * need[1])
    half_y = half_x / aspect
    x_range = (float(centre[0] - half_x), float(centre[0] + half_x))
    y_range = (float(-centre[1] - half_y), float(-centre[1] + half_y))
    return x_range, y_range


#: The ego view: this far behind the ego (m); ahead, its plans' reach (EGO_VIEW_AHEAD_M
#: at least, more on faster roads up to EGO_VIEW_MAX_AHEAD_M).
EGO_VIEW_BEHIND_M = 15.0
EGO_VIEW_AHEAD_M = 45.0
EGO_VIEW_MAX_AHEAD_M = 145.0
#: The ego view's width / height: a tall panel beside the scene view (the left column is
#: split between the two 2D views), so the ego drives up it, along its long side.
EGO_VIEW_ASPECT = 0.72


def ego_view_bounds(plan_reach_m: float, *, aspect: float = EGO_VIEW_ASPECT):
    """Visual bounds of the ego view in its frame (EGO_FRAME: the ego at 0, ahead is up,
    i.e. view y negative): from EGO_VIEW_BEHIND_M behind to ``plan_reach_m`` plus 10 m
    ahead (within EGO_VIEW_AHEAD_M .. EGO_VIEW_MAX_AHEAD_M), centred across. A 5 s plan
    then fills most of the view's height: at 10 m/s it is 50 m of a 75 m view."""
    ahead = min(max(plan_reach_m + 10.0, EGO_VIEW_AHEAD_M), EGO_VIEW_MAX_AHEAD_M)
    half_x = (ahead + EGO_VIEW_BEHIND_M) * aspect / 2.0
    return (-half_x, half_x), (-ahead, EGO_VIEW_BEHIND_M)


def ego_frame_matrices(heading_rad: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)``: the EGO_FRAME transforms' linear parts (the ego's frame in the
    scene's map coordinates) for headings ``(K,)``. A point of the ego's frame at ``(u,
    v)`` (view coordinates: u to the right, v down) lies at ``-v`` ahead and ``-u`` to the
    left of the ego: the turn by the heading times the swap ``[[0, -1], [-1, 0]]``."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    out = np.zeros((c.size, 3, 3))
    # R(heading) @ [[0, -1], [-1, 0]] = [[s, -c], [-c, -s]]
    out[:, 0, 0], out[:, 0, 1] = s, -c
    out[:, 1, 0], out[:, 1, 1] = -c, -s
    out[:, 2, 2] = 1.0
    return out


def _finite(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return pts if pts.size else np.zeros((1, 2))


# ---------------------------------------------------------------------- blueprint
def blueprint(
    *,
    model_names: Sequence[str],
    log10_ranges: dict[str, tuple[float, float]],
    stage_models: Sequence[str],
    active_model: str | None,
    bounds: tuple[tuple[float, float], tuple[float, float]],
    focus_agents: Sequence[int] = (),
    has_misses: bool = False,
    units: dict[str, str] | None = None,
    ego_view: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> rrb.Blueprint:
    """The layout that opens with the recording.

    Left (large): the scene from above; below it the funnel, false negatives and compute
    time. Right: one tab per model with the risk over time of the ``focus_agents`` (the
    agents that matter: tiers and misses; more can be added in the viewer;
    ``log10_ranges``: the models plotted as log10, with their y range), and below it the
    misses list (a text log: clicking a row selects the agent) and the summary.

    ``ego_view`` (bounds from :func:`ego_view_bounds`; given when the recording has
    plans): a second 2D view beside the scene that follows the ego (origin EGO_FRAME:
    the ego at 0, heading right), so that a 5 s plan is readable without zooming.
    """
    x_range, y_range = bounds
    scene = rrb.Spatial2DView(
        name="Scene (top-down, y north)",
        origin="/",
        contents=f"{SCENE}/**",
        background=BACKGROUND,
        visual_bounds=rrb.VisualBounds2D(x_range=x_range, y_range=y_range),
        # The agents' bodies (one entity each) take these; the map, the ego and the
        # paths log their own draw order.
        defaults=[rr.LineStrips2D.from_fields(draw_order=ORDER_AGENTS, show_labels=True)],
    )
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True)
    funnel = rrb.TimeSeriesView(name="Funnel: agents left", origin=FUNNEL, plot_legend=legend)
    missed = rrb.TimeSeriesView(
        name="False negatives per frame (up to stage k)", origin=FALSE_NEGATIVES, plot_legend=legend
    )
    timing = rrb.TimeSeriesView(name="Compute time (ms)", origin=TIMING, plot_legend=legend)
    risk_tabs = [
        _risk_view(
            m, log10_ranges.get(m), m in stage_models, (units or {}).get(m, ""), focus_agents
        )
        for m in model_names
    ]
    misses_view = rrb.TextLogView(name="Misses (click a row: select the agent)", origin=AGENTS)
    summary_view = rrb.TextDocumentView(name="Summary", origin=SUMMARY)
    active = (
        list(model_names).index(active_model)
        if active_model is not None and active_model in model_names
        else 0
    )
    top: rrb.Spatial2DView | rrb.Horizontal = scene
    if ego_view is not None:
        follow = rrb.Spatial2DView(
            name="Ego view (plans: white all agents, orange filtered)",
            origin=EGO_FRAME,
            contents=f"{SCENE}/**",
            background=BACKGROUND,
            visual_bounds=rrb.VisualBounds2D(x_range=ego_view[0], y_range=ego_view[1]),
            defaults=[rr.LineStrips2D.from_fields(draw_order=ORDER_AGENTS, show_labels=True)],
        )
        top = rrb.Horizontal(scene, follow, column_shares=[1.5, 1.0])
    left = rrb.Vertical(
        top, rrb.Horizontal(funnel, missed, timing), row_shares=[2.4, 1.3], name="Scene"
    )
    right = rrb.Vertical(
        rrb.Tabs(*risk_tabs, active_tab=active, name="Risk per agent"),
        rrb.Tabs(misses_view, summary_view, active_tab=0 if has_misses else 1),
        row_shares=[1.4, 1.0],
    )
    return rrb.Blueprint(
        rrb.Horizontal(left, right, column_shares=[3.0, 2.0]),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        collapse_panels=False,
    )


def _risk_view(
    model: str,
    log10_range: tuple[float, float] | None,
    is_stage: bool,
    unit: str,
    agents: Sequence[int],
) -> rrb.TimeSeriesView:
    """One model's tab: the risk over time of ``agents`` (log10 when a range is given)."""
    is_log = log10_range is not None
    contents = [f"+ {risk_path(model, int(a), log10=is_log)}" for a in agents]
    if is_stage:
        contents.append(f"+ {threshold_path(model, log10=is_log)}")
    title = model + (f" [{unit}]" if unit else "")
    if log10_range is not None:
        title = f"log10 {title}"
    if is_stage:
        title += " · stage"
    return rrb.TimeSeriesView(
        name=title,
        origin="/",
        contents=contents or ["- /**"],
        # A legend of the agents the tab opens on (at most FOCUS_AGENTS_MAX, named
        # "agent <id>") and the stage threshold: without one, a user could not tell
        # which line is which agent (issue 31).
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True),
        # Series without their own style (agents the cascade never kept) are quiet grey.
        defaults=[rr.SeriesLines(colors=QUIET_SERIES, widths=1.0)],
        axis_y=None if log10_range is None else rrb.ScalarAxis(range=log10_range),
    )
