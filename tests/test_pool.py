"""replay.core.pool.parallel_map: the ordered map of replay stats and replay experiment on the
project's one process pool (LocalEngine): order, errors, a dead worker, a reused pool."""

from __future__ import annotations

import os

import pytest

from replay.core.pool import LocalEngine, WorkerDied, chunks, parallel_map


def _square(x: int) -> int:
    return x * x


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("three")
    return x


def _die_on_three(x: int) -> int:
    if x == 3:
        os._exit(1)  # a crash in native code, as the pool sees it
    return x


def _threads(_: object) -> str | None:
    return os.environ.get("POLARS_MAX_THREADS")


def test_in_process_when_one_worker():
    assert parallel_map(_square, [3, 1, 2], workers=1, progress=False) == [9, 1, 4]
    assert parallel_map(_square, [], workers=1, progress=False) == []


def test_results_in_task_order_on_worker_processes():
    tasks = list(range(12))
    assert parallel_map(_square, tasks, workers=2, progress=False) == [x * x for x in tasks]


def test_workers_run_polars_single_threaded():
    assert parallel_map(_threads, [0, 1], workers=2, progress=False) == ["1", "1"]


def test_a_task_error_is_raised_in_the_driver():
    with pytest.raises(ValueError, match="three"):
        parallel_map(_fail_on_three, [1, 2, 3, 4], workers=2, progress=False)


def test_a_dead_worker_is_reported_and_a_reused_pool_goes_on():
    engine = LocalEngine(2)
    try:
        with pytest.raises(WorkerDied):
            parallel_map(_die_on_three, [1, 2, 3], workers=2, progress=False, engine=engine)
        assert engine.pending == 0
        assert parallel_map(_square, [4, 5], workers=2, progress=False, engine=engine) == [16, 25]
    finally:
        engine.close()


def test_chunks_cover_the_items_in_order():
    parts = chunks(list(range(23)), workers=2, per_worker=3)
    assert [x for p in parts for x in p] == list(range(23))
    assert len(parts) <= 6 and max(map(len, parts)) - min(map(len, parts)) <= 4
    assert chunks([], workers=2) == []
