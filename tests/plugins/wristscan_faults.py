"""Deliberate faults for ``benchmarks/mutations.py``, applied from outside the code under test.

Nothing in wristscan knows about this module. ``benchmarks/mutations.py`` writes a
``sitecustomize.py`` into a temporary folder and puts that folder first on ``PYTHONPATH``; every
Python process a test run starts (pytest itself, the daemon ``python -m wristscan.daemon.cli run``,
the CLI commands, the simulated devices in their spawned processes) then runs it at start-up.
When ``WRISTSCAN_FAULT`` names a fault, it imports this module and calls
:func:`install_from_environment`, which hooks the import system: right after a wristscan module
named in :data:`FAULTS` has executed (before any other module has imported names from it), the
fault replaces one function or method there. The code under test is never edited.

``WRISTSCAN_FAULT=<name>`` applies a fault at its documented size, ``<name>=<size>`` at another
(in the fault's unit). ``WRISTSCAN_FAULT_LOG=<file>``: every process appends a line when it
patches a module (``patched``) and, once per process and test, when the patched code is used
(``used``, with the test from ``PYTEST_CURRENT_TEST``, which the processes a test starts inherit),
so that a fault no test caught can be told from one never exercised, and a test that failed
without using the fault from one that caught it.

The faults and their seams (see docs/mutations.md):

* ``latency``: ``[sensor] latency_s`` as configured, 1 ms too large. Seam: every configuration is
  validated by ``wristscan.daemon.config.loading.parse_config`` (``load_config`` and
  ``load_default`` call it); the wrapper adds the error to the validated ``Config``, so the
  daemon, the procedures and their reports all see the wrong figure, as with a wrong file.
* ``s2f-shift`` / ``s2f-rot``: the sensor calibration in force off by 0.1 mm along, or rotated by
  0.05 deg about, the sensor frame's diagonal (1, 1, 1)/sqrt(3) (no direction favoured). Seam:
  the calibration reads of the consumers, ``read_calibration`` as bound in
  ``wristscan.daemon.procedure.in_force`` (every procedure) and ``wristscan.daemon.service.setup``
  (the daemon). A test that reads a file back with ``read_calibration`` itself reads it as written.
* ``encoder``: the table calibration's ``encoder_offset_rad`` in force off by 0.05 deg (same seam).
* ``nearest``: the robot state taken at the nearest sample instead of interpolated. Seam:
  ``RobotStateBuffer.__init__`` in ``wristscan.daemon.sync.buffers`` gives each robot buffer a
  ``locate`` and a ``_locate`` (what its interpolation calls) whose fraction is rounded to 0 or 1;
  the usual tick's compiled location (``wristscan.daemon.sync.readytick._mapped_compiled``)
  declines, so that tick goes through them too.
* ``drift``: the sensor clock's drift ignored (the mapping's slope forced to 1, the offset still
  fitted). Seam: ``wristscan.daemon.sync.envelope.support_slope`` answers 0, and the fit's
  compiled slope searches (``envelope._searches``) answer as it would, while a sensor clock's
  ``ClockMapper._refit`` runs (``wristscan.daemon.sync.clockmap``); robot and table clocks are
  left alone.
* ``kinematics``: the robot's nominal kinematics instead of its calibrated model (today the
  factory calibration the controller reports in KinematicsInfo; the kinematic identification of
  a later issue will add its own). Seam: ``wristscan.daemon.devices.robot_model`` (what the
  daemon and the procedures pair with) answers the configured model name whenever it would have
  answered a calibrated model.
"""

from __future__ import annotations

import dataclasses
import importlib.abc
import importlib.machinery
import math
import os
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

ENV = "WRISTSCAN_FAULT"
LOG_ENV = "WRISTSCAN_FAULT_LOG"

Patch = Callable[[Any, float], None]
"""Patches a module (typed Any: its attributes are the code under test's)."""


