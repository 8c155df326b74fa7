"""The sensor calibration's two errors, in the procedures' one tree
(:mod:`wristscan.daemon.procedure.errors`): the command line tells the operator "failed" (the
data or the set-up cannot give a calibration) apart from "aborted" (the procedure was stopped);
in both cases nothing was written."""

from __future__ import annotations

from wristscan.daemon.procedure.errors import ProcedureAborted, ProcedureError

__all__ = ["CalibrationAborted", "CalibrationFailed"]


class CalibrationFailed(ProcedureError):
    """The procedure cannot produce a calibration (the ball is not in view, too few reachable
    orientations, the data do not constrain the result...); the message says what to do."""


class CalibrationAborted(ProcedureAborted):
    """The procedure was stopped: a protective stop, a failed or refused motion, the operator.
    Nothing was written; the calibration in force is unchanged."""
