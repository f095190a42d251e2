"""Fleet coordination for autonomous vehicles (paper Section V-D).

Vehicles on an open G x G grid pick up waiting customers (at most ``capacity`` each) and drop them
at their destinations; the team is rewarded per pick-up, pays a time cost per step and gets a bonus
when the last customer is delivered. Each vehicle sees 6 maps (:data:`CHANNELS`); the oracle heads
for the nearest destination or pick-up cell. The world, moves, rewards and observation:
docs/environments.md, "Fleet coordination".
"""

from __future__ import annotations

from typing import Any

import torch

from medc_training.envs.core import (
    MapsObservationEnv,
    check_bool,
    check_core_options,
    check_int,
    maps_channels,
)
from medc_training.envs.descriptor import Application, register
from medc_training.envs.grid import ACTIONS, action_deltas, pad_blocked, random_free_cells
from medc_training.envs.names import FLEET_COORDINATION

__all__ = [
    "APPLICATION",
    "CHANNELS",
    "DELIVERY_BONUS",
    "PICKUP_REWARD",
    "TIME_COST",
    "FleetCoordination",
    "build_fleet_observations",
]

PICKUP_REWARD = 1.0
DELIVERY_BONUS = 10.0
TIME_COST = 0.1
CHANNELS: tuple[str, ...] = (
    "own_location",
    "team_locations",
    "waiting_pickups",
    "waiting_destinations",
    "own_passenger_destinations",
    "own_load",
)
WAITING, RIDING, DELIVERED = 0, 1, 2


def build_fleet_observations(
    positions: torch.Tensor,
    origin: torch.Tensor,
    destination: torch.Tensor,
    status: torch.Tensor,
    carrier: torch.Tensor,
    capacity: int,
    grid: int,
) -> torch.Tensor:
    """Every vehicle's 6-map observation, float32 [B,N,6,G,G] (channels: :data:`CHANNELS`).

    positions int64 [B,N,2]; origin, destination int64 [B,M,2]; status int64 [B,M]
    (0 waiting, 1 riding, 2 delivered); carrier int64 [B,M] (vehicle index, -1 if none).
    """
    b, n = positions.shape[:2]
    hw = grid * grid
    dev = positions.device
    cell = positions[..., 0] * grid + positions[..., 1]  # [B,N]
    o_cell = origin[..., 0] * grid + origin[..., 1]  # [B,M]
    d_cell = destination[..., 0] * grid + destination[..., 1]
    out = torch.zeros((b, n, len(CHANNELS), hw), dtype=torch.float32, device=dev)
    own = torch.zeros((b, n, hw), device=dev).scatter_(2, cell.unsqueeze(2), 1.0)
    occupied = own.sum(1, keepdim=True)
    out[:, :, 0] = own
    out[:, :, 1] = (occupied - own).clamp_(0.0, 1.0)
    waiting = (status == WAITING).float()
    out[:, :, 2] = (
        torch.zeros((b, hw), device=dev).scatter_add_(1, o_cell, waiting).clamp_(max=1.0).unsqueeze(1)
    )
    out[:, :, 3] = (
        torch.zeros((b, hw), device=dev).scatter_add_(1, d_cell, waiting).clamp_(max=1.0).unsqueeze(1)
    )
    mine = (status == RIDING).unsqueeze(1) & (
        carrier.unsqueeze(1) == torch.arange(n, device=dev).view(1, n, 1)
    )
    mine = mine.float()  # [B,N,M]
    own_dest = torch.zeros((b, n, hw), device=dev).scatter_add_(2, d_cell.unsqueeze(1).expand(b, n, -1), mine)
    out[:, :, 4] = own_dest.clamp_(max=1.0)
    out[:, :, 5] = (mine.sum(-1, keepdim=True) / capacity).clamp_(max=1.0)
    return out.view(b, n, len(CHANNELS), grid, grid)


