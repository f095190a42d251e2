"""The report: report.md and its figures, built from whatever runs exist under OUT/runs/.

Every section is generated from the figure declarations (:mod:`medc_lab.figures`), in four steps:

- :mod:`.finder`: find the finished runs, their curves and summaries;
- :mod:`.reference_play`: play random moves and the classical controllers on the runs' own
  evaluation episodes (cached), and :mod:`.expert_eval` the experts on the reference episodes;
- :mod:`.judge`: the learnability gates and the claims' verdicts (:mod:`medc_training.stats`);
- :mod:`.markdown`: render the sections and the header; the prose is fixed wording around numbers and
  verdicts.

:mod:`.build` puts them together (:func:`build_report`); :mod:`.references`, :mod:`.sweep` and
:mod:`.posthoc` are the claims protocol's yardsticks, the sweep's section and the analysis after the
protocol.
"""

from .build import build_report

__all__ = ["build_report"]