@dataclass(frozen=True)
class Fault:
    """One deliberate fault: what it breaks, its size, and the modules it patches."""

    name: str
    what: str
    size: float
    unit: str
    patches: dict[str, Patch]
    """Module name -> function patching that module (called with the module and the size)."""
    pending: str = ""
    """Why it cannot be applied yet (empty: it can)."""


# --------------------------------------------------------------------------------------------
# Bookkeeping: what was patched and used, in which process


_used: set[str] = set()
_used_lock = threading.Lock()


def _current_test() -> str:
    """The test running in this process or in the one that started it (pytest sets
    ``PYTEST_CURRENT_TEST``; the daemon, CLI and device processes a test starts inherit it)."""
    return os.environ.get("PYTEST_CURRENT_TEST", "").rpartition(" ")[0] or "-"


def _log(kind: str, what: str) -> None:
    """Append ``pid<TAB>kind<TAB>what<TAB>test`` to the log file, if one is named."""
    path = os.environ.get(LOG_ENV)
    if not path:
        return
    line = f"{os.getpid()}\t{kind}\t{what}\t{_current_test()}\n".encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, line)
    finally:
        os.close(fd)


def _note_use(site: str) -> None:
    """Log the first use of a patched ``site`` per process and test."""
    key = f"{site}\t{_current_test()}"
    with _used_lock:
        if key in _used:
            return
        _used.add(key)
    _log("used", site)


# --------------------------------------------------------------------------------------------
# The patches


def _patch_latency(mod: Any, size: float) -> None:
    original = mod.parse_config

    def parse_config(text: str, source: str = "<config>", base_dir: Any = None) -> Any:
        cfg = original(text, source, base_dir)
        sensor = cfg.sensor.model_copy(update={"latency_s": cfg.sensor.latency_s + size})
        out = cfg.model_copy(update={"sensor": sensor})
        out._source = cfg.source
        _note_use("config [sensor] latency_s")
        return out

    mod.parse_config = parse_config


def _diagonal() -> np.ndarray:
    return np.ones(3) / math.sqrt(3.0)


def _perturb_s2f_shift(calib: Any, size: float) -> Any:
    if calib.kind != "sensor2flange":
        return calib
    D = np.eye(4)
    D[:3, 3] = size * _diagonal()
    _note_use("sensor2flange in force (shift)")
    return dataclasses.replace(calib, transform=np.asarray(calib.transform) @ D)


def _perturb_s2f_rot(calib: Any, size: float) -> Any:
    if calib.kind != "sensor2flange":
        return calib
    from scipy.spatial.transform import Rotation

    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(math.radians(size) * _diagonal()).as_matrix()
    _note_use("sensor2flange in force (rotation)")
    return dataclasses.replace(calib, transform=np.asarray(calib.transform) @ D)


def _perturb_encoder(calib: Any, size: float) -> Any:
    if calib.kind != "table":
        return calib
    params = dict(calib.parameters)
    params["encoder_offset_rad"] = params.get("encoder_offset_rad", 0.0) + math.radians(size)
    _note_use("table encoder_offset_rad in force")
    return dataclasses.replace(calib, parameters=params)


def _calibration_reads(perturb: Callable[[Any, float], Any]) -> Patch:
    """A patch of a consumer module's ``read_calibration`` (the name it imported)."""

    def patch(mod: Any, size: float) -> None:
        original = mod.read_calibration

        def read_calibration(*args: Any, **kwargs: Any) -> Any:
            return perturb(original(*args, **kwargs), size)

        mod.read_calibration = read_calibration

    return patch