class FleetCoordination(MapsObservationEnv):
    """Batched fleet coordination core (rules: module docstring).

    ``make_batched("fleet_coordination", num_envs=B, device="cpu", seed=0, agents=3,
    customers=8, capacity=2, grid=10, max_steps=100)``.
    """

    name = FLEET_COORDINATION
    CHANNELS = CHANNELS

    def __init__(
        self,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        agents: int = 3,
        customers: int = 8,
        capacity: int = 2,
        grid: int = 10,
        max_steps: int = 100,
        copy_obs: bool = True,
        observation: str = "maps",
    ) -> None:
        self.grid, self.num_agents, self.max_steps = check_core_options(
            grid, agents, max_steps, grid_range=(3, 64), max_agents=lambda g: min(16, g * g // 2)
        )
        self.num_customers = check_int(
            "customers", customers, 1, min(64, self.grid * self.grid - self.num_agents)
        )
        self.capacity = check_int("capacity", capacity, 1, self.num_customers)
        self.copy_obs = check_bool("copy_obs", copy_obs)
        super().__init__(num_envs, device, seed)
        self.num_actions = len(ACTIONS)
        self._set_observation(observation, len(self.CHANNELS))
        self._deltas = action_deltas(self.device)
        free = torch.zeros((self.num_envs, self.grid, self.grid), dtype=torch.bool, device=self.device)
        self.blocked_pad = pad_blocked(free)
        self._started = False

    @property
    def attributes(self) -> dict[str, Any]:
        return {
            "agents": self.num_agents,
            "customers": self.num_customers,
            "capacity": self.capacity,
            "grid": self.grid,
            "max_steps": self.max_steps,
        }

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        k = self.num_envs if rows is None else len(rows)
        g, n, m = self.grid, self.num_agents, self.num_customers
        free = torch.ones((k, g, g), dtype=torch.bool, device=self.device)
        cells = random_free_cells(free, n + m, self.generator)
        positions, origin = cells[:, :n], cells[:, n:]
        # Destination: uniform over the other G*G - 1 cells.
        o_flat = origin[..., 0] * g + origin[..., 1]
        d_flat = (torch.rand((k, m), generator=self.generator, device=self.device) * (g * g - 1)).long()
        d_flat = d_flat + (d_flat >= o_flat).long()
        destination = torch.stack((d_flat // g, d_flat % g), -1)
        status = torch.full((k, m), WAITING, dtype=torch.long, device=self.device)
        carrier = torch.full((k, m), -1, dtype=torch.long, device=self.device)
        if rows is None:
            self.positions, self.origin, self.destination = positions, origin, destination
            self.status, self.carrier = status, carrier
            self.t = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        else:
            self.positions[rows], self.origin[rows], self.destination[rows] = positions, origin, destination
            self.status[rows], self.carrier[rows] = status, carrier
            self.t[rows] = 0

    def _observe_maps(self) -> torch.Tensor:
        return build_fleet_observations(
            self.positions, self.origin, self.destination, self.status, self.carrier, self.capacity, self.grid
        )

    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.grid
        cell = self.positions[..., 0] * g + self.positions[..., 1]  # [B,N]
        o_cell = self.origin[..., 0] * g + self.origin[..., 1]
        d_cell = self.destination[..., 0] * g + self.destination[..., 1]
        riding = self.status == RIDING
        carrier_cell = cell.gather(1, self.carrier.clamp(min=0))
        self.status = torch.where(riding & (d_cell == carrier_cell), DELIVERED, self.status)
        picked = torch.zeros(self.num_envs, device=self.device)
        # Vehicles pick up in agent order, so two on one cell never take the same customer.
        for v in range(self.num_agents):
            load = ((self.status == RIDING) & (self.carrier == v)).sum(-1, keepdim=True)
            cand = (self.status == WAITING) & (o_cell == cell[:, v : v + 1])
            take = cand & (cand.long().cumsum(-1) <= self.capacity - load)
            self.status = torch.where(take, RIDING, self.status)
            self.carrier = torch.where(take, v, self.carrier)
            picked += take.sum(-1)
        success = (self.status == DELIVERED).all(-1)
        reward = PICKUP_REWARD * picked - TIME_COST + DELIVERY_BONUS * success.float()
        return reward, success

    def oracle_action_scores(self) -> torch.Tensor:
        """float32 [B,N,A]: minus the moves, after each action, to the vehicle's nearest goal."""
        b, n = self.positions.shape[:2]
        new = self.positions.unsqueeze(2) + self._deltas  # [B,N,A,2]
        load = (self.status == RIDING).unsqueeze(1) & (
            self.carrier.unsqueeze(1) == torch.arange(n, device=self.device).view(1, n, 1)
        )
        room = load.sum(-1, keepdim=True) < self.capacity  # [B,N,1]
        want_pick = (self.status == WAITING).unsqueeze(1) & room  # [B,N,M]
        goals = torch.cat((self.origin, self.destination), 1)  # [B,2M,2]
        wanted = torch.cat((want_pick, load), -1)  # [B,N,2M]
        cheb = (new.unsqueeze(3) - goals.view(b, 1, 1, -1, 2)).abs().amax(-1).float()  # [B,N,A,2M]
        cheb = cheb.masked_fill(~wanted.unsqueeze(2), float("inf")).amin(-1)
        cheb = torch.where(torch.isinf(cheb), 0.0, cheb)  # nothing to do: every move is as good
        return torch.where(self.mask, -cheb, float("-inf"))


APPLICATION = register(Application(name=FleetCoordination.name, core=FleetCoordination,
                                   default_observation="maps", channels=maps_channels(CHANNELS)))
