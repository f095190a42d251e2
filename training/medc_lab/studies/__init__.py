"""Studies that stand beside the paper's experiments: the claims protocol's regime probes
(:mod:`.regimes`), the realistic-search study (:mod:`.realistic`) and the calibration of the team's
declarations (:mod:`.calibration`)."""
