"""Scene sources that are not driving logs: simulators that produce :class:`~smart_marl.Scenario` s.

Stage: the first stage of the data flow, beside the readers (a traffic simulator -> Scenario).

* :mod:`smart_marl.sources.sumo`: scenes generated with the SUMO traffic simulator (optional extra
  ``smart-marl[sumo]``); ``generate_scenes`` and ``generate_to_dir``.

Nothing here is imported by ``smart_marl`` itself, so a missing simulator never breaks the package.
"""
