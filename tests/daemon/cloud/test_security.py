"""zenoh security applied to the daemon's session and to every client (docs/security.md), over
real zenoh sessions on a loopback address of the run's own: user/password authentication, an
access-control list, TLS and mutual TLS with certificates made for the test.

"Gets nothing" is measured against a client that is let in: both wait side by side, and the one
refused has received nothing when the one let in has received several batches. Waits are for
events with generous timeouts; nothing asserts how fast a loaded machine delivers. Certificates
are made by ``support.make_tls_files`` with the ``openssl`` command.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from support import free_tcp_port, make_tls_files, own_loopback_host
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.cloud.session import CLIENT_CONFIG_ENV, ZenohSetupError
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session

PREFIX = "wristscan/sec"
STATS = {"received": 7}
CALIBRATION = {"kind": "sensor2flange"}
READ_KEYS = [f"{PREFIX}/cloud", f"{PREFIX}/status", f"{PREFIX}/stats", f"{PREFIX}/alive"]
MESSAGES = [
    "put",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def write_json5(path: Path, content: dict[str, object]) -> Path:
    path.write_text(json.dumps(content, indent=2))
    path.chmod(0o600)
    return path


def usrpwd(user: str, password: str, dictionary: Path | None = None) -> dict[str, object]:
    auth: dict[str, object] = {"user": user, "password": password}
    if dictionary is not None:
        auth["dictionary_file"] = dictionary.name  # relative: to the config file's folder
    return {"transport": {"auth": {"usrpwd": auth}}}


@dataclass
class Daemon:
    """The daemon's zenoh face publishing a batch and a status every 50 ms until closed."""

    endpoint: str
    face: DaemonZenoh
    stop: threading.Event
    thread: threading.Thread

    @classmethod
    def start(cls, endpoint: str, config_file: Path) -> Daemon:
        session = open_session(listen=[endpoint], config_file=config_file)
        face = DaemonZenoh(session, PREFIX, calibration=lambda: CALIBRATION, stats=lambda: STATS)
        stop = threading.Event()
        xyz = np.ones((100, 3), np.float32)

        def publish() -> None:
            while not stop.wait(0.05):
                face.publish_cloud(xyz, 1, 2, 1, "base")
                face.publish_status({"state": "running"})

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        return cls(endpoint, face, stop, thread)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.face.close()
        self.face.session.close()


def alive_within(client: CloudClient, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if client.alive(timeout=0.5):
            return True
        time.sleep(0.1)
    return False


def receive_beside(allowed: CloudClient, refused: list[CloudClient], n: int = 4) -> None:
    """Wait until ``allowed`` has received ``n`` batches; every ``refused`` client, listening
    all that time, must have received none."""
    assert alive_within(allowed, 30), "the daemon's liveliness never reached the allowed client"
    got = 0
    deadline = time.monotonic() + 30
    while got < n:
        assert time.monotonic() < deadline, f"the allowed client received only {got} batches"
        got += allowed.recv(timeout=0.5) is not None
    for client in refused:
        assert client.received == 0
        assert client.recv(timeout=0.05) is None


def assert_refused(client: CloudClient) -> None:
    assert not client.alive(timeout=0.5)
    with pytest.raises(TimeoutError):
        client.query("stats", timeout=0.5)
    assert list(client.session.info.peers_zid()) == []


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, Path]]:
    """A daemon that lets in only known users (the password dictionary) and, by its access
    control list, lets operators read clouds, status, stats and liveliness and no one the
    calibration."""
    folder = tmp_path_factory.mktemp("secured")
    dictionary = folder / "passwords.txt"
    dictionary.write_text("daemon:daemon-pw\nalice:alice-pw\nbob:bob-pw\n")
    dictionary.chmod(0o600)
    conf = usrpwd("daemon", "daemon-pw", dictionary)
    conf["access_control"] = {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "read",
                "messages": MESSAGES,
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": READ_KEYS,
            },
            {
                "id": "no-calibration",
                "messages": MESSAGES,
                "flows": ["ingress", "egress"],
                "permission": "deny",
                "key_exprs": [f"{PREFIX}/calibration"],
            },
        ],
        "subjects": [{"id": "operators", "usernames": ["alice"]}],
        "policies": [
            {"id": "operators-read", "rules": ["read", "no-calibration"], "subjects": ["operators"]}
        ],
    }
    daemon_file = write_json5(folder / "daemon.json5", conf)
    for user in ("alice", "bob"):
        write_json5(folder / f"{user}.json5", usrpwd(user, f"{user}-pw"))
    write_json5(folder / "intruder.json5", usrpwd("alice", "guessed"))
    host = own_loopback_host()
    daemon = Daemon.start(f"tcp/{host}:{free_tcp_port(host)}", daemon_file)
    try:
        yield daemon, folder
    finally:
        daemon.close()


