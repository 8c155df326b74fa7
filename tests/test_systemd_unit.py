"""The systemd unit: systemd accepts it, it keeps the settings the daemon relies on, and its
sandbox does not break the daemon's libraries.

These tests need ``systemd-analyze`` (Debian/Ubuntu package ``systemd``); CI installs it. They
fail, rather than skip, when it is missing.
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "wristscan.service"


def systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    assert exe is not None, "systemd-analyze is missing: install the 'systemd' package (apt)"
    return exe


def unit_settings() -> dict[str, list[str]]:
    """``Section.Key`` -> every value given (keys may repeat), comments dropped."""
    out: dict[str, list[str]] = {}
    section = ""
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.setdefault(f"{section}.{key.strip()}", []).append(value.strip())
    return out


def test_systemd_analyze_verify_accepts_the_unit() -> None:
    # verify exits 0 on unknown keys and unparsable values but prints them: both must be clean.
    done = subprocess.run(
        [systemd_analyze(), "verify", str(UNIT)], capture_output=True, text=True, timeout=60
    )
    ours = [line for line in done.stderr.splitlines() if "wristscan" in line]
    assert done.returncode == 0, done.stderr
    assert ours == []


def test_sandbox_exposure_stays_low() -> None:
    done = subprocess.run(
        [systemd_analyze(), "security", "--offline=yes", "--no-pager", str(UNIT)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for wristscan\.service: (\d+\.\d+)", done.stdout)
    assert m is not None, done.stdout + done.stderr
    assert float(m.group(1)) <= 2.5


def test_unit_keeps_the_settings_the_daemon_relies_on() -> None:
    s = unit_settings()
    expected = {
        "Service.Type": ["notify"],
        "Service.NotifyAccess": ["main"],
        "Service.ExecReload": ["/bin/kill -HUP $MAINPID"],
        "Service.WatchdogSec": ["10"],
        "Service.Restart": ["on-failure"],
        "Service.User": ["wristscan"],
        "Service.Group": ["wristscan"],
        "Service.SupplementaryGroups": ["dialout"],
        "Service.StateDirectory": ["wristscan"],
        "Service.ConfigurationDirectory": ["wristscan"],
        "Service.ReadWritePaths": ["/var/lib/wristscan"],
        "Service.NoNewPrivileges": ["yes"],
        "Service.ProtectSystem": ["strict"],
        "Service.ProtectHome": ["yes"],
        "Service.PrivateTmp": ["yes"],
        "Service.DevicePolicy": ["closed"],
        "Service.LockPersonality": ["yes"],
        "Service.MemoryDenyWriteExecute": ["yes"],
        # The benchmark runs the daemon at the unit's priority (benchmarks/pipeline.py).
        "Service.Nice": ["-10"],
        "Service.CPUWeight": ["1000"],
        "Install.WantedBy": ["multi-user.target"],
    }
    for key, value in expected.items():
        assert s.get(key) == value, key
    assert s["Service.ExecStart"] == [
        "/usr/bin/env wristscan run --config /etc/wristscan/cell.toml"
    ]
    assert {"char-ttyUSB rw", "char-ttyACM rw"} <= set(s["Service.DeviceAllow"])
    families = s["Service.RestrictAddressFamilies"][0].split()
    assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= set(families)
    for key in ("ProtectKernelTunables", "ProtectKernelModules", "ProtectKernelLogs"):
        assert s[f"Service.{key}"] == ["yes"]
    assert s["Service.RestartSec"]


# A child that installs what systemd installs for MemoryDenyWriteExecute=yes (systemd 252, a
# seccomp filter: mmap with PROT_WRITE|PROT_EXEC, mprotect/pkey_mprotect adding PROT_EXEC and
# shmat with SHM_EXEC fail with EPERM) and for RestrictAddressFamilies= (socket() of another family
# fails with EAFNOSUPPORT), proves the filter bites, then runs the daemon's libraries.
_SANDBOXED_CHILD = r"""
import ctypes, errno, mmap, socket, sys
FAMILIES = [int(f) for f in sys.argv[1].split(",")]
NR_MMAP, NR_MPROTECT, NR_SOCKET, NR_SHMAT, NR_PKEY_MPROTECT = 9, 10, 41, 30, 329
PROT_WRITE, PROT_EXEC, SHM_EXEC = 0x2, 0x4, 0o100000
LD, JEQ, AND, RET = 0x20, 0x15, 0x54, 0x06
ALLOW = 0x7FFF0000
def errno_ret(e): return 0x00050000 | e
code = []
def op(c, k, jt=None, jf=None): code.append((c, jt, jf, k))
def label(name): code.append(name)
op(LD, 4); op(JEQ, 0xC000003E, None, "allow")  # x86-64 only
op(LD, 0)
op(JEQ, NR_MMAP, "mmap"); op(JEQ, NR_MPROTECT, "mprot"); op(JEQ, NR_PKEY_MPROTECT, "mprot")
op(JEQ, NR_SHMAT, "shmat"); op(JEQ, NR_SOCKET, "socket")
op(RET, ALLOW)
label("mmap"); op(LD, 32); op(AND, PROT_WRITE | PROT_EXEC)
op(JEQ, PROT_WRITE | PROT_EXEC, "deny", "allow")
label("mprot"); op(LD, 32); op(AND, PROT_EXEC); op(JEQ, PROT_EXEC, "deny", "allow")
label("shmat"); op(LD, 32); op(AND, SHM_EXEC); op(JEQ, SHM_EXEC, "deny", "allow")
label("socket"); op(LD, 16)
for fam in FAMILIES: op(JEQ, fam, "allow")
op(RET, errno_ret(errno.EAFNOSUPPORT))
label("deny"); op(RET, errno_ret(errno.EPERM))
label("allow"); op(RET, ALLOW)
where, n = {}, 0
for c in code:
    if isinstance(c, str): where[c] = n
    else: n += 1
