"""A planner in the loop: what filtering saves a real planner, and what it changes.

:mod:`replay.analysis.planner_eval.open_loop` plans every replayed frame with all agents and with
each filter's agents (and, for planner truth, without each agent in turn);
:mod:`replay.analysis.planner_eval.closed_loop` drives the ego with the planner while the others
replay their log; :mod:`replay.analysis.planner_eval.study` runs, summarises and writes
``replay plan``'s outputs.
"""