def test_unauthenticated_or_wrong_password_gets_nothing(secured: tuple[Daemon, Path]) -> None:
    daemon, folder = secured
    eps = [daemon.endpoint]
    with (
        CloudClient(PREFIX, connect=eps, config_file=folder / "alice.json5") as alice,
        CloudClient(PREFIX, connect=eps) as anonymous,
        CloudClient(PREFIX, connect=eps, config_file=folder / "intruder.json5") as intruder,
    ):
        receive_beside(alice, [anonymous, intruder])
        assert alice.query("stats") == STATS
        assert_refused(anonymous)
        assert_refused(intruder)


def test_access_control_denies_keys(secured: tuple[Daemon, Path]) -> None:
    """alice may read the clouds and stats but not the calibration; bob, a known user in no
    policy, is denied everything by default."""
    daemon, folder = secured
    eps = [daemon.endpoint]
    with (
        CloudClient(PREFIX, connect=eps, config_file=folder / "alice.json5") as alice,
        CloudClient(PREFIX, connect=eps, config_file=folder / "bob.json5") as bob,
    ):
        receive_beside(alice, [bob])
        assert alice.query("stats") == STATS
        with pytest.raises(TimeoutError):
            alice.query("calibration", timeout=1.0)
        assert not bob.alive(timeout=0.5)
        with pytest.raises(TimeoutError):
            bob.query("stats", timeout=0.5)


