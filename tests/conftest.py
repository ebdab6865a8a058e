"""Suite-wide settings.

Hermetic state: the bridge persists ground-station parameter changes under
``$XDG_STATE_HOME/skyloop`` (``mavlink_bridge.gcs.params``). The suite points that at a
temporary directory, for itself and every process it starts, so no test reads a user's
saved parameters or writes to the home directory.

Parallel workers (``make test`` runs pytest-xdist, ``-n 2 --dist loadfile``, then the
tests marked ``timing`` alone): every test
that starts a stack gives it free loopback ports (``loopback.up_args``, ``free_port``);
a session that opens the bus without a hub of its own would claim or join the default
hub, tcp/127.0.0.1:7447, and so another worker's bus, so each worker session gets a hub
of its own in ``SKYLOOP_ZENOH_HUB`` (inherited by the processes it starts).
"""

from __future__ import annotations

import os

import pytest


@pytest.fixture(autouse=True, scope="session")
def _state_home(tmp_path_factory: pytest.TempPathFactory) -> None:
    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("xdg_state"))


@pytest.fixture(autouse=True, scope="session")
def _hub_of_this_worker() -> None:
    from skyloop.launcher import free_port

    os.environ["SKYLOOP_ZENOH_HUB"] = f"tcp/127.0.0.1:{free_port()}"
