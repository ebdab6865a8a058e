"""DDPG (Lillicrap et al. 2015), the paper's baseline (section 2, eqs. 2.6-2.8).

Same networks, replay, exploration and checkpoint format as ``policy.algorithms.td3.TD3``, minus
TD3's three changes: one critic, no target policy smoothing, no delay::

    y_i = r_i + gamma (1 - d_i) Q'(s_{i+1}, mu'(s_{i+1}))         (target)
    L   = 1/N sum_i (y_i - Q(s_i, a_i))^2                         (critic)
    L_actor = -1/N sum_i Q(s_i, mu(s_i))                          (every step)
    theta' <- tau theta + (1 - tau) theta'                        (every step)

**[choice]** hyperparameters as TD3's (400-300, Adam 1e-3 for both, tau 0.005, batch
100), the "our DDPG" setting of the TD3 paper, so the comparison isolates the algorithm.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from policy.algorithms.td3 import TD3, TD3Config

__all__ = ["DDPGConfig", "DDPG"]


@dataclass
class DDPGConfig(TD3Config):
    """TD3Config with DDPG's schedule: ``policy_delay`` 1; the target-smoothing fields
    (``policy_noise``, ``noise_clip``) are unused."""

    policy_delay: int = 1


class DDPG(TD3):
    """Deep Deterministic Policy Gradient with a single critic (``Critic(num_q=1)``).

    ``update`` is TD3's with this ``target`` and ``policy_delay`` 1: critic step, then
    actor step and soft target updates on every call.
    """

    num_q = 1
    config_class = DDPGConfig

    def __init__(self, config: DDPGConfig | None = None,
                 device: str | torch.device = "cpu") -> None:
        super().__init__(config or DDPGConfig(), device)

    def target(self, next_state: torch.Tensor, reward: torch.Tensor,
               done: torch.Tensor) -> torch.Tensor:
        """y = r + gamma (1 - d) Q'(s', mu'(s')), no smoothing noise, one critic."""
        c = self.config
        with torch.no_grad():
            q_next = self.critic_target(next_state, self.actor_target(next_state))[0]
            return reward + c.gamma * (1.0 - done) * q_next
