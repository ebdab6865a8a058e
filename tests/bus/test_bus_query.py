"""Bus request/reply over real loopback Zenoh: a queryable answered when its owner likes
(no user code in Zenoh's threads), a query that times out, a request that does not
decode (answered with an error, counted)."""

from __future__ import annotations

import threading
import time

from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig


def test_query_answered_later_timeout_and_bad_request() -> None:
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    with Bus.open(cfg) as server, Bus.open(cfg) as client:
        assert client.query(keys.COMMAND, "uav1", m.vehicle_command("arm"), m.COMMAND_ACK,
                            timeout=0.5) is None  # nobody declared: None at once
        q = server.queryable(keys.COMMAND, "uav1")
        stop = threading.Event()

        def owner() -> None:  # takes requests in its own loop, answers the arms only
            while not stop.is_set():
                for req in q.take():
                    if req.msg.command == "arm":
                        time.sleep(0.05)  # answered later, not in a callback
                        req.reply(m.command_ack(True, "", "ARMED", True, True, False, 7))
                time.sleep(0.005)

        thread = threading.Thread(target=owner, daemon=True)
        thread.start()
        try:
            # the queryable's declaration takes a moment to be seen (a query before it
            # returns None at once): retry until a deadline, not a count, so a loaded
            # machine does not use the tries up in milliseconds
            ack, deadline = None, time.monotonic() + 20.0
            while ack is None and time.monotonic() < deadline:
                ack = client.query(keys.COMMAND, "uav1", m.vehicle_command("arm"),
                                   m.COMMAND_ACK, timeout=2.0)
                if ack is None:
                    time.sleep(0.01)
            assert ack is not None and ack.accepted and ack.state == "ARMED"
            assert ack.revision == 7
            assert client.query(keys.COMMAND, "uav1", m.vehicle_command("land"),
                                m.COMMAND_ACK, timeout=0.3) is None  # taken, never answered
            client.session.get(keys.key("uav1", keys.COMMAND), payload=b"\x00\x01junk",
                               timeout=1.0)
            wait_for(lambda: q.decode_errors == 1, what="the bad request counted")
            assert q.received == 2 and server.counters()["decode_errors"] == 1
        finally:
            stop.set()
            thread.join(2.0)
