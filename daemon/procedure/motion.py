"""Moving the robot inside a procedure: the checks before (:func:`require_motion`), the one guard
around every motion (:func:`guarded_motion`) and the wait until profiles are being paired
(:func:`wait_until_pairing`).

Safety rules every procedure shares: nothing moves unless ``[robot] motion_enabled`` is set and
the caller confirmed (the CLI's ``--yes``); any failure while moving (protective stop, refused
move, lost link, Ctrl-C) stops the robot (and the table) before the error reaches the caller.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from wristscan.daemon.config import Config
from wristscan.daemon.procedure.errors import MotionNotConfirmed, ProcedureAborted, ProcedureError
from wristscan.drivers.base import DriverError

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Acquisition

__all__ = ["clock_epochs", "guarded_motion", "require_motion", "wait_until_pairing"]

log = logging.getLogger(__name__)

SETTLE_TIMEOUT_S = 20.0
"""How long :func:`wait_until_pairing` waits by default for the first paired profiles (s)."""

NOTHING_WRITTEN = "nothing was written, the calibration in force stays"


def require_motion(cfg: Config, confirmed: bool) -> None:
    """Refuse (:class:`MotionNotConfirmed`) unless motion is enabled in ``cfg`` and confirmed."""
    if not cfg.robot.motion_enabled:
        raise MotionNotConfirmed(
            f"{cfg.source}: [robot] motion_enabled is false: this procedure moves the robot; "
            "enable motion in the configuration (with speed and workspace limits) first"
        )
    if not confirmed:
        raise MotionNotConfirmed(
            "this procedure moves the robot: confirm with --yes (check that the workspace is "
            "clear and the limits in the configuration are right)"
        )


@contextmanager
def guarded_motion(
    acq: Acquisition,
    what: str,
    *,
    error: Callable[[str], BaseException] = ProcedureAborted,
    also: tuple[type[BaseException], ...] = (ProcedureAborted,),
    consequence: str = NOTHING_WRITTEN,
    table: bool = True,
) -> Iterator[None]:
    """Stop the robot (and, with ``table``, the table) when anything escapes the block.

    A driver error, Ctrl-C or an exception of the types ``also`` is then raised as
    ``error("{what} aborted: {reason}; {consequence}")`` from it (``reason`` is "interrupted"
    for Ctrl-C, else the error's text); anything else (a procedure's own error, which says what
    went wrong) is re-raised as it is, after the stop."""
    try:
        yield
    except BaseException as exc:
        acq.stop_motion(table=table)
        if not isinstance(exc, (DriverError, KeyboardInterrupt, *also)):
            raise
        reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else str(exc)
        raise error(f"{what} aborted: {reason}; {consequence}") from exc


def clock_epochs(stats: dict[str, Any]) -> tuple[Any, ...]:
    """Clock epochs of the synchroniser in ``acq.stats()``: a change means a clock fit
    restarted."""
    p = stats.get("pairing", {})
    robot = p.get("robot_clock", {}).get("epoch")
    sensors = tuple(sorted((k, v.get("epoch")) for k, v in p.get("sensor_clocks", {}).items()))
    return (robot, sensors)


def wait_until_pairing(
    acq: Acquisition, timeout_s: float = SETTLE_TIMEOUT_S, stable_s: float = 1.5
) -> None:
    """Wait until robot states arrive, profiles are being paired, and no clock fit restarted
    for ``stable_s`` (a fit is least sure just after it locked). Raises :class:`ProcedureError`
    when nothing is paired in ``timeout_s``; a clock that keeps restarting only costs the
    timeout (the sweeps check again)."""
    deadline = time.monotonic() + timeout_s
    first: int | None = None
    flowing = False
    epochs: tuple[Any, ...] | None = None
    since = time.monotonic()
    while time.monotonic() < deadline:
        failure = acq.pipeline.failure
        if failure is not None:
            raise ProcedureError(f"acquisition failed: {failure}")
        if acq.robot.latest_state() is not None:
            stats = acq.stats()
            paired = int(stats.get("pairing", {}).get("paired", 0))
            if first is None:
                first = paired
            flowing = flowing or paired > first + 20
            now_epochs = clock_epochs(stats)
            if now_epochs != epochs:
                epochs, since = now_epochs, time.monotonic()
            if flowing and time.monotonic() - since >= stable_s:
                return
        time.sleep(0.1)
    if not flowing:
        raise ProcedureError(
            f"no profiles were paired with robot states within {timeout_s:.0f} s: check that "
            "the sensor streams and the robot is connected (wristscan run shows the counters)"
        )
    log.warning("the synchroniser's clock fits keep restarting (host overloaded?)")
