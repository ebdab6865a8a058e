"""The two-thread TD3 update (policy.algorithms.pipeline): exactly the schedule its
docstring names, the worker's errors reach the caller, and the thread goes on close."""

from __future__ import annotations

import threading

import pytest
import torch

from policy.algorithms.ddpg import DDPG, DDPGConfig
from policy.algorithms.pipeline import TargetPipeline
from policy.algorithms.replay import Batch
from policy.algorithms.td3 import TD3, TD3Config

torch.set_num_threads(1)

TINY = dict(state_dim=6, action_dim=2, hidden=(16, 8), max_action=2.0, batch_size=8)


def _batches(n: int, seed: int = 0, state_dim: int = 6) -> list[Batch]:
    g = torch.Generator().manual_seed(seed)
    return [Batch(torch.randn(8, state_dim, generator=g),
                  torch.rand(8, 2, generator=g) * 4 - 2,
                  torch.randn(8, 1, generator=g),
                  torch.randn(8, state_dim, generator=g),
                  (torch.rand(8, 1, generator=g) < 0.2).float()) for _ in range(n)]


def _params(agent: TD3) -> list[torch.Tensor]:
    return [p.detach().clone() for net in (agent.actor, agent.critic, agent.actor_target,
                                           agent.critic_target) for p in net.parameters()]


def _reference(agent: TD3, batches: list[Batch], n: int) -> None:
    """The pipeline's schedule in one thread: y_{k+1} is computed before the soft update
    of step k (the gradient steps of k touch neither the targets nor the noise)."""
    y = agent.target(batches[0].next_state, batches[0].reward, batches[0].done)
    for k in range(n):
        nxt = batches[k + 1]
        y_next = agent.target(nxt.next_state, nxt.reward, nxt.done)
        agent.learn(batches[k], y)
        if agent.delayed_step():
            agent.update_targets()
        y = y_next


@pytest.mark.parametrize(("cls", "cfg_cls"), [(TD3, TD3Config), (DDPG, DDPGConfig)])
def test_the_pipeline_runs_its_documented_schedule_bit_for_bit(cls, cfg_cls):
    n = 12
    batches = _batches(n + 1)
    piped, ref = cls(cfg_cls(**TINY)), cls(cfg_cls(**TINY))
    it = iter(batches)
    with TargetPipeline(piped, lambda: next(it)) as pipe:
        losses = [pipe.update() for _ in range(n)]
    _reference(ref, batches, n)
    assert piped.updates == ref.updates == n
    for a, b in zip(_params(piped), _params(ref), strict=True):
        assert torch.equal(a, b)
    assert sum("actor_loss" in out for out in losses) == n // piped.config.policy_delay


def test_the_pipeline_lags_the_plain_update_by_one_soft_update():
    """What the docstring admits: the same batches through ``TD3.update`` end elsewhere
    (the targets of half the updates are one soft update older), though close."""
    n = 12
    batches = _batches(n + 1)
    piped, plain = TD3(TD3Config(**TINY)), TD3(TD3Config(**TINY))
    it = iter(batches)
    with TargetPipeline(piped, lambda: next(it)) as pipe:
        for _ in range(n):
            pipe.update()
    for b in batches[:n]:
        plain.update(b)
    diffs = [(a - b).abs().max().item()
             for a, b in zip(_params(piped), _params(plain), strict=True)]
    assert max(diffs) > 0
    assert max(diffs) < 1e-2


def test_a_failing_target_is_raised_in_the_caller_and_close_ends_the_thread():
    agent = TD3(TD3Config(**TINY))
    good = _batches(2)
    bad = _batches(1, state_dim=5)[0]  # the wrong state size: the target's matmul fails
    it = iter([good[0], bad, good[1]])
    pipe = TargetPipeline(agent, lambda: next(it))
    pipe.update()  # learns on good[0] while the worker fails on bad
    with pytest.raises(RuntimeError, match="shapes cannot be multiplied"):
        pipe.update()
    pipe.close()
    assert not any(t.name == "skyloop-td-target" for t in threading.enumerate())


def test_settle_keeps_the_next_target_and_the_state_readable():
    """A checkpoint in the middle (``settle`` then ``state_dict``) changes nothing."""
    n = 6
    batches = _batches(n + 1)
    a, b = TD3(TD3Config(**TINY)), TD3(TD3Config(**TINY))
    ia, ib = iter(batches), iter(batches)
    with TargetPipeline(a, lambda: next(ia)) as pa, TargetPipeline(b, lambda: next(ib)) as pb:
        for k in range(n):
            pa.update()
            pb.update()
            if k == 2:
                pa.settle()
                a.state_dict()
    for x, y in zip(_params(a), _params(b), strict=True):
        assert torch.equal(x, y)
