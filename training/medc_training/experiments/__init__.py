"""The paper's experiments (Figs. 6-11, the supplements and the claims sweep), declared once.

- :mod:`.catalogue`: phases, budgets per scale, the experts and users the figures draw on.
- :mod:`.figures`: one declaration per figure, its runs and its claims.
- :mod:`.plan`: the jobs of a phase (and the experts' DAgger jobs), generated from the figures.
- :mod:`.jobs`: one job run atomically; :func:`.jobs.make_learner`, the learner of a config.
- :mod:`.engines`: a local process pool or Ray runs the jobs, skipping finished ones.
- :mod:`.report`: report.md, generated from the same figures; statistics from medc_training.stats.
- :mod:`.sweep_report`: the claims sweep's section (speed-ups, heat map, hypotheses H1-H3).
- :mod:`.posthoc`: the analysis a report adds after its protocol's verdicts (paired by seed, power,
  Holm, non-inferiority by its bound, censored speed-ups).
- :mod:`.reproduction`: a reproduction's phases run in order (``medc-reproduce``).
"""
