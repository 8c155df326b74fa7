"""The scan job's errors: it cannot run or failed (:class:`ScanError`), its plan was refused
before anything moved (:class:`PlanRejected`), it stopped part way (:class:`ScanAborted`), or
the optional surface reconstruction is not installed (:class:`SurfaceUnavailable`). They
subclass the procedures' errors, so the CLI catches one base."""

from __future__ import annotations

from collections.abc import Sequence

from wristscan.daemon.procedure.errors import ProcedureAborted, ProcedureError

__all__ = ["PlanRejected", "ScanAborted", "ScanError", "SurfaceUnavailable"]


class ScanError(ProcedureError):
    """A scan job cannot run or failed; the message says why."""


class PlanRejected(ScanError):
    """The plan failed its checks before anything moved; ``problems`` lists them."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        super().__init__(
            "the plan was refused before anything moved:\n" + "\n".join(f"  {p}" for p in problems)
        )


class ScanAborted(ScanError, ProcedureAborted):
    """The scan stopped part way (protective stop, refused move, lost device, Ctrl-C); the robot
    and the table were stopped."""


class SurfaceUnavailable(ScanError):
    """The optional surface reconstruction library is not installed."""
