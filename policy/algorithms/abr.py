"""Augmentative Backward Reward (ABR), paper section 3.3 and Algorithm 3.1.

Run once per episode that reached the goal, over its T transitions (1-based), from the
transitions' *base* rewards (eq. 3.5)::

    for k = 1 .. floor(T / p_frames):
        l     = k * p_frames
        tau_k = CNN(s_l)                                  p_features = 20 numbers
        zeta_k = max_j cos(tau_k, H_j)                    eqs. 3.3-3.4
        j     = new pattern (append tau_k to H) if H empty or zeta_k < p_similarity
                else argmax_j cos(tau_k, H_j)
        R_k   = floor(sum_{i = l - p_frames + 1 .. l} r_i)
        insert R_k into pattern j's set of distinct returns (sorted ascending)
        m     = 0-based position of R_k in that set
        r_i  += m * p_addReward        for i = l - p_frames + 1 .. l

Transitions after the last full group get no bonus. The goal transition keeps its base
reward: there is no +50 chunk in ABR.

Choices where the paper is silent or ambiguous (abr-method.md), marked **[choice]**:

- **[choice]** The CNN (paper Fig. 3.3): Conv1d over the frame axis with the 35
  attributes as channels (35 -> 32 filters, kernel 2) -> ReLU -> flatten (32 x 2 = 64)
  -> Linear(64 -> 20) -> ReLU. Its weights are drawn once from ``ABRConfig.seed`` (in
  training the run's seed, ``policy.training.train``) with PyTorch's default layer
  initialisation and never trained (the paper does not train it); they are saved in
  ``state_dict``.
- **[choice]** Similarity: eq. 3.4 / Algorithm 3.1 print a sum over the history; we use
  the maximum cosine similarity over stored patterns, and reuse the argmax pattern.
  Cosine similarity of two all-zero feature vectors (possible after the final ReLU) is
  taken as 1 (same "nothing" pattern) and of a zero and a non-zero vector as 0.
- **[choice]** The state fed to the CNN for group k is s_l, the state of transition l
  (the last ``p_frames`` observations up to o_l), as the algorithm writes it.
- **[choice]** R_k is the floor of the sum of *base* rewards (not of already-augmented
  ones), so rewriting an episode is idempotent and independent of the variant history.
- **[choice]** The bonus goes to every transition of a full group, including the goal
  transition when it closes a group ("all transitions in the episode will receive
  additional reward from ABR"); "keeps its base reward" means no goal chunk.
- The pattern history H and the per-pattern return sets persist across episodes for the
  whole run and are saved by ``state_dict``.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from bus.task import TASK
from policy.algorithms.rewards import GoalReward

__all__ = [
    "ABRConfig",
    "ABRGroup",
    "AugmentativeBackwardReward",
    "FeatureCNN",
    "cosine_similarity",
]


@dataclass
class ABRConfig:
    """ABR parameters (paper Table 4.1) and the CNN's shape and seed."""

    p_frames: int = TASK.frames
    p_attributes: int = TASK.obs_dim
    p_features: int = 20
    p_similarity: float = 0.98
    p_add_reward: float = 0.1
    conv_filters: int = 32
    conv_kernel: int = 2
    seed: int = 0  # [choice] seed of the untrained CNN's weights (training: the run's)


@dataclass
class ABRGroup:
    """What ABR did with one group of ``p_frames`` transitions (for logs and tests)."""

    k: int  # 1-based group index
    first: int  # 0-based index of the group's first transition in the episode
    pattern: int  # index j into H
    new_pattern: bool
    similarity: float  # zeta_k (nan when H was empty)
    ret: int  # R_k, floored sum of base rewards
    rank: int  # m, 0-based position of R_k in pattern j's set
    bonus: float  # m * p_addReward added to each transition of the group


class FeatureCNN(nn.Module):
    """Fig. 3.3's feature extractor: (N, p_frames, attributes) states -> (N, p_features)."""

    def __init__(self, config: ABRConfig) -> None:
        super().__init__()
        c = config
        width = c.p_frames - c.conv_kernel + 1
        with torch.random.fork_rng(devices=[]):  # seeded, without touching the global RNG
            torch.manual_seed(c.seed)
            self.conv = nn.Conv1d(c.p_attributes, c.conv_filters, c.conv_kernel)
            self.fc = nn.Linear(c.conv_filters * width, c.p_features)
        self.requires_grad_(False)

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        x = states.transpose(1, 2)  # (N, attributes, frames): attributes are channels
        x = torch.relu(self.conv(x))  # (N, filters, frames - kernel + 1)
        return torch.relu(self.fc(x.flatten(1)))


def cosine_similarity(
    tau: np.ndarray,
    patterns: np.ndarray,
    norms: np.ndarray | None = None,
    tau_norm: float | None = None,
) -> np.ndarray:
    """1 - cod(tau, H_j) of eq. 3.3 for every row of ``patterns`` (zero-vector rule above).

    ``norms`` / ``tau_norm`` are the rows' and tau's Euclidean norms when already known.
    """
    tau = np.asarray(tau)
    patterns = np.asarray(patterns).reshape(-1, tau.shape[0])
    nt = float(np.linalg.norm(tau)) if tau_norm is None else float(tau_norm)
    nh = np.linalg.norm(patterns, axis=1) if norms is None else np.asarray(norms)
    out = np.zeros(patterns.shape[0])
    both = (nh > 0) & (nt > 0)
    if both.all():
        out[:] = (patterns @ tau) / (nh * nt)
    elif both.any():
        out[both] = (patterns[both] @ tau) / (nh[both] * nt)
    if nt == 0:
        out[nh == 0] = 1.0
    return out


