"""Shared inputs of the command-line tests: short runs on the simulated clock."""
from __future__ import annotations

import pytest

from coiltrack.tools import scenarios
from coiltrack.tools.bench.runner import run_inproc


@pytest.fixture(scope="session")
def fusion_log(tmp_path_factory):
    """A 4 s frame log of roetenberg-fusion, seed 1 (enough for the fusion filter to start)."""
    path = tmp_path_factory.mktemp("logs") / "fusion.log"
    run_inproc(scenarios.get("roetenberg-fusion"), seed=1, duration_s=4.0, log_path=path)
    return path


class _EveryMessage(dict):
    """pyigtl's client keeps only the latest message of each device; as its
    ``incoming_messages`` this keeps every one, in arrival order, in ``received``."""

    def __init__(self, received: list):
        super().__init__()
        self.received = received

    def __setitem__(self, device, message):
        self.received.append(message)
        super().__setitem__(device, message)


@pytest.fixture
def igtl_client():
    """``connect(port)``: pyigtl's client on 127.0.0.1:port whose ``received`` list gets
    every message in arrival order; stopped at the end of the test."""
    clients = []

    def connect(port: int):
        import pyigtl

        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port, start_now=False)
        client.received = []
        client.incoming_messages = _EveryMessage(client.received)
        client.start()
        clients.append(client)
        return client

    yield connect
    for c in clients:
        c.stop()
