"""Actor and critic networks for TD3 / DDPG (paper section 2, Algorithm 3.1).

**[choice]** (abr-method.md: not given by the paper) both are 400-300 ReLU MLPs, as in the
TD3 paper. The state is the flattened 3 x 35 frame stack (105 inputs).

- ``Actor``: mu(s) = max_action * tanh(MLP(s)), one action per state.
- ``Critic``: ``num_q`` independent Q-heads Q_j(s, a) = MLP_j([s, a]) *fused* into one
  module: each layer's weights have shape (num_q, in, out) and all heads run in one
  batched matmul (``torch.baddbmm``) instead of ``num_q`` separate small GEMMs and module
  calls. ``num_q = 2`` is TD3's twin critic (eqs. 2.12-2.13), ``num_q = 1`` is DDPG's
  plain critic. Heads share no parameters; they are exactly ``num_q`` separate MLPs
  initialised like ``nn.Linear`` (U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and
  biases).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from bus.task import TASK

__all__ = ["Actor", "Critic", "TwinCritic", "SingleCritic", "mlp"]


def mlp(sizes: list[int], out_act: nn.Module | None = None) -> nn.Sequential:
    """Linear-ReLU stack with ``nn.Linear`` default initialisation."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    if out_act is not None:
        layers.append(out_act)
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy mu(s | theta^mu) = max_action * tanh(MLP(s))."""

    def __init__(
        self,
        state_dim: int = TASK.state_dim,
        action_dim: int = TASK.action_dim,
        hidden: tuple[int, ...] = (400, 300),
        max_action: float = TASK.max_action,
    ) -> None:
        super().__init__()
        self.net = mlp([state_dim, *hidden, action_dim], nn.Tanh())
        self.max_action = float(max_action)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.max_action * self.net(state)


class Critic(nn.Module):
    """``num_q`` Q-networks Q_j(s, a) evaluated together (fused batched layers).

    ``forward(s, a)`` returns all heads, shape (num_q, B, 1). ``q1(s, a)`` evaluates head 0
    only (TD3's actor loss uses Q_1); with ``detach_params=True`` no gradient flows into
    the critic's parameters, only into ``a``, which saves the weight-gradient work of
    the actor update.
    """

    def __init__(
        self,
        state_dim: int = TASK.state_dim,
        action_dim: int = TASK.action_dim,
        hidden: tuple[int, ...] = (400, 300),
        num_q: int = 2,
    ) -> None:
        super().__init__()
        self.num_q = int(num_q)
        self.state_dim = int(state_dim)
        sizes = [state_dim + action_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            bound = 1.0 / math.sqrt(fan_in)
            w = torch.empty(self.num_q, fan_in, fan_out).uniform_(-bound, bound)
            b = torch.empty(self.num_q, 1, fan_out).uniform_(-bound, bound)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([state, action], dim=-1)  # (B, in)
        x = x.unsqueeze(0).expand(self.num_q, -1, -1)  # (num_q, B, in), no copy
        n = len(self.weights)
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = torch.baddbmm(b, x, w)  # b + x @ w for every head at once
            if i < n - 1:
                x = torch.relu(x)
        return x  # (num_q, B, 1)

    def q1(
        self, state: torch.Tensor, action: torch.Tensor, detach_params: bool = False
    ) -> torch.Tensor:
        """Q_1(s, a), shape (B, 1). With ``detach_params`` gradients reach only ``action``:
        the first layer is split as s @ W_s + a @ W_a so that the backward pass skips the
        (B x h1 x state_dim) input-gradient GEMM for the state part."""
        w, b = self.weights[0][0], self.biases[0][0]
        if detach_params:
            w, b = w.detach(), b.detach()
            with torch.no_grad():
                pre = torch.addmm(b, state, w[: self.state_dim])
            x = torch.addmm(pre, action, w[self.state_dim :])
        else:
            x = torch.addmm(b, torch.cat([state, action], dim=-1), w)
        n = len(self.weights)
        for i in range(1, n):
            x = torch.relu(x)
            w, b = self.weights[i][0], self.biases[i][0]
            if detach_params:
                w, b = w.detach(), b.detach()
            x = torch.addmm(b, x, w)
        return x  # (B, 1)


def TwinCritic(
    state_dim: int = TASK.state_dim, action_dim: int = TASK.action_dim,
    hidden: tuple[int, ...] = (400, 300),
) -> Critic:
    """TD3's two critics Q_1, Q_2 in one fused module."""
    return Critic(state_dim, action_dim, hidden, num_q=2)


def SingleCritic(
    state_dim: int = TASK.state_dim, action_dim: int = TASK.action_dim,
    hidden: tuple[int, ...] = (400, 300),
) -> Critic:
    """DDPG's single critic (the same module with one head)."""
    return Critic(state_dim, action_dim, hidden, num_q=1)