class AugmentativeBackwardReward(GoalReward):
    """ABR goal-reward variant; see the module docstring for the algorithm and choices."""

    name = "abr"
    needs_states = True

    def __init__(self, config: ABRConfig | None = None) -> None:
        self.config = config or ABRConfig()
        self.cnn = FeatureCNN(self.config)
        self.returns: list[list[int]] = []  # per pattern: sorted distinct R_k
        self.last_groups: list[ABRGroup] = []  # groups of the last goal episode
        self._set_patterns(np.zeros((0, self.config.p_features), np.float32))

    @property
    def patterns(self) -> np.ndarray:
        """H: the stored patterns, one row each (a view; grows by doubling, so appending
        stays amortised O(1) however long the run)."""
        return self._h[: self._n]

    def _set_patterns(self, patterns: np.ndarray) -> None:
        n = patterns.shape[0]
        self._h = np.zeros((max(64, 2 * n), self.config.p_features), np.float32)
        self._h[:n] = patterns
        self._norms = np.zeros(self._h.shape[0], np.float32)  # |H_j|, cached
        self._norms[:n] = np.linalg.norm(self._h[:n], axis=1)
        self._n = n

    # ------------------------------------------------------------------ pieces

    @torch.no_grad()
    def features(self, states: np.ndarray) -> np.ndarray:
        """tau for a batch of states (N, p_frames, attributes) -> (N, p_features)."""
        x = torch.as_tensor(np.asarray(states, np.float32))
        if x.ndim == 2:
            x = x.reshape(x.shape[0], self.config.p_frames, self.config.p_attributes)
        return self.cnn(x).numpy()

    def match(self, tau: np.ndarray) -> tuple[int, bool, float]:
        """Eqs. 3.3-3.4: (pattern index j, whether it is new, zeta). Appends to H if new."""
        tau = np.asarray(tau, np.float32).reshape(-1)
        nt = np.float32(np.linalg.norm(tau))
        n = self._n
        if n:
            sims = cosine_similarity(tau, self._h[:n], norms=self._norms[:n], tau_norm=nt)
            j = int(np.argmax(sims))
            zeta = float(sims[j])
            if zeta >= self.config.p_similarity:
                return j, False, zeta
        else:
            zeta = math.nan
        if n == self._h.shape[0]:
            self._h = np.concatenate([self._h, np.zeros_like(self._h)])
            self._norms = np.concatenate([self._norms, np.zeros_like(self._norms)])
        self._h[n] = tau
        self._norms[n] = nt
        self._n += 1
        self.returns.append([])
        return self._n - 1, True, zeta

    def rank(self, j: int, ret: int) -> int:
        """Insert R into pattern j's sorted set of distinct returns; m = its 0-based index."""
        s = self.returns[j]
        m = bisect.bisect_left(s, ret)
        if m == len(s) or s[m] != ret:
            s.insert(m, ret)
        return m

    # ------------------------------------------------------------------ variant

    def episode_rewards(
        self, base: np.ndarray, states: np.ndarray | None, reached_goal: bool
    ) -> np.ndarray:
        """Algorithm 3.1's goal branch: base rewards plus the ABR bonus per full group."""
        rewards = np.array(base, dtype=np.float64).reshape(-1)
        self.last_groups = []
        if not reached_goal:
            return rewards
        if states is None:
            raise ValueError("ABR needs the episode's states")
        p = self.config.p_frames
        n_groups = rewards.shape[0] // p
        if n_groups == 0:
            return rewards
        last = np.arange(1, n_groups + 1) * p - 1  # 0-based index of transition l
        taus = self.features(np.asarray(states)[last])
        base = rewards.copy()  # the group returns are of the base rewards
        for k in range(1, n_groups + 1):
            first = (k - 1) * p
            j, new, zeta = self.match(taus[k - 1])
            ret = math.floor(float(base[first : first + p].sum()))
            m = self.rank(j, ret)
            bonus = m * self.config.p_add_reward
            rewards[first : first + p] += bonus
            self.last_groups.append(ABRGroup(k, first, j, new, zeta, ret, m, bonus))
        return rewards

    # ------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """H, the return sets and the CNN weights (loads with ``weights_only=True``)."""
        return {
            "config": asdict(self.config),
            "patterns": torch.from_numpy(self.patterns.copy()),
            "returns": [list(s) for s in self.returns],
            "cnn": self.cnn.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.config = ABRConfig(**state["config"])
        self.cnn = FeatureCNN(self.config)
        self.cnn.load_state_dict(state["cnn"])
        self._set_patterns(state["patterns"].numpy().astype(np.float32))
        self.returns = [[int(r) for r in s] for s in state["returns"]]
        if len(self.returns) != len(self.patterns):
            raise ValueError("ABR state_dict: patterns and return sets differ in number")
