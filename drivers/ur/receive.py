"""Native RTDE receive client: every data package, in order, each stamped when it arrived.

Why not ur_rtde's ``RTDEReceiveInterface``: it keeps only the newest packet and offers no way to
wait for the next one, so a reader has to poll (a fifth of a core at 500 Hz) and still loses the
samples that arrive while it is not scheduled. RTDE runs over TCP: a client that consumes the
stream itself loses nothing while it is starved (the kernel holds the packets; a controller drops
a client only after about 10 s of not reading) and sleeps in ``poll()`` in between.

Protocol version 2 (PROTOCOLS.md, "UR RTDE"): 'V' (version 2) -> accepted; 'v' -> controller
version; 'O' with the frequency and the variable names -> recipe id and types (``NOT_FOUND`` for
an unknown name); 'S' -> accepted; then 'U' data packages. 'M' text messages may come at any
time, during the handshake too: they are logged and kept (:attr:`RtdeReceiver.messages`).
:meth:`RtdeReceiver.close` sends 'P' (best effort) and closes the socket.

:meth:`RtdeReceiver.read` returns every data package received so far, oldest first, decoded in
one go (a NumPy structured view of their fields); :meth:`RtdeReceiver.read_payloads` hands out
the same undecoded, for a caller that converts each package itself. ``host_ns`` of a sample is
``time.monotonic_ns()`` right after the ``recv()`` that completed its packet: packets that
waited in the kernel while the reader was not scheduled share the stamp of the call that took
them in (the controller's own ``timestamp`` still tells them apart).

Units: whatever RTDE defines per variable (SI: s, rad, m, rad/s ...); ``frequency_hz`` in Hz,
timeouts in seconds.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers.base import DriverIOError
from wristscan.drivers.ur import rtde_wire as wire

__all__ = [
    "DEFAULT_PORT",
    "RtdeConnectError",
    "RtdeError",
    "RtdeHandshakeError",
    "RtdeLinkLost",
    "RtdeNotFound",
    "RtdeReceiver",
    "Samples",
    "TextMessage",
]

log = logging.getLogger(__name__)

DEFAULT_PORT = 30004
PROTOCOL_VERSION = 2
_CB3_MAJOR = 3
_E_SERIES_HZ = 500.0
_CB3_HZ = 125.0
_RECV_BYTES = 1 << 18
_MESSAGES_KEPT = 64
# Message levels of protocol 2: 0 exception, 1 error, 2 warning, 3 info.
_LOG_LEVEL = {0: logging.ERROR, 1: logging.ERROR, 2: logging.WARNING, 3: logging.INFO}
_PACKET_NAMES = {
    wire.REQUEST_PROTOCOL_VERSION: "'V' (protocol version)",
    wire.GET_URCONTROL_VERSION: "'v' (controller version)",
    wire.SETUP_OUTPUTS: "'O' (output setup)",
    wire.START: "'S' (start)",
}


class RtdeError(DriverIOError):
    """Any failure of the RTDE link."""


class RtdeConnectError(RtdeError):
    """The TCP connection could not be made (refused, unreachable, timed out)."""


class RtdeHandshakeError(RtdeError):
    """The controller refused or did not answer a step of the handshake."""


class RtdeNotFound(RtdeHandshakeError):
    """The controller does not know some of the requested variables (``names``)."""

    def __init__(self, message: str, names: Sequence[str]) -> None:
        super().__init__(message)
        self.names = tuple(names)


class RtdeLinkLost(RtdeError):
    """The established stream ended: connection closed or reset, no data for too long, or the
    byte stream is out of step."""


@dataclass(frozen=True)
class TextMessage:
    """An RTDE text message ('M') from the controller."""

    text: str
    source: str
    level: int
    """0 exception, 1 error, 2 warning, 3 info."""
    host_ns: int
    """``time.monotonic_ns()`` when it arrived."""


@dataclass(frozen=True)
class Samples:
    """Data packages in arrival order: ``values[name]`` has one row per package (vector
    variables as ``(n, k)``), in native byte order."""

    host_ns: NDArray[np.int64]
    """(n,) host ``time.monotonic_ns()`` when each package was received."""
    values: NDArray[np.void]
    """(n,) structured array, one field per variable of the recipe."""

    def __len__(self) -> int:
        return len(self.host_ns)

    def __getitem__(self, name: str) -> NDArray[Any]:
        return np.asarray(self.values[name])


class RtdeReceiver:
    """One RTDE output stream from a UR controller (``host:port``, TCP).

    ``variables``: RTDE output names (unique, at least one). ``frequency_hz``: output rate;
    None asks for the controller's maximum (500 Hz for an e-Series controller, major version > 3;
    125 Hz for CB3). ``connect_timeout_s`` bounds the TCP connect and, separately, the whole
    handshake; ``data_timeout_s``: no data package for that long counts as a lost link.
    Not thread-safe: one reader.
    """

    def __init__(
        self,
        host: str,
        variables: Sequence[str],
        frequency_hz: float | None = None,
        *,
        port: int = DEFAULT_PORT,
        connect_timeout_s: float = 5.0,
        data_timeout_s: float = 2.5,
    ) -> None:
        names = list(variables)
        if not names or not all(isinstance(n, str) and n and "," not in n for n in names):
            raise ValueError("variables must be one or more RTDE output names")
        if len(set(names)) != len(names):
            raise ValueError(f"variables must not repeat a name: {names}")
        if frequency_hz is not None and not 0.0 < frequency_hz <= _E_SERIES_HZ:
            raise ValueError(f"frequency_hz must be in (0, 500], got {frequency_hz}")
        if connect_timeout_s <= 0 or data_timeout_s <= 0:
            raise ValueError("timeouts must be positive")
        self.host = host
        self.port = port
        self.variables: tuple[str, ...] = tuple(names)
        self.requested_frequency_hz = frequency_hz
        self.connect_timeout_s = connect_timeout_s
        self.data_timeout_s = data_timeout_s

        self.controller_version: tuple[int, int, int, int] | None = None
        """``(major, minor, bugfix, build)`` once connected."""
        self.frequency_hz: float | None = None
        """The output rate asked for (Hz), once connected."""
        self.recipe: wire.Recipe | None = None
        self.messages: deque[TextMessage] = deque(maxlen=_MESSAGES_KEPT)
        """The latest text messages from the controller."""
        self.counters: dict[str, int] = {"packets": 0, "bytes": 0, "text_messages": 0, "ignored": 0}

        self._sock: socket.socket | None = None
        self._poller: select.poll | None = None
        self._rbuf = bytearray(_RECV_BYTES)
        self._buf = b""
        self._last_recv_ns = 0
        self._last_data_s = 0.0
        self._started = False
        self._header = b""
        self._packet_size = 0
        self._payloads = bytearray()  # field bytes of the data packages not handed out yet
        self._stamps: list[int] = []
        self._lost: RtdeLinkLost | None = None

    # ------------------------------------------------------------------ life cycle

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def open(self) -> Self:
        """Connect and run the handshake; raises :class:`RtdeConnectError`,
        :class:`RtdeHandshakeError` or :class:`RtdeNotFound`."""
        if self._sock is not None:
            return self
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except ConnectionRefusedError:
            raise RtdeConnectError(
                f"RTDE {self.address}: connection refused (controller off, or not a UR controller?)"
            ) from None
        except TimeoutError:
            raise RtdeConnectError(
                f"RTDE {self.address}: no answer within {self.connect_timeout_s:g} s"
            ) from None
        except OSError as exc:
            raise RtdeConnectError(f"RTDE {self.address}: cannot connect ({exc})") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(0.0)  # non-blocking: waits go through the poller, with our deadlines
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        self._sock, self._poller = sock, poller
        self._buf = b""
        self._started = False
        try:
            self._handshake(time.monotonic() + self.connect_timeout_s)
        except BaseException:
            self._drop()
            raise
        return self

    def close(self) -> None:
        """Send 'P' (pause) if possible and close the connection."""
        sock = self._sock
        if sock is None:
            return
        if self._started:
            try:
                sock.send(wire.encode(wire.PAUSE))
            except OSError:
                pass  # best effort: the controller handles a vanished client as well
        self._drop()

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _drop(self) -> None:
        sock, self._sock, self._poller = self._sock, None, None
        self._started = False
        self._lost = None
        self._payloads.clear()
        self._stamps.clear()
        if sock is not None:
            sock.close()

    # ------------------------------------------------------------------ reading

    def fileno(self) -> int:
        """The socket's descriptor, to wait for data together with other sources (then
        :meth:`read` with ``timeout=0``); -1 when closed."""
        return -1 if self._sock is None else self._sock.fileno()

    def read(self, timeout: float | None = None) -> Samples:
        """Every data package received since the last call, oldest first, decoded. Waits up to
        ``timeout`` seconds (None: until data comes or the link counts as lost) for the first
        one; returns an empty :class:`Samples` when none came in time. Raises
        :class:`RtdeLinkLost` when the connection ends or stays silent for ``data_timeout_s``;
        the receiver is closed then."""
        stamps, payloads = self.read_payloads(timeout)
        recipe = self.recipe
        assert recipe is not None
        values = np.frombuffer(payloads, recipe.dtype).astype(recipe.numpy_dtype("="))
        return Samples(np.array(stamps, dtype=np.int64), values)

    def read_payloads(self, timeout: float | None = None) -> tuple[list[int], bytes]:
        """Like :meth:`read`, undecoded: the host stamps (ns) and the field bytes of the data
        packages, concatenated, ``recipe.struct.size`` bytes each (decode them with
        ``recipe.struct.iter_unpack`` or ``numpy.frombuffer(..., recipe.dtype)``)."""
        if self._lost is not None:
            lost = self._lost
            self._drop()
            raise lost
        if self._sock is None or not self._started:
            raise RtdeError(f"RTDE {self.address}: not open")
        try:
            self._take_in(wait_s=0.0)  # whatever is queued already: no wait, no poll
            if not self._stamps:
                now = time.monotonic()
                silent_at = self._last_data_s + self.data_timeout_s
                end = silent_at if timeout is None else min(now + max(0.0, timeout), silent_at)
                while not self._stamps:
                    remaining = end - time.monotonic()
                    if remaining <= 0:
                        break
                    self._take_in(wait_s=remaining)
                if not self._stamps and time.monotonic() >= silent_at:
                    silent = time.monotonic() - self._last_data_s
                    raise RtdeLinkLost(f"RTDE {self.address}: no data for {silent:.1f} s")
        except RtdeLinkLost as exc:
            if self._stamps:  # hand out what came before the end; report the end next time
                self._lost = exc
            else:
                self._drop()
                raise
        stamps, payloads = self._stamps, bytes(self._payloads)
        self._stamps = []
        self._payloads.clear()
        return stamps, payloads

    def _take_in(self, wait_s: float) -> bool:
        """Receive what the kernel holds, waiting up to ``wait_s`` for something; parse the
        complete packets. False when nothing came."""
        sock, poller = self._sock, self._poller
        assert sock is not None and poller is not None
        got = False
        while True:
            try:
                n = sock.recv_into(self._rbuf)
            except BlockingIOError:
                if got or wait_s <= 0:
                    return got
                if not poller.poll(max(1, int(wait_s * 1000 + 0.999))):
                    return False
                wait_s = 0.0
                continue
            except OSError as exc:
                raise RtdeLinkLost(f"RTDE {self.address}: connection lost ({exc})") from exc
            if n == 0:
                raise RtdeLinkLost(f"RTDE {self.address}: the controller closed the connection")
            self._last_recv_ns = time.monotonic_ns()
            self.counters["bytes"] += n
            self._buf += self._rbuf[:n]
            got = True
            if self._started:
                self._parse_stream(self._last_recv_ns)
            if n < len(self._rbuf):
                return True  # drained; more may come, but this call has something to return

    def _parse_stream(self, stamp_ns: int) -> None:
        """Take the complete packets out of the buffer: the fields of our data packages into
        the output, anything else to :meth:`_other_packet`."""
        data = self._buf
        header, size = self._header, self._packet_size
        first = wire.HEADER.size + 1
        pos = 0
        end = len(data)
        n = 0
        while end - pos >= wire.HEADER.size:
            if data.startswith(header, pos):  # the usual case: one of our data packages
                if end - pos < size:
                    break
                self._payloads += data[pos + first : pos + size]
                pos += size
                n += 1
                continue
            try:
                packet = wire.next_packet(data, pos)
            except ValueError as exc:
                raise RtdeLinkLost(
                    f"RTDE {self.address}: malformed packet ({exc}): the stream is out of step"
                ) from None
            if packet is None:
                break
            ptype, payload, pos = packet
            if ptype == wire.DATA_PACKAGE and payload[:1] == header[3:4]:
                raise RtdeLinkLost(
                    f"RTDE {self.address}: a data package of {len(payload)} bytes, the recipe "
                    f"needs {size - wire.HEADER.size}"
                )
            self._other_packet(ptype, payload, stamp_ns)
        if n:
            self._stamps.extend([stamp_ns] * n)
            self.counters["packets"] += n
            self._last_data_s = time.monotonic()
        self._buf = data[pos:] if pos else data

    def _other_packet(self, ptype: int, payload: bytes, stamp_ns: int) -> None:
        if ptype == wire.TEXT_MESSAGE:
            text, source, level = wire.parse_text_message(payload)
            self.messages.append(TextMessage(text, source, level, stamp_ns))
            self.counters["text_messages"] += 1
            log.log(
                _LOG_LEVEL.get(level, logging.INFO),
                "RTDE %s message%s: %s",
                self.address,
                f" from {source}" if source else "",
                text,
            )
            return
        # A data package of another recipe, or a late reply: nothing this client asked for.
        self.counters["ignored"] += 1
        log.debug("RTDE %s: ignored packet type %d (%d bytes)", self.address, ptype, len(payload))

    # ------------------------------------------------------------------ handshake

    def _next_packet(self) -> tuple[int, bytes] | None:
        try:
            packet = wire.next_packet(self._buf)
        except ValueError as exc:
            raise RtdeHandshakeError(f"RTDE {self.address}: malformed packet ({exc})") from None
        if packet is None:
            return None
        ptype, payload, end = packet
        self._buf = self._buf[end:]
        return ptype, payload

    def _request(self, ptype: int, payload: bytes, deadline: float) -> bytes:
        """Send one request and return the payload of its reply, taking in text messages."""
        sock = self._sock
        assert sock is not None
        what = _PACKET_NAMES.get(ptype, chr(ptype))
        try:
            sock.sendall(wire.encode(ptype, payload))
            while True:
                packet = self._next_packet()
                if packet is None:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or not self._take_in(wait_s=remaining):
                        raise RtdeHandshakeError(
                            f"RTDE {self.address}: no answer to {what} within "
                            f"{self.connect_timeout_s:g} s"
                        )
                    continue
                rtype, body = packet
                if rtype == ptype:
                    if not body and ptype != wire.GET_URCONTROL_VERSION:
                        raise RtdeHandshakeError(f"RTDE {self.address}: empty answer to {what}")
                    return body
                self._other_packet(rtype, body, self._last_recv_ns)
        except RtdeLinkLost as exc:
            raise RtdeHandshakeError(f"{exc} during the handshake ({what})") from None
        except BlockingIOError:
            raise RtdeHandshakeError(f"RTDE {self.address}: cannot send {what}") from None
        except OSError as exc:
            raise RtdeHandshakeError(f"RTDE {self.address}: {what} failed ({exc})") from exc

    def _handshake(self, deadline: float) -> None:
        reply = self._request(
            wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", PROTOCOL_VERSION), deadline
        )
        if not reply[0]:
            raise RtdeHandshakeError(
                f"RTDE {self.address}: the controller refused protocol version {PROTOCOL_VERSION} "
                "(software older than 3.2 / 5.0?)"
            )
        reply = self._request(wire.GET_URCONTROL_VERSION, b"", deadline)
        if len(reply) < 16:
            raise RtdeHandshakeError(f"RTDE {self.address}: short controller version {reply!r}")
        version = struct.unpack(">IIII", reply[:16])
        self.controller_version = (version[0], version[1], version[2], version[3])
        freq = self.requested_frequency_hz
        if freq is None:
            freq = _E_SERIES_HZ if version[0] > _CB3_MAJOR else _CB3_HZ
        self.frequency_hz = float(freq)
        reply = self._request(
            wire.SETUP_OUTPUTS,
            struct.pack(">d", self.frequency_hz) + ",".join(self.variables).encode("ascii"),
            deadline,
        )
        recipe_id = reply[0]
        types = wire.split_names(reply[1:])
        if len(types) != len(self.variables):
            raise RtdeHandshakeError(
                f"RTDE {self.address}: output setup answered {len(types)} types for "
                f"{len(self.variables)} variables"
            )
        missing = [n for n, t in zip(self.variables, types, strict=True) if t == "NOT_FOUND"]
        if missing:
            raise RtdeNotFound(
                f"RTDE {self.address}: the controller (version "
                f"{'.'.join(map(str, version))}) has no output variable(s) {', '.join(missing)}",
                missing,
            )
        pairs = zip(self.variables, types, strict=True)
        unusable = {n: t for n, t in pairs if t not in wire.TYPE_DTYPE}
        if unusable:
            raise RtdeHandshakeError(
                f"RTDE {self.address}: output variable(s) not usable: {unusable}"
            )
        if recipe_id == 0:
            raise RtdeHandshakeError(
                f"RTDE {self.address}: output setup rejected at {self.frequency_hz:g} Hz (above "
                "the controller's maximum, or another client owns the outputs?)"
            )
        recipe = wire.Recipe(recipe_id, self.variables, types)
        self.recipe = recipe
        self._packet_size = wire.HEADER.size + 1 + recipe.struct.size
        self._header = wire.HEADER.pack(self._packet_size, wire.DATA_PACKAGE) + bytes((recipe_id,))
        reply = self._request(wire.START, b"", deadline)
        if not reply[0]:
            raise RtdeHandshakeError(f"RTDE {self.address}: the controller refused to start")
        self._started = True
        self._last_data_s = time.monotonic()
        log.debug(
            "RTDE %s: streaming %d variables at %g Hz (controller %s)",
            self.address,
            len(self.variables),
            self.frequency_hz,
            ".".join(map(str, version)),
        )
        # Data packages right behind the start reply arrived with it.
        self._parse_stream(self._last_recv_ns)
