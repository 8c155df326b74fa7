"""The procedures' errors, one tree: a procedure cannot run or failed (:class:`ProcedureError`,
the message tells the operator why), or it was stopped part way (:class:`ProcedureAborted`: the
robot and the table were stopped, nothing was written). Each procedure's own errors subclass
these, so the CLI and the tests catch one base."""

from __future__ import annotations

__all__ = ["BallNotFound", "MotionNotConfirmed", "ProcedureAborted", "ProcedureError"]


class ProcedureError(RuntimeError):
    """A procedure cannot run, or failed; the message tells the operator why."""


class MotionNotConfirmed(ProcedureError):
    """Motion is not enabled in the configuration, or was not confirmed: nothing moved."""


class ProcedureAborted(ProcedureError):
    """The procedure stopped part way (protective stop, refused move, lost device, Ctrl-C).
    The robot and the table were stopped; nothing was written."""


class BallNotFound(ProcedureError):
    """A sweep saw no ball (or too little of it to fit)."""
