"""Fixtures of the cloud tests: a zenoh endpoint of the test's own."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from support import free_tcp_port, own_loopback_host


@pytest.fixture
def endpoint() -> Iterator[str]:
    """A TCP endpoint on a loopback address of the test's own, nothing listening yet."""
    host = own_loopback_host()
    yield f"tcp/{host}:{free_tcp_port(host)}"
