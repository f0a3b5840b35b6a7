"""Every corpus command's job engine: per-scene work on local processes or Ray, its
results streamed to files, resumable, failures listed (``docs/batch.md``).

- :mod:`~replay.jobs.scenes`: which files a command reads and the unique key of each;
- :mod:`~replay.jobs.runner`: :class:`Job` (a pure per-scene function and its settings'
  fingerprint), :func:`run_jobs` (plan, run, stream the parts, list the failures);
- :mod:`~replay.jobs.engines`: where the tasks run (:class:`Engine`, local processes,
  Ray);
- :mod:`~replay.jobs.failures`: ``failures.csv``.
"""

from replay.jobs.engines import ENGINES, RAY_MISSING, Engine, RayEngine, check_engine, make_engine
from replay.jobs.failures import Failure, read_failures
from replay.jobs.runner import Job, JobReport, SceneDone, SceneOutput, fingerprint, run_jobs
from replay.jobs.scenes import Inputs, SceneRef, resolve_inputs, scene_refs

__all__ = [
    "ENGINES",
    "RAY_MISSING",
    "Engine",
    "Failure",
    "Inputs",
    "Job",
    "JobReport",
    "RayEngine",
    "SceneDone",
    "SceneOutput",
    "SceneRef",
    "check_engine",
    "fingerprint",
    "make_engine",
    "read_failures",
    "resolve_inputs",
    "run_jobs",
    "scene_refs",
]
