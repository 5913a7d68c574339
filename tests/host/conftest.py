"""Shared fixtures for the host link tests: a fake MCU and fast-timing clients."""

from __future__ import annotations

import threading
import time

import pytest
from fake_mcu import FakeMcu

from oibar.link import LinkClient

# Timings ~5x shorter than the defaults keep the suite fast while preserving their ratios.
FAST = dict(
    heartbeat_period_s=0.05,
    link_timeout_s=0.3,
    retransmit_timeout_s=0.05,
    max_retries=3,
    reconnect_period_s=0.1,
)


@pytest.fixture
def mcu():
    """A running fake MCU whose own link timeout matches the fast client timings."""
    with FakeMcu(link_timeout_s=0.3, telemetry_period_s=0.05, heartbeat_period_s=0.05) as fake:
        yield fake


@pytest.fixture
def fast_timings() -> dict:
    """The FAST timings, for tests that open a link some other way than make_client (a test
    module cannot `from conftest import FAST`: in one pytest run over tests/ that name may be
    another folder's conftest)."""
    return dict(FAST)


@pytest.fixture
def make_client():
    """Factory for LinkClients with fast timings; every client is closed after the test."""
    clients: list[LinkClient] = []

    def make(url: str, **overrides) -> LinkClient:
        client = LinkClient(url, **{**FAST, **overrides})
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.close()


@pytest.fixture(autouse=True)
def no_leftover_link_threads():
    """close() must join every thread it started."""
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        alive = [t.name for t in threading.enumerate() if t.name.startswith("oibar-link-")]
        if not alive:
            return
        time.sleep(0.01)
    pytest.fail(f"link threads still running after the test: {alive}")
