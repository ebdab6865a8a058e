"""skyloop: a software-in-the-loop drone stack.

Importing this package registers the Gymnasium environment ``skyloop/UavNav-v0``
(the in-process env of :mod:`policy.training.env`), so ``gymnasium.make("skyloop/UavNav-v0")``
works after ``import skyloop``.

Where nothing imported skyloop (a fresh interpreter, the worker processes of
Stable-Baselines3's ``SubprocVecEnv``, which start from a forkserver or ``spawn``), use
the module-qualified id ``"skyloop:skyloop/UavNav-v0"``: Gymnasium imports the module
before ``:`` and then finds the id. Gymnasium 1.0 removed the ``gymnasium.envs``
entry-point plugins that once registered installed packages' envs on their own, so an
entry point in pyproject.toml would not do this.

The spec's ``max_episode_steps`` is the task specification's episode limit
(``bus.task.TASK.max_steps``), so ``TimeLimit`` and the env's own timeout agree; a run
that raises the env's limit (``config=EnvConfig(max_steps=...)``) passes the same
``max_episode_steps=`` to ``gymnasium.make``.
"""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version

from skyloop import signals as _signals

if _signals.started_as_command():  # a signal during start-up ends it at once, quietly
    _signals.exit_at_once()

# Small matrices on a 2-core machine: BLAS threads cost far more than they save
# (measured up to 50x slower for the icosahedron matmuls). Users can still override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gymnasium  # noqa: E402

from bus.task import TASK  # noqa: E402

try:  # the one version is pyproject.toml's, as installed
    __version__ = version("skyloop")
except PackageNotFoundError:  # running from a tree that was never installed
    __version__ = "0+unknown"

ENV_ID = "skyloop/UavNav-v0"

if ENV_ID not in gymnasium.registry:  # once, however skyloop came to be imported
    gymnasium.register(id=ENV_ID, entry_point="policy.training.env:UavNavEnv",
                       max_episode_steps=TASK.max_steps)
