"""The ``[service]`` section: how ``wristscan run`` starts and watches its devices.

At start the daemon opens its zenoh session first, then its devices; a device that is not there
yet (a controller still booting, a sensor without power) is retried with exponential backoff,
from ``retry_initial_s`` doubling up to ``retry_max_s`` between attempts, for at most
``wait_for_devices_s`` (0: one attempt, then exit 1). While it waits, systemd STATUS and
``<prefix>/status`` say what it waits for and the watchdog is pinged. A device that delivers no
record for ``outage_after_s`` once open is an outage: logged once when it starts and once, with
its duration, when it ends.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from wristscan.daemon.config.values import Float, StrictModel, cross_field

__all__ = ["ServiceConfig"]


class ServiceConfig(StrictModel):
    wait_for_devices_s: Annotated[Float, Field(ge=0, le=86400)] = 120.0
    """How long to wait at start for devices that cannot be opened yet (0: do not wait)."""
    retry_initial_s: Annotated[Float, Field(gt=0, le=60)] = 0.25
    """First delay between two attempts to open a missing device (doubled after each failure)."""
    retry_max_s: Annotated[Float, Field(gt=0, le=60)] = 2.0
    """Longest delay between two attempts: a device that comes up is open within this."""
    outage_after_s: Annotated[Float, Field(gt=0, le=3600)] = 1.0
    """A device that delivers nothing for this long is in an outage (logged, shown in status)."""

    @model_validator(mode="after")
    def _retry_order(self) -> ServiceConfig:
        if self.retry_initial_s > self.retry_max_s:
            raise cross_field(
                "retry_initial_s",
                f"must not exceed retry_max_s ({self.retry_initial_s:g} > {self.retry_max_s:g})",
            )
        return self
