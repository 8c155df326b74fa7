"""The whole simulated cell: real clients against it, and ``wristscan sim`` as a process.

Each cell is on a loopback address of the run's own (two test runs on one machine never meet);
no assert depends on how fast a loaded machine runs."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import rtde_receive

from wristscan.daemon.config import load_default
from wristscan.daemon.simcell.cell import start_cell
from wristscan.drivers import lpf1
from wristscan.drivers.sim.ur.controller import pick_free_loopback_host


def free_udp_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(30.0)
    return sock


def test_cell_serves_robot_sensor_and_table() -> None:
    sock = _udp_socket()
    host = pick_free_loopback_host()
    cell = start_cell(load_default(), controller_host=host, table_port=0, target=sock.getsockname())
    try:
        ep = cell.endpoints()
        assert ep["robot"]["host"] == host and ep["table"]["port"] > 0
        truth = cell.truth()
        np.testing.assert_allclose(truth["sensor2flange_ur_pose"][:3], [0.06, 0.01, 0.2])
        # The sensor streams LPF1 profiles with consecutive frame counters.
        counters = []
        while len(counters) < 20:
            msg = lpf1.parse_message(sock.recv(1 << 16))
            if msg.header.msg_type == lpf1.MsgType.PROFILE:
                prof = lpf1.decode_profile(msg)
                assert prof.n_points == 2048
                counters.append(prof.frame_counter)
        # Increasing counters (an overloaded host may skip exposures, leaving counted gaps).
        assert np.all(np.diff(counters) >= 1)
        # The real ur_rtde receive client reads the controller at 500 Hz.
        r = rtde_receive.RTDEReceiveInterface(host)
        try:
            t0 = r.getTimestamp()
            time.sleep(0.2)
            # Controller time advances (its rate is tested in test_sim_ur_controller.py), and
            # never ahead of the host's: a sample is sent at its time, not before (causality).
            t1 = r.getTimestamp()
            assert cell.controller is not None
            assert 0.0 < t1 - t0 and cell.controller.host_time_ns(t1) <= time.monotonic_ns()
            assert len(r.getActualQ()) == 6
        finally:
            r.disconnect()
    finally:
        cell.stop()
        sock.close()
    assert multiprocessing.active_children() == []


def test_sim_command_runs_until_sigterm(tmp_path: object) -> None:
    host = pick_free_loopback_host()
    text = open(
        os.path.join(os.path.dirname(__file__), "..", "..", "..", "config", "sim.toml")
    ).read()
    head, _, sim_part = text.partition("[sim.controller]")
    # Everything on the run's own address: the controller, the table (any free port) and the
    # sensor's datagrams (sent to a port free there, so never into another run's driver).
    head = head.replace('host = "127.0.0.1"', f'host = "{host}"')
    head = head.replace('bind_host = "127.0.0.1"', f'bind_host = "{host}"')
    head = head.replace("port = 50002", f"port = {free_udp_port(host)}")
    cfg_text = (
        head
        + "[sim.controller]"
        + sim_part.replace('host = "127.0.0.2"', f'host = "{host}"')
        .replace('host = "127.0.0.1"', f'host = "{host}"')
        .replace("port = 5020", "port = 0")
    )
    cfg_path = os.path.join(str(tmp_path), "cell.toml")
    with open(cfg_path, "w") as fh:
        fh.write(cfg_text)
    proc = subprocess.Popen(
        [sys.executable, "-m", "wristscan.daemon.cli", "sim", "--config", cfg_path, "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        out_lines = []
        assert proc.stdout is not None
        for line in proc.stdout:  # the JSON document ends with a lone closing brace
            out_lines.append(line)
            if line.rstrip() == "}":
                break
        info = json.loads("".join(out_lines))
        assert info["endpoints"]["robot"]["host"] == host
        r = rtde_receive.RTDEReceiveInterface(host)
        r.disconnect()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # Every process the command started has ended: the controller's ports are free again.
    with socket.socket() as s:
        s.bind((host, 30004))


def test_sim_command_rejects_a_bad_config(tmp_path: object) -> None:
    bad = os.path.join(str(tmp_path), "bad.toml")
    with open(bad, "w") as fh:
        fh.write("schema_version = 1\n[robot]\nmax_speed_m_s = -1\n")
    out = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "sim", "--config", bad],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "robot.max_speed_m_s" in out.stderr and "Traceback" not in out.stderr
