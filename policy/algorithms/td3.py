"""TD3 (Fujimoto et al. 2018) as used by the paper (section 2, Algorithm 3.1).

Read top to bottom like CleanRL's ``td3_continuous_action.py``. One ``update`` is one
gradient step of Algorithm 3.1's inner loop on a sampled mini-batch
(s_i, a_i, r_i, s_{i+1}, d_i):

Target policy smoothing (eq. 2.11)::

    a'_i = clip(mu'(s_{i+1}) + clip(eps, -c, c), a_low, a_high),   eps ~ N(0, sigma)

Clipped double-Q target (eq. 2.12), d_i = 1 only for terminal transitions::

    y_i = r_i + gamma (1 - d_i) min_{j=1,2} Q'_j(s_{i+1}, a'_i)

Critic loss (eq. 2.13), both critics regress on the same y::

    L = sum_{j=1,2} 1/N sum_i (y_i - Q_j(s_i, a_i))^2

Every ``policy_delay`` (2) critic updates: deterministic policy gradient on Q_1 and soft
target updates::

    L_actor = -1/N sum_i Q_1(s_i, mu(s_i))
    theta' <- tau theta + (1 - tau) theta'       (actor and both critics, tau = 0.005)

Speed (``benchmarks/bench_td3.py``): both critics are one fused module
(``policy.algorithms.networks.Critic``), the target update is one ``torch._foreach_lerp_`` per
network, Adam runs its ``fused`` kernel, and the actor's gradient does not flow into the
critic weights. The update is GEMM-bound on CPU (about 355 MFLOP per update at 400-300,
batch 100). ``torch.compile`` was tried (default and max-autotune, losses only and the
whole critic step): at best +6 % for 10-60 s of compilation, so it is not used.

Precision (``TD3Config.precision``): ``"fp32"`` computes everything in float32 (bit-exact
with earlier versions). ``"bf16"`` is mixed precision (Micikevicius et al. 2018): the
forward and backward passes of the update run on bfloat16 copies of the networks
(``LowPrecisionCopy``), so their matmuls use the CPU's AMX / AVX512-BF16 units (or a
GPU's tensor cores) with float32 accumulation, while the losses, the float32 master
weights, Adam and the soft target updates stay in float32. Acting always uses the
float32 actor. ``best_precision`` says whether this machine has bfloat16 matmul units.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch
from torch import nn

from bus.task import TASK, TaskSpec
from policy.algorithms.networks import Actor, Critic
from policy.algorithms.replay import Batch

__all__ = ["TD3Config", "TD3", "FusedAdam", "LowPrecisionCopy", "PRECISIONS", "best_precision",
           "flush_denormals", "load_actor", "make_adam", "soft_update"]

ACTOR_FORMAT = "skyloop-actor-1"
# fields older checkpoints' agent configs hold, now the training loop's (TrainConfig)
LEGACY_CONFIG_KEYS = frozenset({"start_steps", "buffer_size"})
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}


@dataclass
class TD3Config:
    """TD3 hyperparameters (paper Table 4.1; **[choice]** entries from the TD3 paper).

    ``policy_noise`` (target smoothing sigma) and ``exploration_noise`` are absolute; left
    as None they become 0.2 * max_action and 0.1 * max_action **[choice]**. ``noise_clip``
    is the paper's target noise bound c = 0.5 (absolute).
    """

    state_dim: int = TASK.state_dim  # 3 frames x 35 attributes (bus.task)
    action_dim: int = TASK.action_dim  # l_x, l_y, l_z, a_z
    max_action: float = TASK.max_action  # actions in [-2, 2]
    hidden: tuple[int, ...] = (400, 300)  # [choice]
    gamma: float = 0.99
    tau: float = 0.005
    lr: float = 1e-3  # [choice] Adam, actor and critics
    policy_noise: float | None = None  # sigma of eq. 2.11 -> 0.2 * max_action
    noise_clip: float = 0.5  # c of eq. 2.11
    exploration_noise: float | None = None  # -> 0.1 * max_action
    policy_delay: int = 2
    batch_size: int = 100
    seed: int = 0
    precision: str = "fp32"  # "bf16": the update's matmuls in bfloat16 (module docstring)

    def __post_init__(self) -> None:
        self.hidden = tuple(int(h) for h in self.hidden)
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, "
                             f"got {self.precision!r}")
        if self.policy_noise is None:
            self.policy_noise = 0.2 * self.max_action
        if self.exploration_noise is None:
            self.exploration_noise = 0.1 * self.max_action


def explore(a: np.ndarray, rng: np.random.Generator, sigma: float,
            max_action: float) -> np.ndarray:
    """Exploration (Algorithm 3.1): clip(mu(s) + eps, -max_action, max_action), eps ~
    N(0, sigma), as float32; used by ``TD3.act`` and the collector process."""
    a = a + rng.normal(0.0, sigma, size=a.shape)
    return np.clip(a, -max_action, max_action).astype(np.float32)


class FusedAdam(torch.optim.Adam):
    """``torch.optim.Adam(fused=True)`` with its per-step bookkeeping done once.

    Adam's ``step`` spends more time regrouping its state lists by device and dtype than the
    fused kernel takes (about 0.5 ms against 0.2 ms a step for the critic, see
    ``benchmarks/bench_td3.py``). This keeps the lists after the first step and calls the
    same kernel with the same arguments, so the updates are bit-identical to torch's and
    the state dict is torch's own (checkpoints load either way). Anything unusual (a
    closure, several parameter groups, a parameter without a gradient) takes torch's path.
    """

    def __init__(self, params: Any, lr: float) -> None:
        super().__init__(params, lr=lr, fused=True)
        self._lists: tuple[list[torch.Tensor], ...] | None = None

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self._lists = None  # the state tensors were replaced

    @torch.no_grad()
    def step(self, closure: Any = None) -> Any:
        group = self.param_groups[0]
        params = group["params"]
        if (closure is not None or len(self.param_groups) != 1 or self._lists is None
                or any(p.grad is None for p in params)):
            out = super().step(closure)
            if all(p in self.state for p in params) and len(self.param_groups) == 1:
                self._lists = tuple([self.state[p][k] for p in params]
                                    for k in ("exp_avg", "exp_avg_sq", "step"))
            return out
        exp_avgs, exp_avg_sqs, steps = self._lists
        beta1, beta2 = group["betas"]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(params, [p.grad for p in params], exp_avgs, exp_avg_sqs, [], steps,
                           amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2,
                           weight_decay=group["weight_decay"], eps=group["eps"],
                           maximize=False, grad_scale=None, found_inf=None)
        return None


@contextmanager
def flush_denormals() -> Iterator[None]:
    """Treat float32 values below 1.2e-38 as zero in this thread (x86 FTZ/DAZ) while inside.

    Training needs it for speed, not accuracy: Adam's moment estimates of parameters
    whose gradient is zero (dead ReLU units) decay geometrically (m by 0.9 a step) into
    the denormal range after about a thousand updates, and x86 CPUs compute on denormals in
    microcode, tens of times slower. Measured in a TD3+ABR valley run (400-300, one thread):
    the fused Adam step took 1.9 ms instead of 0.3 ms, and the whole run went from 103 to
    159 env steps/s with this on. Values this small change no update that matters; runs
    stay deterministic. Applies to the calling thread only (``torch.set_num_threads(1)``).
    """
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def best_precision(device: str | torch.device = "cpu") -> str:
    """"bf16" where ``device`` multiplies bfloat16 matrices in hardware (a CPU with AMX or
    AVX512-BF16, a CUDA GPU with bfloat16 support), else "fp32"."""
    device = torch.device(device)
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    if device.type == "cpu":
        amx = getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()
        avx = getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)()
        return "bf16" if amx or avx else "fp32"
    return "fp32"


class LowPrecisionCopy:
    """The copy of ``module`` that an update computes with (mixed precision).

    ``module`` keeps the float32 master weights (what Adam, the soft target update,
    checkpoints and acting use). ``net()`` returns a copy in ``dtype``, refreshed from the
    master after ``changed()`` or when torch counted an in-place write to a master tensor
    (``Tensor._version``: ``load_state_dict`` from outside, say; the fused Adam kernel
    writes without counting, hence ``changed()``), and ``grads_to_master`` hands its
    gradients to the master's ``.grad`` in float32. With ``dtype`` float32 there is no
    copy: ``net()`` is ``module`` itself.
    """

    def __init__(self, module: nn.Module, dtype: torch.dtype) -> None:
        self.module = module
        self.master = list(module.parameters())
        self._net = module if dtype == torch.float32 else copy.deepcopy(module).to(dtype)
        self.params = list(self._net.parameters())
        self._seen: tuple[int, ...] = ()

    def net(self) -> nn.Module:
        if self._net is not self.module:
            versions = tuple(p._version for p in self.master)
            if versions != self._seen:
                with torch.no_grad():
                    torch._foreach_copy_(self.params, self.master)
                self._seen = versions
        return self._net

    def changed(self) -> None:
        """The master weights were written: the next ``net()`` copies them."""
        self._seen = ()

    def grads_to_master(self) -> None:
        if self._net is self.module:
            return
        for master, p in zip(self.master, self.params, strict=True):
            master.grad = None if p.grad is None else p.grad.float()
            p.grad = None


def make_adam(params: Any, lr: float) -> torch.optim.Adam:
    """Adam with the fused kernel (``FusedAdam``) when this torch has one, else foreach."""
    params = list(params)
    try:
        return FusedAdam(params, lr=lr)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, lr=lr, foreach=True)


@torch.no_grad()
def soft_update(target: list[torch.Tensor], source: list[torch.Tensor], tau: float) -> None:
    """theta' <- tau theta + (1 - tau) theta' for all parameters in one foreach call."""
    torch._foreach_lerp_(target, source, tau)


class TD3:
    """Twin Delayed DDPG agent: actor, fused twin critics, their targets and optimizers."""

    num_q = 2
    config_class: type[TD3Config] = TD3Config

    def __init__(self, config: TD3Config | None = None,
                 device: str | torch.device = "cpu") -> None:
        self.config = c = config or TD3Config()
        self.device = torch.device(device)
        with torch.random.fork_rng(devices=[]):  # seeded init, global RNG untouched
            torch.manual_seed(c.seed)
            self.actor = Actor(c.state_dim, c.action_dim, c.hidden, c.max_action)
            self.critic = Critic(c.state_dim, c.action_dim, c.hidden, num_q=self.num_q)
        # Algorithm 3.1: target networks start as copies, theta' = theta
        self.actor_target = Actor(c.state_dim, c.action_dim, c.hidden, c.max_action)
        self.critic_target = Critic(c.state_dim, c.action_dim, c.hidden, num_q=self.num_q)
        self.actor_target.load_state_dict(self.actor.state_dict())
        self.critic_target.load_state_dict(self.critic.state_dict())
        for p in (*self.actor_target.parameters(), *self.critic_target.parameters()):
            p.requires_grad_(False)
        for net in (self.actor, self.critic, self.actor_target, self.critic_target):
            net.to(self.device)  # initialised on the CPU: the same weights on any device
        self.actor_opt = make_adam(self.actor.parameters(), c.lr)
        self.critic_opt = make_adam(self.critic.parameters(), c.lr)
        self._pairs = [
            (list(self.actor_target.parameters()), list(self.actor.parameters())),
            (list(self.critic_target.parameters()), list(self.critic.parameters())),
        ]
        # what the update computes with: the networks themselves or bfloat16 copies
        self.dtype = PRECISIONS[c.precision]
        self.lp = {name: LowPrecisionCopy(getattr(self, name), self.dtype)
                   for name in ("actor", "critic", "actor_target", "critic_target")}
        self.noise_gen = torch.Generator().manual_seed(c.seed + 1)  # target smoothing
        self.rng = np.random.default_rng(c.seed + 2)  # act()'s noise when given no rng
        self.updates = 0
        # the skyloop task this agent learns (bus.task.TaskSpec.to_dict()) and how its
        # observations are made (perception.observation.scaling_fields), recorded in its
        # actor files; None for other tasks (Gymnasium env ids)
        self.task: dict[str, Any] | None = None
        self.observation: dict[str, Any] | None = None

    # ------------------------------------------------------------------ acting

    @torch.no_grad()
    def act(
        self, state: np.ndarray, noise: bool, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """a = clip(mu(s) + eps, a_low, a_high), eps ~ N(0, exploration_noise) if ``noise``.

        ``state`` is one (3, 35) / (105,) state or a batch of them; returns float32 actions
        of shape (4,) or (N, 4). ``rng`` draws the noise instead of the agent's own
        generator (``self.rng``, saved in ``state_dict``).
        """
        c = self.config
        x = torch.as_tensor(np.asarray(state, dtype=np.float32))
        single = x.numel() == c.state_dim
        a = self.actor(x.reshape(-1, c.state_dim).to(self.device)).cpu().numpy()
        if noise:
            a = explore(a, rng or self.rng, c.exploration_noise, c.max_action)
        a = a.astype(np.float32, copy=False)
        return a[0] if single else a

    # ------------------------------------------------------------------ learning

    def target(self, next_state: torch.Tensor, reward: torch.Tensor,
               done: torch.Tensor) -> torch.Tensor:
        """y of eq. 2.12 with the smoothed target action of eq. 2.11 (no gradient)."""
        c, dt = self.config, self.dtype
        with torch.no_grad():
            next_state = next_state.to(dt)
            mu_next = self.lp["actor_target"].net()(next_state).float()
            eps = torch.randn(mu_next.shape, generator=self.noise_gen).to(self.device)
            eps = eps * c.policy_noise
            eps = eps.clamp(-c.noise_clip, c.noise_clip)  # clip(eps, -c, c)
            next_action = (mu_next + eps).clamp(-c.max_action, c.max_action)  # eq. 2.11
            q_next = self.lp["critic_target"].net()(next_state, next_action.to(dt))  # (2,B,1)
            min_q = q_next.min(dim=0).values.float()  # min_j Q'_j
            return reward + c.gamma * (1.0 - done) * min_q  # eq. 2.12

    def _critic_loss(self, state: torch.Tensor, action: torch.Tensor,
                           y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        q = self.lp["critic"].net()(state, action.to(self.dtype)).float()  # (2, B, 1)
        per_q = (q - y.unsqueeze(0)).pow(2).mean(dim=(1, 2))  # eq. 2.13, one MSE per critic
        return per_q.sum(), q.detach()

    def _actor_loss(self, state: torch.Tensor) -> torch.Tensor:
        # deterministic policy gradient through Q_1 only; critic weights get no gradient.
        action = self.lp["actor"].net()(state)
        return -self.lp["critic"].net().q1(state, action, detach_params=True).float().mean()

    def actor_step(self, state: torch.Tensor) -> float:
        """One actor step on the deterministic policy gradient through Q_1; returns the
        loss."""
        actor_loss = self._actor_loss(state)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.lp["actor"].grads_to_master()
        self.actor_opt.step()
        self.lp["actor"].changed()
        return actor_loss.item()

    def update(self, batch: Batch, train_actor: bool = True) -> dict[str, float]:
        """One gradient step of Algorithm 3.1 on ``batch``; returns the losses.

        ``actor_loss`` is reported only on delayed (actor) steps. ``train_actor=False``
        steps the critics (and the target updates) only: the actor stays as it is (a
        learner warming a fresh critic up under a trained actor). The three parts, in
        order: ``target`` (y, eq. 2.12), ``learn`` (critic and delayed actor steps) and, on
        delayed steps, ``update_targets`` (``policy.algorithms.pipeline`` runs the first
        in a second thread).
        """
        batch = self.to_device(batch)
        y = self.target(batch.next_state, batch.reward, batch.done)
        out = self.learn(batch, y, train_actor)
        if self.delayed_step():
            self.update_targets()
        return out

    def to_device(self, batch: Batch) -> Batch:
        """``batch`` on the learner's device (as it is on the CPU)."""
        if self.device.type == "cpu":
            return batch
        return Batch(*(t.to(self.device, non_blocking=True) for t in batch))

    def delayed_step(self) -> bool:
        """Whether the last ``learn`` was a delayed step (actor and target updates)."""
        return self.updates % self.config.policy_delay == 0

    def learn(self, batch: Batch, y: torch.Tensor, train_actor: bool = True
              ) -> dict[str, float]:
        """The gradient steps of one update given its TD target ``y``: the critics on
        eq. 2.13, then, every ``policy_delay`` calls and if ``train_actor``, the actor on
        the deterministic policy gradient through Q_1. Counts the update; does not touch
        the target networks (``update_targets``)."""
        self.updates += 1
        state = batch.state.to(self.dtype)  # no copy in float32

        critic_loss, q = self._critic_loss(state, batch.action, y)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.lp["critic"].grads_to_master()
        self.critic_opt.step()
        self.lp["critic"].changed()
        out = {"critic_loss": critic_loss.item(), "q1": q[0].mean().item()}

        if self.delayed_step() and train_actor:  # delayed policy update
            out["actor_loss"] = self.actor_step(state)
        return out

    def update_targets(self) -> None:
        """theta' <- tau theta + (1 - tau) theta' for the actor and both critics."""
        for target, source in self._pairs:
            soft_update(target, source, self.config.tau)
        self.lp["actor_target"].changed()
        self.lp["critic_target"].changed()

    # ------------------------------------------------------------------ checkpoints

    def save_actor(self, path: str | Path | BinaryIO) -> None:
        """Write the actor alone (what a deployed policy needs); read with ``load_actor``
        (a path, or a binary file object such as ``io.BytesIO``)."""
        c = self.config
        state = {
            "format": ACTOR_FORMAT,
            "config": {"state_dim": c.state_dim, "action_dim": c.action_dim,
                       "hidden": list(c.hidden), "max_action": c.max_action},
            "actor": self.actor.state_dict(),
        }
        if self.task is not None:
            state["task"] = dict(self.task)
        if self.observation is not None:
            state["observation"] = dict(self.observation)
        torch.save(state, path)

    def state_dict(self) -> dict[str, Any]:
        """Networks, targets, optimizers, counters and RNG states (``weights_only`` safe)."""
        cfg = asdict(self.config)
        cfg["hidden"] = list(cfg["hidden"])
        return {
            "config": cfg,
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "noise_gen": self.noise_gen.get_state(),
            "rng": _rng_state(self.rng),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> TD3:
        """Rebuild an agent (with its saved config) from ``state_dict()``."""
        config = {k: v for k, v in state["config"].items() if k not in LEGACY_CONFIG_KEYS}
        agent = cls(cls.config_class(**config))
        agent.load_state_dict(state)
        return agent

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("actor", "critic", "actor_target", "critic_target"):
            module: nn.Module = getattr(self, name)
            module.load_state_dict(state[name])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.noise_gen.set_state(state["noise_gen"])
        self.rng.bit_generator.state = _rng_from(state["rng"])
        for copy_ in self.lp.values():
            copy_.changed()


#: TaskSpec fields that shape what an actor reads and writes: an actor trained with other
#: values cannot fly this task (the episode limits may differ: they change no input)
TASK_IO_FIELDS = ("frames", "faces", "action_dim", "max_action")


def load_actor(path: str | Path | BinaryIO, task: TaskSpec | None = None) -> Actor:
    """Read an actor written by ``TD3.save_actor`` (eval mode, no gradients).

    With ``task``, an actor file that records the task it was trained for must match it
    in ``TASK_IO_FIELDS`` (ValueError naming the file and the field); files from before
    the task was recorded are taken as they are. The recorded task is the returned
    actor's ``trained_task`` (None when not recorded).
    """
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != ACTOR_FORMAT:
        raise ValueError(f"{path}: not a skyloop actor file")
    trained = TaskSpec.from_dict(state["task"], where=str(path)) if "task" in state else None
    if task is not None and trained is not None:
        for name in TASK_IO_FIELDS:
            if getattr(trained, name) != getattr(task, name):
                raise ValueError(f"{path}: trained for task {name}={getattr(trained, name)}"
                                 f", but this task has {name}={getattr(task, name)}")
    c = state["config"]
    actor = Actor(c["state_dim"], c["action_dim"], tuple(c["hidden"]), c["max_action"])
    try:
        actor.load_state_dict(state["actor"])
    except RuntimeError as exc:  # torch's message spans lines; keep the first mismatch
        detail = next((line.strip() for line in str(exc).splitlines()
                       if "size mismatch" in line or "Missing" in line
                       or "Unexpected" in line), str(exc).splitlines()[0])
        raise ValueError(f"{path}: its weights do not fit the {c['state_dim']}-"
                         f"{'-'.join(map(str, c['hidden']))}-{c['action_dim']} actor its "
                         f"config names ({detail})") from None
    actor.eval().requires_grad_(False)
    actor.trained_task = trained  # what it was trained under (None: not recorded)
    # how its observations were made (perception.observation.scaling_fields; None: not
    # recorded, i.e. the default ObservationConfig at the task's radius)
    actor.trained_observation = state.get("observation")
    return actor


def _rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """numpy PCG64 state as strings (big ints do not pass ``torch.load(weights_only)``)."""
    s = rng.bit_generator.state
    return {
        "bit_generator": s["bit_generator"],
        "state": str(s["state"]["state"]),
        "inc": str(s["state"]["inc"]),
        "has_uint32": int(s["has_uint32"]),
        "uinteger": int(s["uinteger"]),
    }


def _rng_from(d: dict[str, Any]) -> dict[str, Any]:
    return {
        "bit_generator": d["bit_generator"],
        "state": {"state": int(d["state"]), "inc": int(d["inc"])},
        "has_uint32": int(d["has_uint32"]),
        "uinteger": int(d["uinteger"]),
    }
