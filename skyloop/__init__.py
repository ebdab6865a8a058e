"""skyloop: a software-in-the-loop drone stack.

Importing this package registers the Gymnasium environment ``skyloop/UavNav-v0``
(the in-process env of :mod:`policy.env`), so ``gymnasium.make("skyloop/UavNav-v0")``
works after ``import skyloop``.
"""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version

# Small matrices on a 2-core machine: BLAS threads cost far more than they save
# (measured up to 50x slower for the icosahedron matmuls). Users can still override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gymnasium  # noqa: E402

try:  # the one version is pyproject.toml's, as installed
    __version__ = version("skyloop")
except PackageNotFoundError:  # running from a tree that was never installed
    __version__ = "0+unknown"

ENV_ID = "skyloop/UavNav-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="policy.env:UavNavEnv")
