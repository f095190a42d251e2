"""FedAvg of parameters and the behavioural-cloning loss."""

import math

import pytest
import torch
from medc_training.fedavg import fedavg
from medc_training.losses import bc_loss, ppo_policy_loss


def test_fedavg_equal_weights_is_the_mean():
    a = {"w": torch.tensor([1.0, 2.0]), "b": torch.tensor(0.0)}
    b = {"w": torch.tensor([3.0, 6.0]), "b": torch.tensor(4.0)}
    out = fedavg([a, b])
    assert out["w"].tolist() == [2.0, 4.0] and out["b"].item() == 2.0


def test_fedavg_weighted_and_keeps_integer_buffers_from_first():
    a = {"w": torch.tensor([0.0]), "n": torch.tensor([7])}
    b = {"w": torch.tensor([10.0]), "n": torch.tensor([9])}
    out = fedavg([a, b], weights=[3, 1])
    assert out["w"].item() == pytest.approx(2.5)
    assert out["n"].item() == 7


def test_fedavg_rejects_mismatched_architectures():
    with pytest.raises(ValueError, match="one architecture"):
        fedavg([{"w": torch.zeros(2)}, {"v": torch.zeros(2)}])
    with pytest.raises(ValueError, match="shape"):
        fedavg([{"w": torch.zeros(2)}, {"w": torch.zeros(3)}])


def test_bc_loss_is_negative_log_probability_of_expert_action():
    logits = torch.tensor([[0.0, math.log(3.0)], [0.0, 0.0]])
    loss = bc_loss(logits, torch.tensor([1, 0]))
    assert loss.tolist() == pytest.approx([-math.log(0.75), -math.log(0.5)])


def test_bc_loss_gradient_raises_the_expert_action():
    logits = torch.zeros(1, 4, requires_grad=True)
    bc_loss(logits, torch.tensor([2])).sum().backward()
    assert logits.grad[0, 2] < 0 and (logits.grad[0, [0, 1, 3]] > 0).all()


def test_ppo_policy_loss_clips_the_ratio():
    old = torch.zeros(2)
    new = torch.log(torch.tensor([1.5, 0.5]))
    loss, _ = ppo_policy_loss(new, old, torch.tensor([1.0, -1.0]), clip=0.2)
    # positive advantage: min(1.5, 1.2) = 1.2; negative advantage: min(-0.5, -0.8) = -0.8
    assert loss.tolist() == pytest.approx([-1.2, 0.8])
