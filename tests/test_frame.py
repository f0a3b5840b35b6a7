"""Frame construction, validation and selection."""

from __future__ import annotations

import numpy as np
import pytest

from risk import Frame, FrameError, Kind


def two_agents(**overrides):
    args = dict(
        xy=np.array([[0.0, 0.0], [10.0, 0.0]]),
        heading=np.zeros(2),
        speed=np.array([5.0, 3.0]),
        length=np.array([4.5, 4.5]),
        width=np.array([1.8, 1.8]),
        paths=[np.array([[0.0, 0.0], [50.0, 0.0]]), np.array([[10.0, 0.0], [60.0, 0.0]])],
        ego=0,
    )
    args.update(overrides)
    return args


def test_from_arrays_builds_flat_paths_and_defaults():
    f = Frame.from_arrays(**two_agents())
    assert f.n_agents == 2
    assert f.paths.shape == (2, 2, 2)
    assert list(f.path_agent) == [0, 1]
    assert list(f.ids) == [0, 1]
    assert list(f.kinds) == [Kind.VEHICLE, Kind.VEHICLE]
    assert f.ego_id == 0
    assert list(f.others) == [False, True]


def test_candidates_and_padding_repeat_last_point():
    paths = [
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]),
        [np.array([[10.0, 0.0], [20.0, 0.0]]), np.array([[10.0, 0.0], [10.0, 5.0]])],
    ]
    f = Frame.from_arrays(**two_agents(paths=paths), kinds=["vehicle", "cyclist"], ids=[7, 9])
    assert f.paths.shape == (3, 3, 2)
    assert list(f.path_agent) == [0, 1, 1]
    assert list(f.path_points) == [3, 2, 2]
    np.testing.assert_array_equal(f.paths[1, 2], [20.0, 0.0])
    assert len(f.agent_paths(1)) == 2
    assert f.index_of(9) == 1


def test_arrays_are_read_only():
    f = Frame.from_arrays(**two_agents())
    with pytest.raises(ValueError):
        f.xy[0, 0] = 1.0


@pytest.mark.parametrize(
    ("override", "field", "agent"),
    [
        ({"xy": np.array([[0.0, 0.0], [np.nan, 0.0]])}, "xy", 1),
        ({"speed": np.array([5.0, np.inf])}, "speed", 1),
        ({"speed": np.array([-1.0, 0.0])}, "speed", 0),
        ({"length": np.array([4.5, -1.0])}, "length", 1),
        ({"width": np.array([4.5, np.nan])}, "width", 1),
        ({"heading": np.zeros(3)}, "heading", None),
        ({"ego": 2}, "ego", None),
        ({"paths": [np.zeros((1, 2)), np.zeros((0, 2))]}, "paths", 1),
        ({"paths": [np.zeros((1, 2)), np.array([[0.0, 0.0], [np.nan, 1.0]])]}, "paths", 1),
    ],
)
def test_validation_names_agent_and_field(override, field, agent):
    with pytest.raises(FrameError) as err:
        Frame.from_arrays(**two_agents(**override))
    assert err.value.field == field
    assert err.value.index == agent
    if agent is not None:
        assert f"agent #{agent}" in str(err.value)


def test_invalid_agents_are_not_validated_and_are_sanitised():
    f = Frame.from_arrays(
        **two_agents(xy=np.array([[0.0, 0.0], [np.nan, np.nan]]), speed=np.array([1.0, np.nan])),
        valid=[True, False],
    )
    assert np.isfinite(f.xy).all() and np.isfinite(f.speed).all()
    assert list(f.others) == [False, False]


def test_unknown_kind_and_duplicate_ids():
    with pytest.raises(FrameError, match="unknown kind"):
        Frame.from_arrays(**two_agents(), kinds=["vehicle", "tram"])
    with pytest.raises(FrameError, match="more than once"):
        Frame.from_arrays(**two_agents(), ids=[3, 3])


def test_select_keeps_ego_and_regroups_paths():
    paths = [np.zeros((1, 2)), [np.ones((2, 2)), 2 * np.ones((2, 2))], 3 * np.ones((1, 2))]
    f = Frame.from_arrays(
        xy=np.zeros((3, 2)),
        heading=np.zeros(3),
        speed=np.zeros(3),
        length=np.ones(3),
        width=np.ones(3),
        paths=paths,
        ego=1,
        ids=[10, 11, 12],
    )
    s = f.select([2, 1])
    assert list(s.ids) == [12, 11]
    assert s.ego == 1
    assert list(s.path_agent) == [0, 1, 1]
    np.testing.assert_array_equal(s.paths[0, 0], [3.0, 3.0])
    with pytest.raises(FrameError):
        f.select([0, 2])
