""":meth:`Pairer.poll <wristscan.daemon.sync.pairing.Pairer.poll>` for the usual tick: every
pending profile can be paired now (one sensor epoch, clocks locked, robot states covering every
exposure, no table), so the batches are made without the per-profile status arrays.

The arithmetic of such a tick, the sensor times mapped onto the host clock
(``ClockMapper.to_host``, ``uncertainty_ns``), back onto the controller clock (``to_device``)
and located among the robot samples (``SampleBuffer._locate``), is one compiled call when the
kernels are in use (:mod:`wristscan.calib.jit_clock`: the same bits), else those numpy steps;
and the poses (``kinematics.forward_between``: the kernel ends with that one's).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit
from wristscan.calib.kinematics_small import MATMUL_MAX, dh_table
from wristscan.daemon.sync.batch import PairedBatch

if TYPE_CHECKING:
    from wristscan.daemon.sync.clockmap import ClockMapper
    from wristscan.daemon.sync.pairing import Pairer

__all__ = ["poll_all_ready"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

_NO_ROWS = np.zeros(0, dtype=np.int64)


def poll_all_ready(pairer: Pairer) -> list[PairedBatch] | None:
    """The poll's batches when every pending profile can be paired now; None (nothing done)
    otherwise."""
    pend = pairer._pending
    key = pend.single_key()
    cfg = pairer.config
    robot_clock = pairer.robot_clock
    if key is None or cfg.mode != "clock" or cfg.use_table or not robot_clock.locked:
        return None
    clk = pairer._sensor_clocks[key[0]]
    if not clk.is_locked(key[1]):
        return None
    x = pend.x
    got = _mapped_compiled(clk, key[1], robot_clock, pairer, x)
    if got is None:
        got = _mapped_numpy(clk, key[1], robot_clock, pairer, x)
    if got is None:
        return None
    exposure, unc, F, ordered = got
    pairer._need_ns = {}
    pairer.waiting_for_states = 0
    P = int(x.shape[0])
    step = cfg.max_batch_profiles
    sels: list[slice] | list[IntArray]
    if ordered:
        # In exposure order already (the usual tick): the batches take slices of this
        # poll's arrays, not copies (the stable sort would keep this order).
        sels = [slice(k, min(k + step, P)) for k in range(0, P, step)]
    else:
        ready = np.argsort(exposure, kind="stable")
        sels = [ready[k : k + step] for k in range(0, P, step)]
    host = pend.host
    batches = [pairer._batch(sel, exposure, unc, F, None, host) for sel in sels]
    pairer.paired += P
    pairer.batches += len(batches)
    pend.keep(_NO_ROWS)
    return batches


Mapped = tuple[IntArray, FloatArray, FloatArray, bool]
"""Exposures, their clock uncertainties, ``flange2base`` and whether in exposure order."""


def _mapped_numpy(
    clk: ClockMapper, epoch: int, robot_clock: ClockMapper, pairer: Pairer, x: IntArray
) -> Mapped | None:
    exposure = clk.to_host(x, epoch)
    t_robot = robot_clock.to_device(exposure)
    F = pairer.robot.poses_if_covered(t_robot)
    if F is None:
        return None
    unc = clk.uncertainty_ns(x, epoch)
    ordered = x.shape[0] == 1 or bool((exposure[1:] >= exposure[:-1]).all())
    return exposure, unc, F, ordered


def _mapped_compiled(
    clk: ClockMapper, epoch: int, robot_clock: ClockMapper, pairer: Pairer, x: IntArray
) -> Mapped | None:
    """:func:`_mapped_numpy` in one kernel call, the poses included; None when the kernels are
    not in use, the robot buffer holds fewer than two samples or the poses are more than
    ``forward_between`` computes compiled (the numpy steps decide)."""
    kern = jit.kernel("map_locate")
    buf = pairer.robot.buffer
    if kern is None or len(buf) < 2 or pairer.robot.mode != "joint" or x.shape[0] > MATMUL_MAX:
        return None
    s, r = clk._get_line(epoch), robot_clock._get_line(None)
    P = int(x.shape[0])
    exposure = np.empty(P, dtype=np.int64)
    unc = np.empty(P)
    rows = np.empty(P, dtype=np.int64)
    frac = np.empty(P)
    F = np.empty((P, 4, 4))
    ok, ordered = kern(
        x,
        # Tuples (no arrays made) of the types the kernel was compiled for.
        (float(s.a), float(s.d), float(s.x_e), float(s.u0**2), float(s.u_slope)),
        (int(s.x_ref), int(s.y_ref - clk.config.latency_ns)),
        (float(r.a), float(1.0 + r.d)),
        (int(robot_clock.config.latency_ns - r.y_ref), int(r.x_ref)),
        buf.times,
        buf.max_gap_ns,
        exposure,
        unc,
        rows,
        frac,
        buf.values,
        dh_table(pairer.robot.model),
        F,
    )
    return (exposure, unc, F, bool(ordered)) if ok else None
