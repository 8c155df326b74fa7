"""Dashboard server replies (TCP 29999) of the simulated UR controller.

Text protocol: one command per line, one reply line each (UR's "Dashboard Server e-Series" manual
gives the replies reproduced here). ur_rtde's ``DashboardClient`` compares several replies
verbatim ("Starting program", "Stopped", "Protective stop releasing"), so they are kept exact.
"""

from __future__ import annotations

from typing import Protocol

__all__ = ["WELCOME", "DashboardTarget", "reply"]

WELCOME = "Connected: Universal Robots Dashboard Server"

ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
}
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
}
RUNTIME_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED"}


class DashboardTarget(Protocol):
    """What the dashboard needs from the controller."""

    version: tuple[int, int, int, int]
    serial_number: str
    model_name: str
    robot_mode: int
    safety_mode: int
    runtime_state: int
    program_name: str
    loaded_program: str | None

    def power_on(self) -> None: ...
    def power_off(self) -> None: ...
    def brake_release(self) -> None: ...
    def unlock_protective_stop(self) -> bool: ...
    def play(self) -> bool: ...
    def pause(self) -> bool: ...
    def stop_program(self) -> None: ...


_FIXED_REPLIES = {
    "is in remote control": "true",
    "close safety popup": "closing safety popup",
    "close popup": "closing popup",
    "get operational mode": "NONE",
    "clear operational mode": "No longer controlling the operational mode. ",
    "restart safety": "Restarting safety",
}
"""Commands answered the same whatever the controller's state."""
_CLOSING_REPLIES = {"shutdown": "Shutting down", "quit": "Disconnected"}
"""Commands after whose reply the server closes the connection."""
_PREFIX_REPLIES = (("popup ", "showing popup"), ("addtolog ", "Added log message"))
"""Commands with an argument, answered the same whatever it is."""


def reply(target: DashboardTarget, line: str) -> tuple[str, bool]:
    """Reply to one command line; the flag asks to close the connection after replying."""
    cmd = line.strip()
    low = cmd.lower()
    if low in _FIXED_REPLIES:
        return _FIXED_REPLIES[low], False
    if low in _CLOSING_REPLIES:
        return _CLOSING_REPLIES[low], True
    for prefix, text in _PREFIX_REPLIES:
        if low.startswith(prefix):
            return text, False
    answer = _query(target, low)
    if answer is None:
        answer = _command(target, cmd, low)
    return answer, False


def _query(target: DashboardTarget, low: str) -> str | None:
    """The reply to a question about the controller, or None for another command."""
    major, minor, bugfix, build = target.version
    if low == "polyscopeversion":
        return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2024)"
    if low == "version":
        return f"{major}.{minor}.{bugfix}.{build}"
    if low == "get serial number" and not (major == 5 and minor < 6):  # e-Series: from 5.6
        return target.serial_number
    if low == "get robot model":
        # The dashboard names the arm family without the e-Series suffix.
        return target.model_name.rstrip("e")
    if low == "robotmode":
        return f"Robotmode: {ROBOT_MODES.get(target.robot_mode, 'UNKNOWN')}"
    if low == "safetystatus":
        return f"Safetystatus: {SAFETY_MODES.get(target.safety_mode, 'FAULT')}"
    if low == "safetymode":
        return f"Safetymode: {SAFETY_MODES.get(target.safety_mode, 'FAULT')}"
    if low == "programstate":
        state = RUNTIME_STATES.get(target.runtime_state, "STOPPED")
        return f"{state} {target.program_name or '<unnamed>'}"
    if low == "running":
        return f"Program running: {'true' if target.runtime_state == 2 else 'false'}"
    if low == "get loaded program":
        if target.loaded_program:
            return f"Loaded program: {target.loaded_program}"
        return "No program loaded"
    if low == "isprogramsaved":
        return f"true {target.program_name or '<unnamed>'}"
    return None


def _command(target: DashboardTarget, cmd: str, low: str) -> str:
    """The reply to a command that acts on the controller (or to an unknown one)."""
    if low == "unlock protective stop":
        if target.unlock_protective_stop():
            return "Protective stop releasing"
        return (
            "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of "
            "protective stop before unlocking"
        )
    if low == "power on":
        target.power_on()
        return "Powering on"
    if low == "power off":
        target.power_off()
        return "Powering off"
    if low == "brake release":
        target.brake_release()
        return "Brake releasing"
    if low.startswith("load "):
        name = cmd[5:].strip()
        target.loaded_program = name
        return f"Loading program: {name}"
    if low == "play":
        return "Starting program" if target.play() else "Failed to execute: play"
    if low == "pause":
        return "Pausing program" if target.pause() else "Failed to execute: pause"
    if low == "stop":
        target.stop_program()
        return "Stopped"
    return f"could not understand: '{cmd}'"
