"""TD3 / DDPG: target (eqs. 2.11-2.12) against a hand computation, critic loss (2.13),
delayed updates, learning a 1-step task, checkpoints."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from policy.algorithms.ddpg import DDPG, DDPGConfig
from policy.algorithms.networks import Actor, Critic
from policy.algorithms.replay import Batch, ReplayBuffer
from policy.algorithms.td3 import TD3, TD3Config, load_actor

torch.set_num_threads(1)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().numpy()


def _actor_np(actor: Actor, s: np.ndarray) -> np.ndarray:
    lin = [m for m in actor.net if isinstance(m, torch.nn.Linear)]
    x = s
    for i, m in enumerate(lin):
        x = x @ _np(m.weight).T + _np(m.bias)
        if i < len(lin) - 1:
            x = np.maximum(x, 0)
    return actor.max_action * np.tanh(x)


def _critic_np(critic: Critic, s: np.ndarray, a: np.ndarray, head: int) -> np.ndarray:
    x = np.concatenate([s, a], axis=1)
    n = len(critic.weights)
    for i in range(n):
        x = x @ _np(critic.weights[i])[head] + _np(critic.biases[i])[head]
        if i < n - 1:
            x = np.maximum(x, 0)
    return x


TINY = dict(state_dim=3, action_dim=2, hidden=(5, 4), max_action=2.0)


def _batch(n=6, seed=0, state_dim=3, action_dim=2) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(
        torch.randn(n, state_dim, generator=g),
        torch.rand(n, action_dim, generator=g) * 4 - 2,
        torch.randn(n, 1, generator=g),
        torch.randn(n, state_dim, generator=g),
        (torch.rand(n, 1, generator=g) < 0.5).float(),
    )


def test_config_defaults():
    c = TD3Config()
    assert (c.gamma, c.tau, c.noise_clip, c.batch_size, c.lr) == (0.99, 0.005, 0.5, 100, 1e-3)
    assert c.policy_noise == pytest.approx(0.4) and c.exploration_noise == pytest.approx(0.2)
    assert (c.hidden, c.max_action, c.state_dim, c.action_dim) == ((400, 300), 2.0, 105, 4)
    assert c.policy_delay == 2


def test_an_agent_saved_with_the_old_training_fields_loads():
    """Checkpoints before the agent's config dropped start_steps and buffer_size (the
    training loop's, TrainConfig) hold them in their config: they still load."""
    agent = TD3(TD3Config(**TINY, seed=3))
    state = agent.state_dict()
    state["config"] = {**state["config"], "start_steps": 10_000, "buffer_size": 1_000_000}
    restored = TD3.from_state_dict(state)
    for a, b in zip(agent.actor.parameters(), restored.actor.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("policy_noise", [0.2, 5.0])  # 5.0: noise and action clips active
def test_td3_target_matches_hand_computation(policy_noise):
    agent = TD3(TD3Config(**TINY, policy_noise=policy_noise, seed=3))
    # make the targets differ from the online networks
    with torch.no_grad():
        for p in (*agent.actor_target.parameters(), *agent.critic_target.parameters()):
            p.add_(torch.randn(p.shape) * 0.3)
    b = _batch()
    gen_state = agent.noise_gen.get_state()
    y = agent.target(b.next_state, b.reward, b.done)

    eps = torch.randn((6, 2), generator=torch.Generator().set_state(gen_state)).double().numpy()
    s2, r, d = _np(b.next_state), _np(b.reward), _np(b.done)
    mu = _actor_np(agent.actor_target, s2)
    a2 = np.clip(mu + np.clip(eps * policy_noise, -0.5, 0.5), -2.0, 2.0)  # eq. 2.11
    if policy_noise > 1:
        assert np.any(np.abs(eps * policy_noise) > 0.5)
    q1 = _critic_np(agent.critic_target, s2, a2, 0)
    q2 = _critic_np(agent.critic_target, s2, a2, 1)
    assert not np.allclose(q1, q2)
    expected = r + 0.99 * (1 - d) * np.minimum(q1, q2)  # eq. 2.12
    np.testing.assert_allclose(_np(y), expected, rtol=1e-5, atol=1e-5)


def test_ddpg_target_matches_hand_computation():
    agent = DDPG(DDPGConfig(**TINY, seed=1))
    b = _batch(seed=2)
    y = agent.target(b.next_state, b.reward, b.done)
    s2 = _np(b.next_state)
    q = _critic_np(agent.critic_target, s2, _actor_np(agent.actor_target, s2), 0)
    np.testing.assert_allclose(_np(y), _np(b.reward) + 0.99 * (1 - _np(b.done)) * q, rtol=1e-5,
                               atol=1e-5)
    assert agent.critic.num_q == 1


def test_fused_critic_equals_separate_heads_and_loss():
    agent = TD3(TD3Config(**TINY))
    b = _batch()
    y = torch.randn(6, 1)
    loss, q = agent._critic_loss(b.state, b.action, y)
    s, a = _np(b.state), _np(b.action)
    q1, q2 = _critic_np(agent.critic, s, a, 0), _critic_np(agent.critic, s, a, 1)
    np.testing.assert_allclose(_np(q[0]), q1, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_np(q[1]), q2, rtol=1e-5, atol=1e-6)
    yy = _np(y)
    expected = np.mean((yy - q1) ** 2) + np.mean((yy - q2) ** 2)  # eq. 2.13
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    torch.testing.assert_close(agent.critic.q1(b.state, b.action), q[0])


def test_delayed_actor_and_soft_target_updates():
    agent = TD3(TD3Config(**TINY))
    b = _batch()
    snap = lambda m: [p.detach().clone() for p in m.parameters()]  # noqa: E731
    actor0, critic0, at0, ct0 = (snap(agent.actor), snap(agent.critic),
                                 snap(agent.actor_target), snap(agent.critic_target))
    out = agent.update(b)  # step 1: critic only
    assert "actor_loss" not in out
    assert all(torch.equal(x, y) for x, y in zip(actor0, snap(agent.actor), strict=True))
    assert not all(torch.equal(x, y) for x, y in zip(critic0, snap(agent.critic), strict=True))
    assert all(torch.equal(x, y) for x, y in zip(ct0, snap(agent.critic_target), strict=True))
    out = agent.update(b)  # step 2: actor and targets
    assert "actor_loss" in out
    assert not all(torch.equal(x, y) for x, y in zip(actor0, snap(agent.actor), strict=True))
    for old, new, src in zip(at0 + ct0, snap(agent.actor_target) + snap(agent.critic_target),
                             snap(agent.actor) + snap(agent.critic), strict=True):
        torch.testing.assert_close(new, 0.995 * old + 0.005 * src)


def test_act_shapes_bounds_and_noise():
    agent = TD3(TD3Config())
    s = np.random.default_rng(0).normal(size=(3, 35)).astype(np.float32)
    a = agent.act(s, noise=False)
    assert a.shape == (4,) and a.dtype == np.float32 and np.all(np.abs(a) <= 2.0)
    np.testing.assert_array_equal(a, agent.act(s.reshape(-1), noise=False))
    assert agent.act(np.stack([s, s]), noise=False).shape == (2, 4)
    assert not np.array_equal(a, agent.act(s, noise=True))


def _one_step_task(agent_cls, config_cls, updates: int, seed: int = 0,
                   precision: str = "fp32") -> float:
    """Bandit: any state, reward = -sum|a - target|, every transition terminal."""
    target = np.array([0.5, -1.0, 1.0, 0.0], np.float32)
    cfg = config_cls(state_dim=6, action_dim=4, hidden=(64, 64), seed=seed, batch_size=100,
                     precision=precision)
    agent = agent_cls(cfg)
    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(capacity=5000, state_shape=(1, 6), action_dim=4, seed=seed)
    for _ in range(3000):  # one-step episodes of one-frame states
        s = rng.normal(size=(1, 6)).astype(np.float32)
        a = rng.uniform(-2, 2, 4).astype(np.float32)
        buf.add(s, a, -float(np.abs(a - target).sum()), s, terminal=True)
        buf.end_episode()
    for _ in range(updates):
        agent.update(buf.sample(cfg.batch_size))
    states = rng.normal(size=(50, 6)).astype(np.float32)
    return float(np.abs(agent.act(states, noise=False) - target).mean())


# a random policy is ~1.0 off per dimension, the zero action 0.625
def test_td3_learns_one_step_task():
    assert _one_step_task(TD3, TD3Config, updates=600) < 0.3


def test_ddpg_learns_one_step_task():
    assert _one_step_task(DDPG, DDPGConfig, updates=600) < 0.3


@pytest.mark.parametrize("cls,cfg_cls", [(TD3, TD3Config), (DDPG, DDPGConfig)])
def test_mixed_precision_learns_one_step_task(cls, cfg_cls):
    assert _one_step_task(cls, cfg_cls, updates=600, precision="bf16") < 0.3


def test_mixed_precision_gradients_follow_fp32_and_masters_stay_fp32():
    """bf16: from the same weights and batch, the critic's and the actor's gradients point
    where the float32 ones do (bfloat16 keeps ~3 significant digits); masters, targets and
    Adam stay float32, and the copies the update computes with follow every change of the
    masters (optimizer steps, soft updates, a load from outside)."""
    cfg = dict(state_dim=105, action_dim=4, hidden=(64, 48), seed=3)
    ref, mixed = TD3(TD3Config(**cfg)), TD3(TD3Config(**cfg, precision="bf16"))
    b = _batch(n=64, seed=0, state_dim=105, action_dim=4)
    y = ref.target(b.next_state, b.reward, b.done)
    y_mixed = mixed.target(b.next_state, b.reward, b.done)
    assert y_mixed.dtype == torch.float32 and torch.allclose(y_mixed, y, rtol=0.05, atol=0.02)

    def grads(agent, loss) -> torch.Tensor:
        loss.backward()
        if agent is mixed:
            for name in ("critic", "actor"):
                agent.lp[name].grads_to_master()
        params = [*agent.critic.parameters(), *agent.actor.parameters()]
        g = torch.cat([p.grad.flatten() for p in params if p.grad is not None])
        for p in params:
            p.grad = None
        return g

    for loss in (lambda a: a._critic_loss(b.state.to(a.dtype), b.action, y)[0],
                 lambda a: a._actor_loss(b.state.to(a.dtype))):
        g_ref, g_mixed = grads(ref, loss(ref)), grads(mixed, loss(mixed))
        assert g_mixed.dtype == torch.float32 and g_mixed.shape == g_ref.shape
        assert torch.nn.functional.cosine_similarity(g_mixed, g_ref, dim=0) > 0.99

    for i in range(4):
        assert np.isfinite(mixed.update(_batch(n=32, seed=i, state_dim=105, action_dim=4))
                           ["critic_loss"])
    for net in ("actor", "critic", "actor_target", "critic_target"):
        masters = list(getattr(mixed, net).parameters())
        assert all(p.dtype == torch.float32 for p in masters)
        for p, p_lp in zip(masters, mixed.lp[net].net().parameters(), strict=True):
            assert p_lp.dtype == torch.bfloat16 and torch.equal(p_lp, p.to(torch.bfloat16))
    assert all(s["exp_avg"].dtype == torch.float32 for s in mixed.critic_opt.state.values())
    assert ref.lp["critic"].net() is ref.critic  # no copy in float32
    mixed.actor.load_state_dict(ref.actor.state_dict())  # from outside: an actor file
    for p_ref, p_lp in zip(ref.actor.parameters(), mixed.lp["actor"].net().parameters(),
                           strict=True):
        assert torch.equal(p_lp, p_ref.to(torch.bfloat16))


def test_flush_denormals_only_inside():
    tiny = torch.tensor([1e-39], dtype=torch.float32)  # a denormal
    from policy.algorithms.td3 import flush_denormals

    with flush_denormals():
        assert (tiny * 1.0).item() == 0.0
    assert (tiny * 1.0).item() > 0.0


def test_precision_is_checked():
    with pytest.raises(ValueError, match="precision"):
        TD3Config(precision="fp8")
    from policy.algorithms.td3 import best_precision

    assert best_precision("cpu") in ("fp32", "bf16")


def _roundtrip(state):
    f = io.BytesIO()
    torch.save(state, f)
    f.seek(0)
    return torch.load(f, weights_only=True)


@pytest.mark.parametrize("cls,cfg_cls", [(TD3, TD3Config), (DDPG, DDPGConfig)])
def test_state_dict_roundtrip(cls, cfg_cls):
    agent = cls(cfg_cls(**TINY, seed=4))
    for i in range(5):
        agent.update(_batch(seed=i))
    agent.act(np.zeros(3, np.float32), noise=True)
    restored = cls.from_state_dict(_roundtrip(agent.state_dict()))
    s = np.random.default_rng(1).normal(size=(7, 3)).astype(np.float32)
    np.testing.assert_array_equal(restored.act(s, noise=False), agent.act(s, noise=False))
    np.testing.assert_array_equal(restored.act(s, noise=True), agent.act(s, noise=True))
    # training continues identically (optimizer moments, counters, noise generator)
    b = _batch(seed=9)
    for _ in range(2):
        assert restored.update(b) == agent.update(b)
    np.testing.assert_array_equal(restored.act(s, noise=False), agent.act(s, noise=False))
    assert restored.updates == agent.updates == 7


def test_actor_file_records_its_task_and_refuses_another(tmp_path):
    from dataclasses import replace

    from bus.task import TASK
    from policy.training.evaluate import ActorController

    agent = TD3(TD3Config())
    agent.save_actor(tmp_path / "old.pt")  # no task recorded: taken as it is
    load_actor(tmp_path / "old.pt", task=TASK)
    agent.task = TASK.to_dict()
    agent.save_actor(tmp_path / "ok.pt")
    assert torch.load(tmp_path / "ok.pt", weights_only=True)["task"]["frames"] == 3
    ActorController(tmp_path / "ok.pt")
    load_actor(tmp_path / "ok.pt", task=replace(TASK, max_steps=50))  # limits may differ
    agent.task = replace(TASK, max_action=1.0).to_dict()
    agent.save_actor(tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"other.pt: trained for task max_action=1.0, but "
                                         r"this task has max_action=2.0"):
        ActorController(tmp_path / "other.pt")
    load_actor(tmp_path / "other.pt")  # without a task to check (a Gymnasium task)


def test_save_and_load_actor(tmp_path):
    agent = TD3(TD3Config(**TINY, seed=2))
    agent.update(_batch())
    agent.update(_batch())
    agent.save_actor(tmp_path / "actor.pt")
    actor = load_actor(tmp_path / "actor.pt")
    s = np.random.default_rng(0).normal(size=(4, 3)).astype(np.float32)
    np.testing.assert_array_equal(actor(torch.from_numpy(s)).numpy(), agent.act(s, noise=False))
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    np.testing.assert_array_equal(agent.act(s, True, rng=rng_a), agent.act(s, True, rng=rng_b))


def test_fused_adam_matches_torch_adam_bit_for_bit():
    """policy.algorithms.td3.FusedAdam calls torch's fused kernel directly: the same parameters and
    optimizer state as torch.optim.Adam(fused=True), before and after a state-dict round
    trip."""
    import copy

    from policy.algorithms.td3 import FusedAdam

    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(7, 16), torch.nn.ReLU(), torch.nn.Linear(16, 2))
            for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    ours = FusedAdam(nets[0].parameters(), lr=1e-2)
    ref = torch.optim.Adam(nets[1].parameters(), lr=1e-2, fused=True)
    x = torch.randn(64, 7)
    for step in range(30):
        if step == 15:  # a checkpoint in the middle (a copy, as from a file)
            ours.load_state_dict(copy.deepcopy(ref.state_dict()))
        for net, opt in zip(nets, (ours, ref), strict=True):
            opt.zero_grad(set_to_none=True)
            net(x).pow(2).mean().backward()
            opt.step()
    for a, b in zip(nets[0].parameters(), nets[1].parameters(), strict=True):
        assert torch.equal(a, b)
    sa, sb = ours.state_dict()["state"], ref.state_dict()["state"]
    assert all(torch.equal(sa[i][k], sb[i][k]) for i in sb for k in sb[i])
