"""Probes behind the observation and architecture choices: whether an observation carries the
oracle's answer (:mod:`.learnability`, supervised) and which observation MDRL-sparse learns from
(:mod:`.observation`)."""
