"""The stable public import path of the subscriber API::

    from wristscan.daemon.client import CloudClient

The implementation lives in :mod:`wristscan.daemon.cloud.client`, beside the WSC1 codec and the
daemon's zenoh side; this module keeps the documented path working wherever that code moves.
It exports what that module exports: :class:`CloudClient`, ``Wsc1Error`` (the WSC1 codec's
error for a malformed payload) and ``ZenohSetupError`` (a session that cannot be opened: bad
endpoint, zenoh security file, certificate or password; one line).
"""

from wristscan.daemon.cloud.client import CloudClient, Wsc1Error, ZenohSetupError

__all__ = ["CloudClient", "Wsc1Error", "ZenohSetupError"]