def _patch_nearest(mod: Any, size: float) -> None:
    del size
    cls = mod.RobotStateBuffer
    original_init = cls.__init__

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        buf = self._buf
        locate, locate_all = buf.locate, buf._locate

        def nearest(t_ns: Any) -> Any:
            i, s, reason = locate(t_ns)
            _note_use("robot state at the nearest sample")
            return i, np.rint(s), reason

        def nearest_all(t_ns: Any) -> Any:  # what interpolation uses (issue 21)
            i, s, reason, all_ok = locate_all(t_ns)
            _note_use("robot state at the nearest sample")
            return i, np.rint(s), reason, all_ok

        buf.locate = nearest
        buf._locate = nearest_all

    cls.__init__ = init


def _patch_compiled_locate(mod: Any, size: float) -> None:
    """The usual tick's compiled mapping and location (issue 21, ``readytick``) declines, so the
    tick takes the numpy steps, whose location the buffer's patched ``_locate`` gives."""
    del size
    mod._mapped_compiled = lambda *args, **kwargs: None


def _patch_robot_model(mod: Any, size: float) -> None:
    del size
    original = mod.robot_model

    def robot_model(cfg: Any, devices: Any) -> Any:
        model = original(cfg, devices)
        if not isinstance(model, str):
            # The calibrated model was in force: pair with the nominal table instead.
            _note_use("nominal kinematics instead of the calibrated model")
            return cfg.robot.model
        return model

    mod.robot_model = robot_model


_zero_slope = threading.local()


def _patch_support_slope(mod: Any, size: float) -> None:
    del size
    original = mod.support_slope

    def support_slope(*args: Any, **kwargs: Any) -> float:
        if getattr(_zero_slope, "on", False):
            _note_use("sensor clock slope forced to 1")
            return 0.0
        return float(original(*args, **kwargs))

    mod.support_slope = support_slope
    original_searches = mod._searches

    def searches(X: Any, R: Any, *args: Any, **kwargs: Any) -> Any:
        # The fit's five slope searches in one compiled call (issue 21) bypass
        # support_slope: the same answers as five zeros from it.
        if getattr(_zero_slope, "on", False):
            _note_use("sensor clock slope forced to 1")
            v1, v2 = float(R[0::2].min()), float(R[1::2].min())
            return 0.0, 0.0, 0.0, v1, v2, (0.0, 0.0)
        return original_searches(X, R, *args, **kwargs)

    mod._searches = searches


def _patch_sensor_refit(mod: Any, size: float) -> None:
    del size
    cls = mod.ClockMapper
    original = cls._refit

    def _refit(self: Any) -> None:
        if not str(self.name).startswith("sensor"):
            original(self)
            return
        _zero_slope.on = True
        try:
            original(self)
        finally:
            _zero_slope.on = False

    cls._refit = _refit


_IN_FORCE = "wristscan.daemon.procedure.in_force"
_RUNTIME = "wristscan.daemon.service.setup"

FAULTS: dict[str, Fault] = {
    f.name: f
    for f in (
        Fault(
            "latency",
            "[sensor] latency_s configured 1 ms too large",
            0.001,
            "s",
            {"wristscan.daemon.config.loading": _patch_latency},
        ),
        Fault(
            "s2f-shift",
            "sensor2flange in force off by 0.1 mm (along the sensor frame's diagonal)",
            0.1e-3,
            "m",
            {m: _calibration_reads(_perturb_s2f_shift) for m in (_IN_FORCE, _RUNTIME)},
        ),
        Fault(
            "s2f-rot",
            "sensor2flange in force rotated by 0.05 deg (about the sensor frame's diagonal)",
            0.05,
            "deg",
            {m: _calibration_reads(_perturb_s2f_rot) for m in (_IN_FORCE, _RUNTIME)},
        ),
        Fault(
            "nearest",
            "robot state taken at the nearest sample instead of interpolated",
            0.0,
            "",
            {
                "wristscan.daemon.sync.buffers": _patch_nearest,
                "wristscan.daemon.sync.readytick": _patch_compiled_locate,
            },
        ),
        Fault(
            "drift",
            "sensor clock drift ignored (the clock mapping's slope forced to 1)",
            0.0,
            "",
            {
                "wristscan.daemon.sync.envelope": _patch_support_slope,
                "wristscan.daemon.sync.clockmap": _patch_sensor_refit,
            },
        ),
        Fault(
            "encoder",
            "table encoder offset in force off by 0.05 deg",
            0.05,
            "deg",
            {m: _calibration_reads(_perturb_encoder) for m in (_IN_FORCE, _RUNTIME)},
        ),
        Fault(
            "kinematics",
            "the robot's nominal kinematics instead of its calibrated model",
            0.0,
            "",
            {"wristscan.daemon.devices": _patch_robot_model},
        ),
    )
}


