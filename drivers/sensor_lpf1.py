"""LPF1 sensor drivers: UDP, TCP and serial (COBS) transports of wristscan's own profile protocol.

The wire format is ``docs/lpf1.md``; decoding is :mod:`wristscan.drivers.lpf1` (one vectorised
step per profile). What the three drivers share lives in :class:`_Lpf1Messages`: fragments are
reassembled, profiles decoded and booked by frame counter (lost, duplicates, reordered);
HEARTBEAT, HELLO and STATUS messages are counted in ``health().detail`` and never become
profiles. A HELLO whose frame counter is behind the last delivered profile announces a device
reboot: the counter history restarts instead of counting the whole history as late frames.

The UDP driver's ``read_blocks`` (the daemon's hot path) decodes the whole PROFILE messages of a
receive pass together (:mod:`wristscan.drivers.lpf1_block`) and everything else through the
same per-message handling as ``read``: the same profiles, counters and health detail.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

from cobs import cobs

from wristscan.drivers import _bpf, lpf1, lpf1_block
from wristscan.drivers._sensor import SensorCore
from wristscan.drivers._stream import Chunk, StreamProfileSensor, TcpTransport, Transport, open_url
from wristscan.drivers._udp import Datagrams, UdpProfileSensor
from wristscan.drivers.base import DriverInitError
from wristscan.drivers.lpf1_reader import Reassembler, SerialDecoder, StreamDecoder
from wristscan.drivers.records import Profile, ProfileBlock

__all__ = ["Lpf1SerialSensor", "Lpf1TcpSensor", "Lpf1UdpSensor"]

log = logging.getLogger(__name__)


class _Lpf1Messages:
    """LPF1 message handling common to every transport."""

    def __init__(self, sensor: SensorCore) -> None:
        self.sensor = sensor
        self.reassembler = Reassembler()
        self.incomplete_frames = 0
        self.hello: dict[str, Any] | None = None
        """The latest HELLO payload (the sensor's self-description)."""
        self.status: dict[str, Any] | None = None
        """The latest STATUS payload."""

    def reset(self) -> None:
        self.incomplete_frames += self.reassembler.dropped_frames
        self.reassembler = Reassembler()

    def handle(self, msg: lpf1.Message, host_time_ns: int) -> None:
        s = self.sensor
        h = msg.header
        if s.expected_sensor_id is not None and h.sensor_id != s.expected_sensor_id:
            s.stats["foreign"] += 1
            return
        kind = h.msg_type
        if kind == lpf1.MsgType.PROFILE:
            if h.frag_count > 1 and h.frame_counter == s._last_counter:
                # A duplicated fragment of the frame just delivered: kept out of the
                # reassembler, where it would wait for fragments that never come. (Older
                # counters go in: after a reboot without HELLO they are the new frames.)
                s.stats["late_fragments"] += 1
                return
            try:
                whole = self.reassembler.push(msg)
                if whole is None:
                    return
                profile = lpf1.decode_profile(whole, host_time_ns)
            except lpf1.FrameError as exc:
                s._reject(str(exc))
                return
            s._deliver(profile)
        elif kind == lpf1.MsgType.HEARTBEAT:
            s.stats["heartbeats"] += 1
        else:
            try:
                info = msg.json()
            except lpf1.FrameError as exc:
                s._reject(str(exc))
                return
            if kind == lpf1.MsgType.HELLO:
                s.stats["hellos"] += 1
                self.hello = info
                last = s._last_counter
                if last is not None and h.frame_counter < last:
                    s._restart(f"HELLO at frame {h.frame_counter}, after frame {last}")
            else:
                s.stats["statuses"] += 1
                self.status = info
                log.info("%s: sensor status %s", s.kind, info)

    def detail(self) -> dict[str, Any]:
        return {
            "incomplete_frames": self.incomplete_frames + self.reassembler.dropped_frames,
            "hello": self.hello,
            "status": self.status,
        }


class Lpf1UdpSensor(UdpProfileSensor):
    """LPF1 datagrams sent to ``bind_host:port``; fragments reassembled.

    ``source_host`` keeps datagrams from that address only; ``recv_buffer_bytes`` sizes the
    socket receive buffer (the granted size is logged and in ``health().detail``).
    """

    kind: ClassVar[str] = "lpf1-udp"

    def __init__(
        self,
        sensor_id: int | None = None,
        bind_host: str = "0.0.0.0",
        port: int = 50002,
        source_host: str | None = None,
        recv_buffer_bytes: int = 8 << 20,
    ) -> None:
        super().__init__(sensor_id, bind_host, port, source_host, recv_buffer_bytes)
        self.lpf1 = _Lpf1Messages(self)

    def _reset_decoder(self) -> None:
        self.lpf1.reset()

    def _admission_program(self, fraction: float) -> list[_bpf.Instruction]:
        # The header's msg_type (byte 6) and the low half of frame_counter (bytes 16-19).
        return _bpf.counter_filter(fraction, 16, lpf1.HEADER_LEN, 6, int(lpf1.MsgType.PROFILE))

    def _on_datagram(self, frame: memoryview, host_time_ns: int) -> None:
        try:
            msg = lpf1.parse_message(frame)
        except lpf1.FrameError as exc:
            self._reject(str(exc))
            return
        self.lpf1.handle(msg, host_time_ns)

    def _on_datagrams(self, grams: Datagrams) -> list[ProfileBlock]:
        """A pass's datagrams: runs of whole PROFILE messages of one shape decoded as one
        block each (:mod:`wristscan.drivers.lpf1_block`), the others one by one; the blocks
        in arrival order."""
        headers = lpf1_block.read_headers(grams)
        block = lpf1_block.decode_uniform(grams, headers, self.expected_sensor_id)
        if block is not None:  # the usual pass
            kept = self._deliver_block(block)
            self._log_raw(grams, len(grams))
            return [] if kept is None else [kept]
        out: list[ProfileBlock] = []
        records: list[Profile] = []
        for run in lpf1_block.plan(grams, headers, self.expected_sensor_id):
            if not run.fast:
                for i in range(run.start, run.stop):
                    self._datagram_slow(grams, i, records)
                continue
            if records:
                out += ProfileBlock.from_profiles(records)
                records = []
            kept = self._deliver_block(lpf1_block.decode_run(grams, headers, run))
            if kept is not None:
                out.append(kept)
        if records:
            out += ProfileBlock.from_profiles(records)
        self._log_raw(grams, len(grams))
        return out

    def _health_detail(self) -> dict[str, Any]:
        return {**super()._health_detail(), **self.lpf1.detail()}


class _Lpf1StreamSensor(StreamProfileSensor):
    """LPF1 on a byte stream (TCP: magic + length resynchronisation; serial: COBS frames)."""

    def __init__(self, sensor_id: int | None) -> None:
        super().__init__(sensor_id)
        self.lpf1 = _Lpf1Messages(self)
        self._decoder: StreamDecoder | SerialDecoder = self._new_decoder()
        self._skipped_total = 0

    def _new_decoder(self) -> StreamDecoder | SerialDecoder:
        return StreamDecoder()

    def _reset_decoder(self) -> None:
        self._skipped_total += self._decoder.skipped_bytes
        self._decoder = self._new_decoder()
        self.lpf1.reset()

    def _consume(self, data: Chunk, host_time_ns: int) -> None:
        dec = self._decoder
        bad0, skipped0 = dec.bad_messages, dec.skipped_bytes
        msgs = dec.feed(data)
        bad = dec.bad_messages - bad0
        skipped = dec.skipped_bytes - skipped0
        if bad or skipped:
            for _ in range(max(bad, 1)):
                self._reject(f"{bad} bad message(s), {skipped} byte(s) skipped to resynchronise")
        for msg in msgs:
            self._valid()
            self.lpf1.handle(msg, host_time_ns)

    def _health_detail(self) -> dict[str, Any]:
        return {
            **super()._health_detail(),
            **self.lpf1.detail(),
            "skipped_bytes": self._skipped_total + self._decoder.skipped_bytes,
        }


class Lpf1TcpSensor(_Lpf1StreamSensor):
    """LPF1 over TCP: the driver connects to the sensor (or bridge) at ``host:port``;
    resynchronises on the magic after garbage; reconnects with backoff."""

    kind: ClassVar[str] = "lpf1-tcp"

    def __init__(
        self,
        host: str,
        port: int,
        sensor_id: int | None = None,
        connect_timeout_s: float = 2.0,
    ) -> None:
        if not 0 < int(port) <= 65535:
            raise DriverInitError(f"lpf1-tcp: port {port} outside 1..65535")
        if connect_timeout_s <= 0:
            raise DriverInitError("lpf1-tcp: connect_timeout_s must be positive")
        super().__init__(sensor_id)
        self.host, self.port = host, int(port)
        self.connect_timeout_s = float(connect_timeout_s)

    def _connect(self) -> Transport:
        return TcpTransport(self.host, self.port, self.connect_timeout_s)


class Lpf1SerialSensor(_Lpf1StreamSensor):
    """LPF1 COBS frames on a serial line: ``url`` is a device path or a pyserial URL
    (``socket://host:port``, ``loop://``, ``rfc2217://``)."""

    kind: ClassVar[str] = "lpf1-serial"

    def __init__(self, url: str, sensor_id: int | None = None, baudrate: int = 921600) -> None:
        if not url:
            raise DriverInitError("lpf1-serial: url is empty")
        if baudrate <= 0:
            raise DriverInitError("lpf1-serial: baudrate must be positive")
        super().__init__(sensor_id)
        self.url, self.baudrate = url, int(baudrate)

        self._joining = True
        self._head = bytearray()

    def _new_decoder(self) -> StreamDecoder | SerialDecoder:
        return SerialDecoder()

    def _reset_decoder(self) -> None:
        super()._reset_decoder()
        self._joining = True
        self._head = bytearray()

    def _consume(self, data: Chunk, host_time_ns: int) -> None:
        if self._joining:
            # The port may have been opened in the middle of a frame: up to the first
            # delimiter, bytes that do not make a valid message are not the sensor's fault.
            self._head += data
            end = self._head.find(b"\x00")
            if end < 0:
                if len(self._head) > lpf1.MAX_PAYLOAD:
                    self._head.clear()
                return
            self._joining = False
            data, first = self._head[end + 1 :], bytes(self._head[: end + 1])
            self._head = bytearray()
            try:
                lpf1.parse_message(cobs.decode(first[:-1]))
                data = first + data
            except (cobs.DecodeError, lpf1.FrameError):
                self.stats["startup_discarded_bytes"] += len(first)
        super()._consume(data, host_time_ns)

    def _connect(self) -> Transport:
        return open_url(self.url, self.baudrate)
