"""The research harness: the paper's experiments, their report and the studies behind docs/reproduction.

It imports :mod:`medc_training` (the product) and is never imported by it (tests/test_layout.py).

- :mod:`.catalogue`: phases, budgets per scale, the experts and users the figures draw on.
- :mod:`.figures`: one declaration per figure, its runs and its claims.
- :mod:`.plan`: the jobs of a phase (and the experts' DAgger jobs), generated from the figures; the
  product's :mod:`medc_training.jobs` and :mod:`medc_training.engines` run them.
- :mod:`.reproduction`: a reproduction's phases run in order (``medc-reproduce``).
- :mod:`.report`: report.md, generated from the same figures (find runs, play references, judge,
  render), with the claims sweep's section and the analysis after the protocol.
- :mod:`.report_plots`: the report's figures.
- :mod:`.studies`: the regime probes, the realistic-search study and the declaration calibration.
- :mod:`.window`: the legacy window evaluator of the committed reproduction's runs, registered
  with the product's evaluation on import.
- :mod:`.cli`: the harness's entry points.
"""

from . import window  # noqa: F401  (registers the legacy window evaluator)