# --------------------------------------------------------------------------------------------
# Applying a fault at import time


class _AfterImport(importlib.abc.MetaPathFinder):
    """Runs a patch on a module right after it has executed, before anyone imports from it."""

    def __init__(self, patches: dict[str, Callable[[ModuleType], None]]) -> None:
        self.patches = patches
        self._busy = threading.local()

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        patch = self.patches.get(fullname)
        if patch is None or getattr(self._busy, "on", False):
            return None
        self._busy.on = True
        try:
            spec = None
            for finder in sys.meta_path:
                find = getattr(finder, "find_spec", None)
                if finder is self or find is None:
                    continue
                spec = find(fullname, path, target)
                if spec is not None:
                    break
        finally:
            self._busy.on = False
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        loader: Any = spec.loader
        execute = loader.exec_module

        def exec_module(module: ModuleType) -> None:
            execute(module)
            patch(module)
            _log("patched", fullname)

        loader.exec_module = exec_module
        return spec


def _bind(patch: Patch, size: float) -> Callable[[ModuleType], None]:
    return lambda module: patch(module, size)


def install(name: str, size: float | None = None) -> Fault:
    """Apply fault ``name`` (at ``size``, default the documented one) to this process."""
    if name not in FAULTS:
        raise ValueError(f"{ENV}: unknown fault {name!r} (known: {', '.join(FAULTS)})")
    fault = FAULTS[name]
    if fault.pending:
        raise ValueError(f"{ENV}: fault {name!r} is pending: {fault.pending}")
    value = fault.size if size is None else size
    bound: dict[str, Callable[[ModuleType], None]] = {
        mod: _bind(p, value) for mod, p in fault.patches.items()
    }
    for mod, apply in list(bound.items()):
        if mod in sys.modules:  # already imported (not at start-up; an explicit install)
            apply(sys.modules[mod])
            _log("patched", mod)
            del bound[mod]
    if bound:
        sys.meta_path.insert(0, _AfterImport(bound))
    return fault


def install_from_environment() -> Fault | None:
    """Apply the fault ``WRISTSCAN_FAULT`` names (``name`` or ``name=size``), if any."""
    spec = os.environ.get(ENV, "").strip()
    if not spec:
        return None
    name, _, size = spec.partition("=")
    return install(name.strip(), float(size) if size.strip() else None)


SITECUSTOMIZE = '''"""Written by benchmarks/mutations.py: applies WRISTSCAN_FAULT."""
import os
import sys

if os.environ.get("WRISTSCAN_FAULT"):
    sys.path.insert(0, {plugins!r})
    try:
        import wristscan_faults
    finally:
        sys.path.remove({plugins!r})
    wristscan_faults.install_from_environment()
'''
"""The ``sitecustomize.py`` that reaches every process (``plugins``: this module's folder)."""


def write_sitecustomize(folder: str | os.PathLike[str]) -> str:
    """Write the ``sitecustomize.py`` into ``folder``; returns the folder (for PYTHONPATH)."""
    path = os.path.join(os.fspath(folder), "sitecustomize.py")
    plugins = os.path.dirname(os.path.abspath(__file__))
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(SITECUSTOMIZE.format(plugins=plugins))
    return os.fspath(folder)
