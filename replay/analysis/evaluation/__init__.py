"""``replay evaluate``: every model against the survival baseline and what really happened.

- :mod:`~replay.analysis.evaluation.streaming`: the evaluation ``replay evaluate`` runs,
  one scene's part file at a time (:func:`evaluate_parts`; :func:`evaluate_frame` for a
  table in memory), so that the driver never holds the corpus's rows (issue 38);
- :mod:`~replay.analysis.evaluation.corpus`: names, references, agreement, settings, and
  :func:`evaluate_table`, the same summary from every row at once with exact every-score
  ROC curves: the slow obvious oracle the tests compare the streamed one with;
- :mod:`~replay.analysis.evaluation.collect`: the agents an evaluation reads (the parts
  of a run, lazily; or in memory: :func:`collect_agents`, :func:`evaluate_inputs`);
- :mod:`~replay.analysis.evaluation.files`: ``summary.json``, tables, plots, the text;
- :mod:`~replay.analysis.evaluation.plots`, :mod:`~replay.analysis.evaluation.report`
  (the Markdown report), :mod:`~replay.analysis.evaluation.sensitivity` (the sweep);
- :mod:`~replay.analysis.evaluation.run`: the workflow (:func:`run_evaluation`).

The modules are imported by name (``from replay.analysis.evaluation.corpus import
...``): this package imports none of them, so a worker that replays scenes does not load
matplotlib or scipy.
"""
