"""Progress of a procedure, as events: the CLI prints them, a test or a GUI collects them.

A procedure takes ``progress: Progress | None`` and reports through it what it is doing; the
callback must not raise or block (it runs on the procedure's thread between motions).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["Progress", "ProgressEvent", "StepReport", "no_progress", "stage_reporter"]


@dataclass(frozen=True)
class ProgressEvent:
    """What a procedure is doing: ``stage`` (``connect``, ``find``, ``sweep``, ``pass``...),
    ``step`` of ``total`` within it (0 of 0 when not counted) and a one-line message."""

    stage: str
    step: int
    total: int
    message: str

    def __str__(self) -> str:
        count = f" {self.step}/{self.total}" if self.total else ""
        return f"[{self.stage}{count}] {self.message}"


Progress = Callable[[ProgressEvent], None]
"""Progress callback of a procedure."""


def no_progress(event: ProgressEvent) -> None:
    """The :data:`Progress` callback of a caller that does not follow the progress."""


StepReport = Callable[[int, int, str], None]
"""``report(step, total, message)`` within one stage, as :func:`stage_reporter` makes it."""


def stage_reporter(progress: Progress | None, stage: str) -> StepReport:
    """``report(step, total, message)`` sending :class:`ProgressEvent` of ``stage`` to
    ``progress`` (nothing when it is None): the shape most procedure loops count in."""
    sink = progress or no_progress

    def report(step: int, total: int, message: str) -> None:
        sink(ProgressEvent(stage, step, total, message))

    return report