class Filter(ctypes.Structure):
    _fields_ = [("code", ctypes.c_uint16), ("jt", ctypes.c_uint8), ("jf", ctypes.c_uint8),
                ("k", ctypes.c_uint32)]
class Prog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.POINTER(Filter))]
insns, n = [], 0
for c in code:
    if isinstance(c, str): continue
    cc, jt, jf, k = c
    rel = lambda lab: 0 if lab is None else where[lab] - n - 1
    insns.append(Filter(cc, rel(jt), rel(jf), k)); n += 1
arr = (Filter * len(insns))(*insns)
libc = ctypes.CDLL(None, use_errno=True)
assert libc.prctl(38, 1, 0, 0, 0) == 0, "PR_SET_NO_NEW_PRIVS"
assert libc.prctl(22, 2, ctypes.byref(Prog(len(insns), arr)), 0, 0) == 0, "PR_SET_SECCOMP"

try:
    mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    sys.exit("the W^X filter is not active")
except PermissionError:
    pass
try:
    socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
    sys.exit("the address family filter is not active")
except OSError as exc:
    assert exc.errno == errno.EAFNOSUPPORT, exc

import threading
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
import pymodbus.client, serial, pydantic, typer
import rtde_control, rtde_receive, dashboard_client
import zenoh
from wristscan.daemon import config
from wristscan.daemon.io import calibfile
from wristscan.daemon.service import notify
from wristscan.daemon.cli.app import main
from wristscan.calib import kinematics, se3
assert np.linalg.svd(np.random.default_rng(0).random((64, 64)))[1][0] > 0
assert np.allclose(least_squares(lambda p: p - 3.0, np.zeros(3)).x, 3.0)
assert np.allclose(Rotation.from_rotvec([0, 0, 1]).as_matrix(), se3.rot_z(1.0))
kinematics.inverse("UR5e", kinematics.forward("UR5e", [0.3, -1.9, 1.9, -1.57, -1.57, 0.2]))
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
conf.insert_json5("scouting/multicast/enabled", "false")
got = threading.Event()
with zenoh.open(conf) as session:
    sub = session.declare_subscriber("wristscan/test", lambda sample: got.set())
    session.put("wristscan/test", bytes(200_000))
    assert got.wait(10), "no zenoh sample"
    sub.undeclare()
assert main(["check-config", "--default"]) == 0
print("sandboxed ok")
"""


@pytest.mark.slow
def test_the_daemon_libraries_run_under_the_units_memory_and_socket_rules() -> None:
    """Why MemoryDenyWriteExecute=yes is on: numpy, scipy, ur_rtde, zenoh and pymodbus run
    under the same seccomp rules (no library needs writable+executable memory, e.g. a JIT)."""
    if sys.platform != "linux" or not hasattr(socket, "AF_PACKET"):
        pytest.fail("this check needs Linux")
    import platform

    assert platform.machine() == "x86_64", "the seccomp filter in this test is written for x86-64"
    s = unit_settings()
    assert s["Service.MemoryDenyWriteExecute"] == ["yes"]
    families = [
        int(getattr(socket, name)) for name in s["Service.RestrictAddressFamilies"][0].split()
    ]
    done = subprocess.run(
        [sys.executable, "-c", _SANDBOXED_CHILD, ",".join(map(str, families))],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "sandboxed ok"
