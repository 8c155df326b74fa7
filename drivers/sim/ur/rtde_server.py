"""The RTDE side of the simulated controller (TCP 30004): one client connection each.

Per connection, as on a robot: protocol version 2, the controller version, output recipes
(ids from 1, each at its own divisor of the controller cycle), input recipes (ids 1, 2, 3 ...,
an input variable owned by one connection at a time), start and pause, and the input data
packages, which go to the controller (:meth:`~.program.ProgramHost.apply_inputs`). The
controller sends every started connection the output packages due in each cycle
(:meth:`~.engine.Controller.run_cycle`); a client that stops reading for about 10 s is dropped.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
from typing import Any

from wristscan.drivers.sim.ur.engine import Controller
from wristscan.drivers.ur import rtde_wire

__all__ = ["RtdeConnection"]

log = logging.getLogger(__name__)


class RtdeConnection(asyncio.Protocol):
    """One RTDE client connection."""

    def __init__(self, ctrl: Controller) -> None:
        self.ctrl = ctrl
        self.reader = rtde_wire.PacketReader()
        self.transport: asyncio.Transport | None = None
        self.started = False
        self.outputs: list[tuple[rtde_wire.Recipe, int]] = []
        self.outputs_valid = True
        self.inputs: dict[int, rtde_wire.Recipe] = {}
        self.next_input_id = 1
        self.protocol_version = 2
        self._drop_limit = 1 << 20

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.ctrl.rtde_conns.add(self)
        log.debug("RTDE client connected from %s", transport.get_extra_info("peername"))

    def connection_lost(self, exc: Exception | None) -> None:
        self.ctrl.rtde_conns.discard(self)
        for name, owner in list(self.ctrl.input_owner.items()):
            if owner is self:
                del self.ctrl.input_owner[name]
        self.transport = None
        log.debug("RTDE client gone (%s)", exc)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            # The controller forgets the client at once, like a robot dropping the socket.
            self.connection_lost(None)

    def reply(self, ptype: int, payload: bytes) -> None:
        if self.transport is not None:
            self.transport.write(rtde_wire.encode(ptype, payload))

    def data_received(self, data: bytes) -> None:
        try:
            for ptype, payload in self.reader.feed(data):
                self._handle(ptype, payload)
        except (ValueError, struct.error) as e:
            log.warning("RTDE client sent a malformed packet (%s); closing", e)
            self.close()

    def _handle(self, ptype: int, payload: bytes) -> None:
        ctrl = self.ctrl
        if ptype == rtde_wire.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            ok = version == 2
            if ok:
                self.protocol_version = version
            self.reply(ptype, bytes((int(ok),)))
        elif ptype == rtde_wire.GET_URCONTROL_VERSION:
            self.reply(ptype, struct.pack(">IIII", *ctrl.version))
        elif ptype == rtde_wire.SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif ptype == rtde_wire.SETUP_INPUTS:
            self._setup_inputs(payload)
        elif ptype == rtde_wire.START:
            self.started = self.outputs_valid
            self.reply(ptype, bytes((int(self.started),)))
        elif ptype == rtde_wire.PAUSE:
            self.started = False
            self.reply(ptype, b"\x01")
        elif ptype == rtde_wire.DATA_PACKAGE:
            if not payload:
                return
            recipe = self.inputs.get(payload[0])
            if recipe is None:
                log.warning("RTDE data for unknown input recipe %d ignored", payload[0])
                return
            ctrl.apply_inputs(recipe.unpack(payload[1:]))
        elif ptype == rtde_wire.TEXT_MESSAGE:
            log.debug("RTDE text message from client: %r", payload)
        else:
            log.warning("RTDE packet type %d not handled", ptype)

    def _setup_outputs(self, payload: bytes) -> None:
        (freq,) = struct.unpack(">d", payload[:8])
        names = rtde_wire.split_names(payload[8:])
        types = [
            rtde_wire.VARIABLE_TYPES[n] if n in rtde_wire.OUTPUT_NAMES else "NOT_FOUND"
            for n in names
        ]
        max_freq = self.ctrl.cfg.frequency_hz
        ok = bool(names) and "NOT_FOUND" not in types and 0.0 < freq <= max_freq + 1e-9
        recipe_id = 0
        if ok:
            recipe_id = len(self.outputs) + 1
            divisor = max(1, round(max_freq / freq))
            recipe = rtde_wire.Recipe(recipe_id, names, types)
            self.outputs.append((recipe, divisor))
            bytes_per_s = (recipe.struct.size + 4) * max_freq / divisor
            self._drop_limit = max(1 << 16, int(10 * bytes_per_s))
            self.outputs_valid = True  # a valid setup after a rejected one (client retry)
        else:
            log.warning("output recipe rejected (frequency %g Hz, types %s)", freq, types)
            self.outputs_valid = False
        self.reply(rtde_wire.SETUP_OUTPUTS, bytes((recipe_id,)) + ",".join(types).encode())

    def _setup_inputs(self, payload: bytes) -> None:
        names = rtde_wire.split_names(payload)
        owner = self.ctrl.input_owner
        types = []
        for n in names:
            if n not in rtde_wire.INPUT_NAMES:
                types.append("NOT_FOUND")
            elif owner.get(n, self) is not self:
                types.append("IN_USE")
            else:
                types.append(rtde_wire.VARIABLE_TYPES[n])
        recipe_id = 0
        if names and all(t in rtde_wire.TYPE_FORMAT for t in types):
            recipe_id = self.next_input_id
            self.next_input_id += 1
            self.inputs[recipe_id] = rtde_wire.Recipe(recipe_id, names, types)
            for n in names:
                owner[n] = self
        else:
            log.warning("input recipe rejected: %s", dict(zip(names, types, strict=True)))
        self.reply(rtde_wire.SETUP_INPUTS, bytes((recipe_id,)) + ",".join(types).encode())

    def due(self, k: int) -> bool:
        return any(k % div == 0 for _, div in self.outputs)

    def outputs_for(self, k: int, values: dict[str, Any], defaults: dict[str, Any]) -> bytes:
        """The data packages of cycle ``k`` for this client (its recipes due at ``k``)."""
        return b"".join(
            rtde_wire.encode(rtde_wire.DATA_PACKAGE, recipe.pack(values, defaults))
            for recipe, div in self.outputs
            if k % div == 0
        )

    def send_packets(self, data: bytes) -> None:
        t = self.transport
        if t is None or not data:
            return
        if t.get_write_buffer_size() > self._drop_limit:
            log.warning("RTDE client stopped reading for about 10 s; dropping it")
            self.close()
            return
        t.write(data)