def test_cli_uses_the_per_user_client_config(
    secured: tuple[Daemon, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``wristscan status`` takes its credentials from $WRISTSCAN_ZENOH_CONFIG; without them the
    daemon does not answer, and a missing file is one line, exit 2."""
    daemon, folder = secured
    args = ["status", "--prefix", PREFIX, "--connect", daemon.endpoint, "--timeout", "20"]
    monkeypatch.setenv(CLIENT_CONFIG_ENV, str(folder / "alice.json5"))
    ok = CliRunner().invoke(app, args)
    assert ok.exit_code == 0, ok.output
    assert "running" in ok.output and "received" in ok.output
    monkeypatch.setenv(CLIENT_CONFIG_ENV, "")
    refused = CliRunner().invoke(app, [*args[:-1], "2"])
    assert refused.exit_code == 1 and "no wristscan daemon answered" in refused.output
    monkeypatch.setenv(CLIENT_CONFIG_ENV, str(folder / "missing.json5"))
    missing = CliRunner().invoke(app, args)
    assert missing.exit_code == 2
    assert "missing.json5: No such file or directory" in missing.output
    assert "Traceback" not in missing.output and missing.exception is not None


def test_tls_with_the_right_ca_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    host = own_loopback_host()
    make_tls_files(tmp_path / "cell", host)
    make_tls_files(tmp_path / "other", host)
    tls = {"listen_certificate": "cell/server.pem", "listen_private_key": "cell/server.key"}
    daemon_file = write_json5(tmp_path / "daemon.json5", {"transport": {"link": {"tls": tls}}})
    for name in ("cell", "other"):
        ca = {"root_ca_certificate": f"{name}/ca.pem"}
        write_json5(tmp_path / f"trust-{name}.json5", {"transport": {"link": {"tls": ca}}})
    daemon = Daemon.start(f"tls/{host}:{free_tcp_port(host)}", daemon_file)
    try:
        eps = [daemon.endpoint]
        # The trusted client through the per-user file, the others named explicitly; one told
        # not to read the per-user file knows no CA of the plant.
        monkeypatch.setenv(CLIENT_CONFIG_ENV, str(tmp_path / "trust-cell.json5"))
        with (
            CloudClient(PREFIX, connect=eps) as trusted,
            CloudClient(PREFIX, connect=eps, config_file=tmp_path / "trust-other.json5") as wrong,
            CloudClient(
                PREFIX,
                connect=[f"tcp/{host}:{daemon.endpoint.rsplit(':', 1)[1]}"],
                config_file=tmp_path / "trust-cell.json5",
            ) as plain,
            CloudClient(PREFIX, connect=eps, user_config=False) as no_ca,
        ):
            receive_beside(trusted, [wrong, plain, no_ca])
            assert trusted.query("calibration") == CALIBRATION
            for client in (wrong, plain, no_ca):
                assert_refused(client)
    finally:
        daemon.close()


def test_mutual_tls_needs_a_client_certificate_of_the_ca(tmp_path: Path) -> None:
    host = own_loopback_host()
    for name in ("cell", "other"):
        make_tls_files(tmp_path / name, host, client=True)
    tls = {
        "listen_certificate": "cell/server.pem",
        "listen_private_key": "cell/server.key",
        "root_ca_certificate": "cell/ca.pem",
        "enable_mtls": True,
    }
    daemon_file = write_json5(tmp_path / "daemon.json5", {"transport": {"link": {"tls": tls}}})
    for name in ("cell", "other", "none"):
        client = {"root_ca_certificate": "cell/ca.pem", "enable_mtls": True}
        if name != "none":
            client["connect_certificate"] = f"{name}/client.pem"
            client["connect_private_key"] = f"{name}/client.key"
        write_json5(tmp_path / f"{name}.json5", {"transport": {"link": {"tls": client}}})
    daemon = Daemon.start(f"tls/{host}:{free_tcp_port(host)}", daemon_file)
    try:
        eps = [daemon.endpoint]
        with (
            CloudClient(PREFIX, connect=eps, config_file=tmp_path / "cell.json5") as trusted,
            CloudClient(PREFIX, connect=eps, config_file=tmp_path / "other.json5") as foreign,
            CloudClient(PREFIX, connect=eps, config_file=tmp_path / "none.json5") as anonymous,
        ):
            receive_beside(trusted, [foreign, anonymous])
            assert_refused(foreign)
            assert_refused(anonymous)
    finally:
        daemon.close()


def test_setup_errors_are_one_line(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """An endpoint already taken, a bad file: a ZenohSetupError naming it, one line, no zenoh
    source locations, never the file's content (a password on the faulty line)."""
    import socket

    host = own_loopback_host()
    with socket.socket() as taken:
        taken.bind((host, 0))
        taken.listen()
        endpoint = f"tcp/{host}:{taken.getsockname()[1]}"
        with pytest.raises(ZenohSetupError) as err:
            open_session(listen=[endpoint])
    assert isinstance(err.value, RuntimeError)
    message = str(err.value)
    assert endpoint in message and "Address already in use" in message
    assert "\n" not in message and ".rs:" not in message
    broken = tmp_path / "broken.json5"
    broken.write_text('{ transport: { auth: { usrpwd: { user: "u", password: "hunter2" }}} ,,')
    with pytest.raises(ZenohSetupError, match=r"broken\.json5: line 1 column \d+") as err:
        open_session(config_file=broken)
    assert "hunter2" not in str(err.value) and "\n" not in str(err.value)
    # Opening a session with a password logs neither the password nor the configuration.
    secret = write_json5(tmp_path / "secret.json5", usrpwd("carol", "s3cr3t-pw"))
    with caplog.at_level(logging.DEBUG):
        open_session(connect=[endpoint], config_file=secret).close()
    assert "zenoh session" in caplog.text and "s3cr3t-pw" not in caplog.text
    tls = {"listen_certificate": "none.pem", "listen_private_key": "none.key"}
    nocert = write_json5(tmp_path / "nocert.json5", {"transport": {"link": {"tls": tls}}})
    with pytest.raises(ZenohSetupError, match=r"tls/.*nocert\.json5.*private key"):
        open_session(listen=[f"tls/{host}:{free_tcp_port(host)}"], config_file=nocert)


def test_the_daemon_applies_its_zenoh_config_file(tmp_path: Path) -> None:
    """The daemon's session as ``wristscan run`` opens it from its TOML config
    (``service.setup.open_daemon_session``), with ``[zenoh] config_file`` (relative to the TOML
    file) asking for a user and password: a client with credentials reads the batches, one
    without gets nothing. (Checked once by hand with ``wristscan run`` on the simulated cell too:
    ~36 s on a loaded machine, too long for the default run.)"""
    from wristscan.daemon.config import load_config
    from wristscan.daemon.service.setup import open_daemon_session
    from wristscan.daemon.simcell.cell import dump_toml, free_sim_config

    (tmp_path / "passwords.txt").write_text("daemon:daemon-pw\nalice:alice-pw\n")
    daemon_conf = usrpwd("daemon", "daemon-pw", tmp_path / "passwords.txt")
    write_json5(tmp_path / "zenoh.json5", daemon_conf)
    write_json5(tmp_path / "alice.json5", usrpwd("alice", "alice-pw"))
    doc = free_sim_config({"zenoh": {"config_file": "zenoh.json5"}})
    (tmp_path / "cell.toml").write_text(dump_toml(doc))
    cfg = load_config(tmp_path / "cell.toml")
    assert cfg.zenoh.config_file == str(tmp_path / "zenoh.json5")
    assert cfg.zenoh.shared_memory is False
    session = open_daemon_session(cfg)
    face = DaemonZenoh(session, cfg.zenoh.prefix)
    try:
        eps = list(cfg.zenoh.listen)
        alice_file = tmp_path / "alice.json5"
        with (
            CloudClient(cfg.zenoh.prefix, connect=eps, config_file=alice_file) as alice,
            CloudClient(cfg.zenoh.prefix, connect=eps) as anonymous,
        ):
            assert alive_within(alice, 30)
            xyz = np.ones((10, 3), np.float32)
            deadline = time.monotonic() + 30
            while alice.received < 3:
                assert time.monotonic() < deadline, "the daemon's batches never reached alice"
                face.publish_cloud(xyz, 1, 2, 1, "base")
                time.sleep(0.05)
            assert anonymous.received == 0
            assert_refused(anonymous)
    finally:
        face.close()
        session.close()
