"""What securing the daemon's zenoh traffic costs (issue 22, docs/security.md): the daemon's face
(``DaemonZenoh.publish_cloud``, congestion control BLOCK: lossless) publishing the batches of
5 kHz x 2048 points (102 400 points, 1.2 MB, one every 10 ms) to a ``CloudClient`` in another
process, over sessions built by ``wristscan.daemon.cloud.session`` as the daemon and the client
commands build them, on loopback:

* plain TCP, shared memory off (wristscan's default) and on;
* TLS (certificates made by ``openssl``), shared memory off;
* TLS + user/password + an access-control list (deny by default), shared memory off.

For each: batches published and received (sequence numbers: none may be missing), and the CPU of
the publishing process (all its threads: encoding, the put, zenoh's TX and TLS) and of the
subscriber's, each as a share of one core over the window.

Targets: nothing lost in any case; the secured publisher (TLS + user/password + ACL) within 10 %
of a core of the plain one (the daemon spends 44-51 % of a core at 5 kHz, docs/pipeline.md).

    .venv/bin/python benchmarks/zenoh_security.py [--duration 5] [--points 102400]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import free_tcp_port, make_tls_files, own_loopback_host

from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session

PREFIX = "wristscan/bench"
PERIOD_S = 0.010
ACL_MESSAGES = ["put", "declare_subscriber", "liveliness_token", "liveliness_query"]


def _write(path: Path, content: Mapping[str, object]) -> str:
    path.write_text(json.dumps(content))
    path.chmod(0o600)
    return str(path)


def _case_files(folder: Path, host: str) -> dict[str, tuple[str | None, str | None, bool]]:
    """Case name -> (daemon's zenoh file, client's zenoh file, shared memory)."""
    make_tls_files(folder / "tls", host)
    server = {"listen_certificate": "tls/server.pem", "listen_private_key": "tls/server.key"}
    trust = {"root_ca_certificate": "tls/ca.pem"}
    (folder / "passwords.txt").write_text("daemon:d-pw\nbench:b-pw\n")
    acl = {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "read",
                "messages": ACL_MESSAGES,
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": [f"{PREFIX}/cloud", f"{PREFIX}/alive"],
            }
        ],
        "subjects": [{"id": "bench", "usernames": ["bench"]}],
        "policies": [{"id": "p", "rules": ["read"], "subjects": ["bench"]}],
    }
    auth_d = {"user": "daemon", "password": "d-pw", "dictionary_file": "passwords.txt"}
    daemon_secured = {
        "transport": {"link": {"tls": server}, "auth": {"usrpwd": auth_d}},
        "access_control": acl,
    }
    client_secured = {
        "transport": {
            "link": {"tls": trust},
            "auth": {"usrpwd": {"user": "bench", "password": "b-pw"}},
        }
    }
    return {
        "plain TCP": (None, None, False),
        "plain TCP, shared memory": (None, None, True),
        "TLS": (
            _write(folder / "d-tls.json5", {"transport": {"link": {"tls": server}}}),
            _write(folder / "c-tls.json5", {"transport": {"link": {"tls": trust}}}),
            False,
        ),
        "TLS + user/password + ACL": (
            _write(folder / "d-sec.json5", daemon_secured),
            _write(folder / "c-sec.json5", client_secured),
            False,
        ),
    }


def subscriber(endpoint: str, config: str, shm: bool, count: int) -> None:
    """Child: receive ``count`` batches (or stop after 10 s without one); print JSON figures."""
    with CloudClient(
        PREFIX,
        connect=[endpoint],
        capacity=4096,
        config_file=config or None,
        shared_memory=shm,
        user_config=False,
    ) as client:
        deadline = time.monotonic() + 30
        while not client.alive(timeout=0.5):
            if time.monotonic() > deadline:
                raise SystemExit("no daemon liveliness")
        print("ready", flush=True)
        seqs: list[int] = []
        cpu0 = wall0 = 0.0
        while len(seqs) < count:
            cloud = client.recv(timeout=10.0)
            if cloud is None:
                break
            if not seqs:
                cpu0, wall0 = time.process_time(), time.monotonic()
            seqs.append(cloud.seq)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    gaps = int(np.sum(np.diff(seqs) - 1)) if len(seqs) > 1 else 0
    print(json.dumps({"received": len(seqs), "gaps": gaps, "cpu": cpu / max(wall, 1e-9)}))


def run_case(
    endpoint: str, files: tuple[str | None, str | None, bool], duration: float, points: int
) -> dict[str, float]:
    daemon_file, client_file, shm = files
    count = int(duration / PERIOD_S)
    session = open_session(listen=[endpoint], config_file=daemon_file, shared_memory=shm)
    face = DaemonZenoh(session, PREFIX, congestion="block")
    child = subprocess.Popen(
        [sys.executable, __file__, "--sub", endpoint, client_file or "", str(int(shm)), str(count)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None
        if child.stdout.readline().strip() != "ready":
            raise RuntimeError("the subscriber did not start")
        time.sleep(0.5)  # the subscription reaches the publisher
        xyz = np.random.default_rng(0).normal(size=(points, 3)).astype(np.float32)
        cpu0, wall0 = time.process_time(), time.monotonic()
        nxt = wall0
        for _ in range(count):
            face.publish_cloud(xyz, 1, 2, points // 2048, "base")
            nxt += PERIOD_S
            time.sleep(max(0.0, nxt - time.monotonic()))
        pub_cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0)
        out, _ = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        face.close()
        session.close()
    sub = json.loads(out.splitlines()[-1])
    return {"published": count, "pub_cpu": pub_cpu, **sub}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=5.0, help="publishing window per case, s")
    ap.add_argument("--points", type=int, default=102_400, help="points per batch")
    ap.add_argument("--sub", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.sub:
        endpoint, config, shm, count = args.sub
        subscriber(endpoint, config, shm == "1", int(count))
        return 0
    host = own_loopback_host()
    figures: list[Figure] = []
    results: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, files in _case_files(Path(tmp), host).items():
            proto = "tls" if files[0] else "tcp"
            r = run_case(f"{proto}/{host}:{free_tcp_port(host)}", files, args.duration, args.points)
            results[name] = r
            lost = r["published"] - r["received"]
            figures += [
                Figure(f"{name}: lost batches", lost, "", "0", lost == 0 and r["gaps"] == 0),
                Figure(f"{name}: publisher CPU", 100 * r["pub_cpu"], "% core", "info", None),
                Figure(f"{name}: subscriber CPU", 100 * r["cpu"], "% core", "info", None),
            ]
    added = results["TLS + user/password + ACL"]["pub_cpu"] - results["plain TCP"]["pub_cpu"]
    figures.append(
        Figure("secured - plain publisher CPU", 100 * added, "% core", "<= 10", added <= 0.10)
    )
    return report(f"zenoh security cost, {args.points} points every 10 ms (issue 22)", figures)


if __name__ == "__main__":
    sys.exit(main())
