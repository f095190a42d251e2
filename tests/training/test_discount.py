"""The discount factor from the command line: ``medc-train --gamma`` reaches the run's config (and so
its manifest), the update discounts with it, and a value outside (0, 1] is refused by name."""

import pytest
import torch
from medc_training.cli.train import build_parser, config_from_args
from medc_training.config import TrainConfig
from medc_training.gae import compute_gae


def test_gamma_on_the_command_line_reaches_the_config_and_defaults_to_the_papers():
    given = config_from_args(build_parser().parse_args(["--out", "x", "--gamma", "0.95"]))
    default = config_from_args(build_parser().parse_args(["--out", "x"]))
    assert given.gamma == 0.95 and given.to_dict()["gamma"] == 0.95
    assert default.gamma == 0.99


@pytest.mark.parametrize("gamma", [0.0, -0.5, 1.5])
def test_a_discount_outside_the_unit_interval_is_refused(gamma):
    with pytest.raises(ValueError, match="gamma"):
        TrainConfig(gamma=gamma).validate()


def test_a_lower_discount_weighs_a_late_success_less():
    """One episode found at its fourth step, reward 1 there, a zero critic: the return of the first
    step is gamma**3, so the first move of a long search counts for less at a lower gamma."""
    rewards = torch.tensor([[0.0], [0.0], [0.0], [1.0]])
    zeros = torch.zeros_like(rewards)
    done = torch.tensor([[False], [False], [False], [True]])
    first = {g: compute_gae(rewards, zeros, zeros, done, torch.zeros_like(done), g, 1.0)[1][0, 0].item()
             for g in (0.99, 0.95)}
    assert first[0.99] == pytest.approx(0.99**3) and first[0.95] == pytest.approx(0.95**3)
