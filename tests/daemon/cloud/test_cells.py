"""A plant of three cells through one zenoh router (a Python session in router mode stands in
for zenohd): each cell's daemon face in client mode towards the router, with an address and
prefix of its own; one consumer on the router gets every cell's clouds, and ``wristscan cells``
lists the live cells with their counters, and forgets a cell when its daemon goes away.

The full scenario with three simulated cells at 1 kHz x 2048 points is benchmarks/plant.py."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh
from support import free_tcp_port, own_loopback_host
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud import wsc1
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session

CELLS = ("wristscan/cell1", "wristscan/cell2", "wristscan/cell3")


class _Cell:
    """One cell's daemon face: publishes a batch and a status message every 20 ms."""

    def __init__(self, prefix: str, router: str) -> None:
        self.session = open_session("client", connect=[router])
        self.published = 0
        self.face = DaemonZenoh(
            self.session, prefix, stats=lambda: {"published": self.published, "dropped": {}}
        )
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"cell {prefix}")
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            self.face.publish_cloud(np.ones((10, 3)), 1, 2, 1, "base")
            self.published += 1
            self.face.publish_status({"state": "running"})
            self.stop.wait(0.02)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.face.close()
        self.session.close()


@pytest.fixture
def router() -> Iterator[str]:
    host = own_loopback_host()
    endpoint = f"tcp/{host}:{free_tcp_port(host)}"
    session = open_session("router", listen=[endpoint])
    try:
        yield endpoint
    finally:
        session.close()


def _cells(router: str) -> tuple[int, list[dict[str, object]]]:
    res = CliRunner().invoke(
        app, ["cells", "--connect", router, "--mode", "client", "--json", "--timeout", "3"]
    )
    return res.exit_code, json.loads(res.stdout) if res.exit_code == 0 else []


def test_three_cells_through_one_router(router: str) -> None:
    cells = [_Cell(p, router) for p in CELLS]
    consumer = open_session("client", connect=[router])
    seen: dict[str, int] = {}
    lock = threading.Lock()

    def on_cloud(sample: zenoh.Sample) -> None:
        prefix = str(sample.key_expr).rsplit("/", 1)[0]
        assert wsc1.decode(sample.payload.to_bytes()).n_points == 10
        with lock:
            seen[prefix] = seen.get(prefix, 0) + 1

    sub = consumer.declare_subscriber("wristscan/*/cloud", on_cloud)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                if len(seen) == 3 and min(seen.values()) >= 5:
                    break
            time.sleep(0.05)
        assert sorted(seen) == list(CELLS) and min(seen.values()) >= 5, seen
        code, listed = _cells(router)
        assert code == 0
        assert [c["prefix"] for c in listed] == list(CELLS)
        assert all(c["state"] == "running" for c in listed), listed
        assert all(int(c["stats"]["published"]) > 0 for c in listed)  # type: ignore[index]
        # a cell whose daemon stops leaves the list: its token goes with it
        cells.pop(1).close()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            code, listed = _cells(router)
            if [c["prefix"] for c in listed] == [CELLS[0], CELLS[2]]:
                break
        assert [c["prefix"] for c in listed] == [CELLS[0], CELLS[2]]
    finally:
        sub.undeclare()
        consumer.close()
        for c in cells:
            c.close()


def test_no_cell_is_exit_1_and_a_bad_root_is_a_usage_error(router: str) -> None:
    res = CliRunner().invoke(
        app, ["cells", "--connect", router, "--mode", "client", "--timeout", "0.5"]
    )
    assert res.exit_code == 1 and "no live cell under wristscan/**" in res.output
    res = CliRunner().invoke(app, ["cells", "--root", "wristscan/*", "--connect", router])
    assert res.exit_code == 2 and "--root must be a plain zenoh key" in res.output
    res = CliRunner().invoke(app, ["cells", "--timeout", "nan", "--connect", router])
    assert (
        res.exit_code == 2 and "--timeout: must be a finite number >= 0.1 (got nan)" in res.output
    )
