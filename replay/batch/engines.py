"""The engines of ``replay batch``: :mod:`replay.jobs.engines` (every corpus command's)."""

from replay.jobs.engines import ENGINES, RAY_MISSING, Engine, RayEngine, check_engine, make_engine

__all__ = ["ENGINES", "RAY_MISSING", "Engine", "RayEngine", "check_engine", "make_engine"]
