"""The actor-learner's settings (``skyloop learner``), numpy only.

The node is :mod:`policy.learner_node`, the command line :mod:`skyloop.learner_cli`.
Policy nodes started with ``skyloop policy --weights-from-bus`` fly the versions it
publishes, swapped in between episodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from policy.rewards import GOAL_REWARDS as REWARDS  # numpy only

ALGOS = ("td3", "ddpg")  # policy.agents.ALGOS (which imports torch)


@dataclass
class LearnerConfig:
    """What the learner learns from and how (see :mod:`policy.learner_node`)."""

    vehicles: list[str] = field(default_factory=lambda: ["*"])  # "*": every vehicle
    algo: str = "td3"
    reward: str = "abr"
    seed: int = 0
    updates_per_step: float = 1.0  # TD3 updates per new env step
    warmup: int = 1000  # transitions in the buffer before updates start [choice]
    critic_warmup: int = 1000  # first updates train the critic only [choice]
    publish_every: int = 1  # consumed episodes between two publishes
    checkpoint_every: int = 50  # consumed episodes between two checkpoints
    init_actor: str | None = "shipped"  # "shipped", "scratch" or an actor file
    buffer_size: int = 1_000_000
    max_episodes: int = 0  # stop after this many (0: until SIGINT/SIGTERM)
    grace_s: float = 2.0  # wait for an episode's late observations/commands
    queue_size: int = 100_000  # messages between the Zenoh callbacks and the main loop
    threads: int = 1  # torch threads
    resume: bool = False

    def validate(self) -> None:
        from bus.keys import check_vehicle

        if self.algo not in ALGOS:
            raise ValueError(f"unknown algorithm {self.algo!r}; choose from {ALGOS}")
        if self.reward not in REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; choose from {REWARDS}")
        for v in self.vehicles:
            check_vehicle(v, wildcard=True)
        if "*" in self.vehicles and len(self.vehicles) > 1:
            raise ValueError("--vehicles: '*' (every vehicle) or a list of names, not both")
        for name in ("publish_every", "checkpoint_every", "queue_size", "buffer_size",
                     "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
        if min(self.updates_per_step, self.warmup, self.critic_warmup, self.max_episodes,
               self.grace_s) < 0:
            raise ValueError("--updates-per-step, --warmup, --critic-warmup, --max-episodes "
                             "and --grace must be >= 0")
