"""What can go wrong before a zenoh session runs, caught early and told in one line:
``ZenohConfig.problems`` (what ``check-config`` and ``run`` report about the ``[zenoh]``
section: a bind host that does not resolve or is not this machine's, a zenoh config file
missing, a directory, invalid, naming a missing certificate, a password everyone may read, TLS
without a certificate), while loading the config stays possible on any machine (a client reads
it for the prefix and endpoints); and shared memory, off by default, so a clean run leaves no
zenoh files in /dev/shm."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import zenoh
from support import free_tcp_port, own_loopback_host
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.config import load_config

REPO = Path(__file__).resolve().parents[3]
SIM_ZENOH = 'listen = ["tcp/127.0.0.1:7447"]'


def cell_toml(tmp_path: Path, zenoh_lines: str) -> Path:
    """The simulated cell's config with ``zenoh_lines`` in place of its listen line."""
    text = (REPO / "config" / "sim.toml").read_text()
    assert SIM_ZENOH in text
    path = tmp_path / "cell.toml"
    path.write_text(text.replace(SIM_ZENOH, zenoh_lines))
    return path


def zenoh_problems(tmp_path: Path, zenoh_lines: str) -> list[str]:
    """The ``[zenoh]`` problems of :func:`cell_toml`'s config; the config itself loads."""
    return load_config(cell_toml(tmp_path, zenoh_lines)).zenoh.problems()


def write(path: Path, text: str, mode: int = 0o600) -> Path:
    path.write_text(text)
    path.chmod(mode)
    return path


def test_listen_hosts_that_cannot_be_bound(tmp_path: Path) -> None:
    (found,) = zenoh_problems(tmp_path, 'listen = ["tcp/no-such-host.invalid:7447"]')
    assert found.startswith("zenoh.listen: item 0: the host 'no-such-host.invalid' does not")
    # 192.0.2.1 (TEST-NET-1) is no address of this machine.
    (found,) = zenoh_problems(tmp_path, 'listen = ["tcp/127.0.0.1:7447", "tcp/192.0.2.1:7447"]')
    assert found.startswith("zenoh.listen: item 1: cannot listen on '192.0.2.1'")
    # The port itself is not bound by the check: a running daemon may hold it.
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        listen = f'listen = ["tcp/[::1]:7447", "tcp/localhost:7447", "tcp/127.0.0.1:{port}"]'
        assert zenoh_problems(tmp_path, listen) == []


@pytest.mark.parametrize(
    ("content", "mode", "expected"),
    [
        (None, 0o600, "missing.json5: No such file or directory"),
        ("dir", 0o700, "Is a directory"),
        ('{ mode: "peer" ,, }', 0o600, "line 1 column 17: expected identifier or string"),
        ("{ bogus_key: 1 }", 0o600, "line 1 column 3: unknown field `bogus_key`"),
        (
            '{ transport: { link: { tls: { root_ca_certificate: "ca.pem" } } } }',
            0o600,
            "transport/link/tls/root_ca_certificate {dir}/ca.pem: No such file or directory",
        ),
        (
            '{ transport: { auth: { usrpwd: { user: "u", password: "p" } } } }',
            0o644,
            "holds a password and every user may read it",
        ),
    ],
)
def test_a_zenoh_config_file_that_cannot_work(
    tmp_path: Path, content: str | None, mode: int, expected: str
) -> None:
    name = "missing.json5"
    if content == "dir":
        name = "adir"
        (tmp_path / name).mkdir()
    elif content is not None:
        name = "zenoh.json5"
        write(tmp_path / name, content, mode)
    (found,) = zenoh_problems(tmp_path, f'listen = []\nconfig_file = "{name}"')
    assert found.startswith("zenoh.config_file: ")
    assert expected.format(dir=tmp_path) in found
    assert '"p"' not in found


