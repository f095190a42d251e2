"""The research harness: the paper's experiments, their report and the studies behind docs/reproduction.

It imports :mod:`medc_training` (the product) and is never imported by it (tests/test_layout.py).

- :mod:`.catalogue`: phases, budgets per scale, the experts and users the figures draw on.
- :mod:`.figures`: one declaration per figure, its runs and its claims.
- :mod:`.plan`: the jobs of a phase (and the experts' DAgger jobs), generated from the figures; the
  product's :mod:`medc_training.jobs` and :mod:`medc_training.engines` run them.
- :mod:`.reproduction`: a reproduction's phases run in order (``medc-reproduce``).
- :mod:`.report`: report.md, generated from the same figures; statistics from medc_training.stats.
- :mod:`.sweep_report`: the claims sweep's section (speed-ups, heat map, hypotheses H1-H3).
- :mod:`.posthoc`: the analysis a report adds after its protocol's verdicts (paired by seed, power,
  Holm, non-inferiority by its bound, censored speed-ups).
- :mod:`.studies`: the regime probes, the realistic-search study and the declaration calibration.
- :mod:`.cli`: the harness's entry points.
"""
