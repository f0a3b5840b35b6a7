"""Writing outputs: what every layer above ``risk`` may import to write files.

- :mod:`outputs.atomic`: atomic file output (temp file beside the target, rename on
  success) and :func:`outputs.atomic.safe_name` for file names made from data;
- :mod:`outputs.sinks`: the types a replay hands to its outputs
  (:class:`~outputs.sinks.Sink`, :class:`~outputs.sinks.SceneInfo`,
  :class:`~outputs.sinks.FrameResult`);
- :mod:`outputs.transaction`: a command's outputs, all or nothing
  (:class:`~outputs.transaction.OutputGuard`);
- :mod:`outputs.process`: the output process, a second interpreter that writes outputs
  while the replay computes.

It is its own top-level package, not a module of ``replay``, so that ``converters`` and
``recordings`` can use it without importing the ``replay`` package, which imports them in
turn (see ``docs/architecture.md``). It imports only the standard library, numpy and
``risk``'s types.
"""