def test_a_tls_listener_needs_its_certificate(tmp_path: Path) -> None:
    """Without a config_file the config is refused at load (one line from check-config); with a
    file lacking the certificate and key, ``problems`` names the keys."""
    path = cell_toml(tmp_path, 'listen = ["tls/127.0.0.1:7447"]')
    result = CliRunner().invoke(app, ["check-config", str(path)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "zenoh.config_file: a tls/ or quic/ listen endpoint needs a config_file" in result.output
    write(
        tmp_path / "zenoh.json5", "{ transport: { link: { tls: { root_ca_certificate: null } } } }"
    )
    lines = 'listen = ["tls/127.0.0.1:7447"]\nconfig_file = "zenoh.json5"'
    needs = "zenoh.config_file: a tls/ or quic/ listen endpoint needs transport/link/tls/listen_"
    assert zenoh_problems(tmp_path, lines) == [f"{needs}certificate", f"{needs}private_key"]
    for name in ("server.pem", "server.key"):
        write(tmp_path / name, "not checked here: zenoh reads it at start")
    tls = '{ listen_certificate: "server.pem", listen_private_key: "server.key" }'
    write(tmp_path / "zenoh.json5", f"{{ transport: {{ link: {{ tls: {tls} }} }} }}")
    assert zenoh_problems(tmp_path, lines) == []


def test_a_client_loads_the_config_of_a_daemon_of_another_machine(tmp_path: Path) -> None:
    """``wristscan status -c cell.toml`` on an operator's PC: the daemon's listen address and its
    zenoh config file are not this machine's; the config still loads (prefix, endpoints), the
    problems are only what check-config and run report."""
    lines = 'listen = ["tcp/192.0.2.1:7447"]\nconfig_file = "/etc/wristscan/zenoh/daemon.json5"'
    problems = zenoh_problems(tmp_path, lines)
    assert [p.split(":")[0] for p in problems] == ["zenoh.listen", "zenoh.config_file"]


SHM_RUN = textwrap.dedent(
    """
    import json, sys, time
    import numpy as np
    from wristscan.daemon.cloud.client import CloudClient
    from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session

    endpoint, shm = sys.argv[1], sys.argv[2] == "on"
    session = open_session(listen=[endpoint], shared_memory=shm)
    face = DaemonZenoh(session, "wristscan/shm")
    xyz = np.ones((20000, 3), np.float32)  # 240 kB batches: zenoh would share them
    with CloudClient("wristscan/shm", connect=[endpoint], shared_memory=shm) as client:
        got, deadline = 0, time.monotonic() + 60
        while got < 3 and time.monotonic() < deadline:
            face.publish_cloud(xyz, 1, 2, 1, "base")
            got += client.recv(timeout=0.2) is not None
        maps = open("/proc/self/maps").read().splitlines()
        mapped = sorted({m.split()[-1] for m in maps if "/dev/shm/" in m})
    face.close()
    session.close()
    print(json.dumps({"received": got, "mapped": mapped}))
    """
)


def shm_run(shared_memory: bool) -> dict[str, object]:
    host = own_loopback_host()
    args = [f"tcp/{host}:{free_tcp_port(host)}", "on" if shared_memory else "off"]
    out = subprocess.run(
        [sys.executable, "-c", SHM_RUN, *args], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    result: dict[str, object] = json.loads(out.stdout.splitlines()[-1])
    return result


def test_shared_memory_is_off_by_default_and_leaves_no_files() -> None:
    """With the default settings a daemon's session and a client in one process never map a
    /dev/shm file (so none is left after exit); with shared memory asked for, zenoh does."""
    default = shm_run(shared_memory=False)
    assert default == {"received": 3, "mapped": []}
    shared = shm_run(shared_memory=True)
    assert shared["received"] == 3
    assert isinstance(shared["mapped"], list) and shared["mapped"]
    assert all(str(p).endswith(".zenoh") for p in shared["mapped"])


def test_the_zenoh_files_of_docs_security_are_valid() -> None:
    """Every JSON5 example of docs/security.md is a zenoh configuration zenoh accepts (a key
    misspelt there would be an unknown field)."""
    import re

    text = (REPO / "docs" / "security.md").read_text()
    blocks = re.findall(r"```json5\n(.*?)```", text, re.DOTALL)
    assert len(blocks) >= 5
    for block in blocks:
        zenoh.Config.from_json5(block)


def test_session_config_merges_wristscan_settings_over_the_file(tmp_path: Path) -> None:
    """The file's endpoints stay when wristscan gives none; mode, multicast scouting and shared
    memory are always wristscan's; the file's relative paths are resolved against its folder."""
    from wristscan.daemon.cloud.session import session_config

    text = """{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:7001"] },
        scouting: { multicast: { enabled: true } }, transport: { shared_memory: { enabled: true },
        link: { tls: { root_ca_certificate: "certs/ca.pem" } } } }"""
    file = write(tmp_path / "zenoh.json5", text)

    def get(conf: zenoh.Config, key: str) -> object:
        return json.loads(conf.get_json(key))

    kept = session_config("peer", config_file=file)
    assert get(kept, "mode") == "peer" and get(kept, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert get(kept, "scouting/multicast/enabled") is False
    assert get(kept, "transport/shared_memory/enabled") is False
    ca = get(kept, "transport/link/tls/root_ca_certificate")
    assert ca == str(tmp_path.resolve() / "certs" / "ca.pem")
    ours = session_config("peer", listen=["tcp/127.0.0.1:7002"], config_file=file)
    assert get(ours, "listen/endpoints") == ["tcp/127.0.0.1:7002"]
    plain = session_config("peer", shared_memory=True)
    assert get(plain, "listen/endpoints") == [] and get(plain, "connect/endpoints") == []
    assert get(plain, "transport/shared_memory/enabled") is True


def test_the_per_user_client_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from wristscan.daemon.cloud.session import CLIENT_CONFIG_ENV, user_client_config

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv(CLIENT_CONFIG_ENV, raising=False)
    assert user_client_config() is None
    mine = tmp_path / ".config" / "wristscan" / "zenoh.json5"
    mine.parent.mkdir(parents=True)
    write(mine, "{}")
    assert user_client_config() == mine
    monkeypatch.setenv(CLIENT_CONFIG_ENV, str(tmp_path / "other.json5"))
    assert user_client_config() == tmp_path / "other.json5"
    monkeypatch.setenv(CLIENT_CONFIG_ENV, "")
    assert user_client_config() is None


def test_secrets_everyone_may_read(tmp_path: Path) -> None:
    """A password dictionary or a private key that every user may read is a problem; the same
    files readable by their owner only are not."""
    write(tmp_path / "passwords.txt", "daemon:pw\n", 0o644)
    write(tmp_path / "server.key", "key", 0o644)
    write(tmp_path / "server.pem", "certificate", 0o644)
    auth = '{ usrpwd: { dictionary_file: "passwords.txt" } }'
    tls = '{ listen_certificate: "server.pem", listen_private_key: "server.key" }'
    write(tmp_path / "zenoh.json5", f"{{ transport: {{ auth: {auth}, link: {{ tls: {tls} }} }} }}")
    lines = 'listen = ["tls/127.0.0.1:7447"]\nconfig_file = "zenoh.json5"'
    found = zenoh_problems(tmp_path, lines)
    assert [p.split()[1] for p in found] == [
        "transport/link/tls/listen_private_key",
        "transport/auth/usrpwd/dictionary_file",
    ]
    assert all(p.endswith("every user may read it (chmod o-r)") for p in found)
    for name in ("passwords.txt", "server.key"):
        (tmp_path / name).chmod(0o600)
    assert zenoh_problems(tmp_path, lines) == []
