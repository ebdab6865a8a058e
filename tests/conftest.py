"""Suite-wide settings.

Hermetic state: the bridge persists ground-station parameter changes under
``$XDG_STATE_HOME/skyloop`` (``mavlink_bridge.params``). The suite points that at a
temporary directory, for itself and every process it starts, so no test reads a user's
saved parameters or writes to the home directory.
"""

from __future__ import annotations

import os

import pytest


@pytest.fixture(autouse=True, scope="session")
def _state_home(tmp_path_factory: pytest.TempPathFactory) -> None:
    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("xdg_state"))
