"""How frames reach the cars: one small ``Transport`` class per boundary, chosen by name.

Like python-can's interfaces: ``open_transport("udp" | "serial" | "can" | "loop", cars, **options)``
builds one; a driver that is not installed (pyserial, python-can) fails only when its transport
is chosen. Every transport moves whole protocol frames (docs/protocol.md section 2) and knows
nothing of their meaning: ``send`` never blocks and never awaits (the dispatcher sends a whole
step's commands back to back), and incoming frames go to the ``on_frame`` callback given to
``open``, in the event loop's thread. What a transport refuses before the protocol sees it (a
serial frame failing its CRC, a CAN frame with bad padding) is counted in ``dropped``.

- ``udp``: one datagram endpoint for the whole fleet (uvloop or asyncio); a car is sent to at the
  address its authenticated frames come from (``confirm_source``), or its fleet address before.
- ``serial``: one serial port per car (fleet ``serial`` field), frames in COBS + CRC-16 (section 9).
- ``can``: one python-can bus, CAN FD, the id mapping of section 10.
- ``loop``: in process, like pyserial's ``loop://``: for unit tests of the dispatcher.
"""

from __future__ import annotations

import asyncio
import importlib
import inspect
import os
from collections import Counter
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any, ClassVar

from udan.edge.protocol import CAN_CAR_BASE, CAN_MAX_CAR, FrameError, can_pack, can_unpack
from udan.fleetfile import CarEntry

FrameHandler = Callable[[bytes], None]


class TransportError(RuntimeError):
    """A transport that cannot be built or used, with a one-line reason."""


class Transport:
    """Base class: moves protocol frames between the edge and its cars."""

    name: ClassVar[str] = ""

    def __init__(self, cars: Sequence[CarEntry]) -> None:
        self.cars = {c.car_id: c for c in cars}
        self.dropped: Counter[str] = Counter()
        self._on_frame: FrameHandler | None = None

    async def open(self, on_frame: FrameHandler) -> None:
        """Start receiving: every frame from a car is passed to ``on_frame``."""
        self._on_frame = on_frame

    def send(self, car_id: int, frame: bytes) -> None:
        """Queue one frame for a car now, never blocking; ``TransportError``/``OSError`` if not."""
        raise NotImplementedError

    def confirm_source(self, car_id: int) -> None:
        """The frame being delivered passed the protocol's checks for ``car_id``.

        Called from inside ``on_frame``. Transports where a car's address can change (UDP) send
        to where its authenticated frames come from, as a car answers the edge's last accepted
        frame (section 4); the others have fixed wiring and ignore it.
        """

    def send_back(self, car_id: int, frame: bytes) -> None:
        """Answer the frame being delivered (called inside ``on_frame``) where it came from.

        Unlike ``confirm_source`` this does not make that the car's address: the frame being
        answered may be a replayed one (a JOIN anyone could have recorded). Transports with fixed
        wiring send as ``send`` does.
        """
        self.send(car_id, frame)

    def close(self) -> None:
        """Stop receiving and release the link."""
        self._on_frame = None

    def _deliver(self, frame: bytes) -> None:
        if self._on_frame is not None:
            self._on_frame(frame)


_REGISTRY: dict[str, type[Transport]] = {}


def register(name: str) -> Callable[[type[Transport]], type[Transport]]:
    """Class decorator: make a transport available to ``open_transport`` under ``name``."""

    def add(cls: type[Transport]) -> type[Transport]:
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return add


def open_transport(name: str, cars: Sequence[CarEntry], **options: Any) -> Transport:
    """Build the transport ``name`` for ``cars``; a bad name or option is a ``TransportError``."""
    cls = _REGISTRY.get(name)
    if cls is None:
        raise TransportError(f"unknown transport {name!r}; known: {', '.join(sorted(_REGISTRY))}")
    accepted = [p for p in inspect.signature(cls).parameters if p != "cars"]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise TransportError(
            f"transport {name!r} has no option {', '.join(unknown)}; "
            f"options: {', '.join(accepted) or 'none'}"
        )
    return cls(cars, **options)


def _driver(module: str, package: str, transport: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError:
        raise TransportError(
            f"transport {transport!r} needs {package} (pip install {package})"
        ) from None


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free on ``host`` right now (for stand-ins started before the edge binds)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def host_port(text: str, what: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); a one-line ``TransportError`` otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise TransportError(f"{what} must be HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


# --- UDP ---------------------------------------------------------------------------------------
class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpTransport) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.owner._received(data, addr)

    def error_received(self, exc: Exception) -> None:
        self.owner.dropped["socket_error"] += 1


@register("udp")
class UdpTransport(Transport):
    """One datagram endpoint for the fleet; one datagram is one frame (section 1)."""

    def __init__(self, cars: Sequence[CarEntry], *, listen: str = "0.0.0.0:9000") -> None:
        super().__init__(cars)
        self.listen = host_port(listen, "listen address")
        self.address: tuple[str, int] | None = None
        self._routes = {c.car_id: c.address for c in cars if c.address is not None}
        self._endpoint: asyncio.DatagramTransport | None = None
        self._source: Any = None

    async def open(self, on_frame: FrameHandler) -> None:
        """Bind the listen address (``OSError`` if it is taken); ``address`` is the bound one."""
        await super().open(on_frame)
        loop = asyncio.get_running_loop()
        self._endpoint, _ = await loop.create_datagram_endpoint(
            lambda: _Datagrams(self), local_addr=self.listen
        )
        self.address = self._endpoint.get_extra_info("sockname")[:2]

    def _received(self, data: bytes, addr: Any) -> None:
        self._source = addr
        try:
            self._deliver(data)
        finally:
            self._source = None

    def confirm_source(self, car_id: int) -> None:
        """Answer the car where its authenticated frame came from."""
        if self._source is not None:
            self._routes[car_id] = self._source

    def send_back(self, car_id: int, frame: bytes) -> None:
        """One datagram to the source of the datagram being delivered."""
        if self._source is None or self._endpoint is None or self._endpoint.is_closing():
            self.send(car_id, frame)
        else:
            self._endpoint.sendto(frame, self._source)

    def send(self, car_id: int, frame: bytes) -> None:
        """One datagram to the car's address (the OS sends it before this returns)."""
        addr = self._routes.get(car_id)
        if addr is None:
            raise TransportError(f"car {car_id}: no address (none in the fleet file, not heard)")
        if self._endpoint is None or self._endpoint.is_closing():
            raise TransportError("udp transport is not open")
        self._endpoint.sendto(frame, addr)

    def close(self) -> None:
        """Close the socket."""
        super().close()
        if self._endpoint is not None:
            self._endpoint.close()


# --- serial: COBS + CRC-16/CCITT-FALSE (section 9) ---------------------------------------------
MAX_SERIAL_BODY = 253  # one COBS block: a frame is never longer than 256 bytes on the line


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = (crc << 1) ^ 0x1021 if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, no final xor."""
    crc = 0xFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[(crc >> 8) ^ byte]
    return crc


def cobs_encode(data: bytes) -> bytes:
    """COBS, canonical form: the output has no 0x00 (a full 254-byte run at the end gets no 01)."""
    out = bytearray()
    runs = data.split(b"\x00")
    for i, run in enumerate(runs):
        full, rest = divmod(len(run), 254)
        for k in range(full):
            out += b"\xff" + run[254 * k : 254 * (k + 1)]
        if rest or not full or i < len(runs) - 1:
            out.append(rest + 1)
            out += run[254 * full :]
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of ``cobs_encode``; ``ValueError`` on a 0x00 or a block running past the end."""
    out = bytearray()
    i = 0
    while i < len(data):
        code = data[i]
        block = data[i + 1 : i + code]
        if code == 0 or i + code > len(data) or 0 in block:
            raise ValueError("bad COBS block")
        out += block
        i += code
        if code < 255 and i < len(data):
            out.append(0)
    return bytes(out)


def serial_frame(body: bytes) -> bytes:
    """``COBS(body || CRC16(body)) || 0x00``: one body as it goes on the line."""
    if len(body) > MAX_SERIAL_BODY:
        raise ValueError(f"serial body of {len(body)} bytes exceeds {MAX_SERIAL_BODY}")
    return cobs_encode(body + crc16(body).to_bytes(2, "big")) + b"\x00"


class Deframer:
    """Splits a byte stream at 0x00 into bodies whose COBS and CRC check out."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Bytes as they arrive, split anywhere -> the complete, checked bodies."""
        bodies = []
        self._buf += data
        while (end := self._buf.find(0)) >= 0:
            chunk = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if not chunk:
                continue
            try:
                raw = cobs_decode(chunk)
            except ValueError:
                self.bad_frames += 1
                continue
            if len(raw) < 3 or crc16(raw[:-2]) != int.from_bytes(raw[-2:], "big"):
                self.bad_frames += 1
                continue
            bodies.append(raw[:-2])
        if len(self._buf) > 2 * (MAX_SERIAL_BODY + 4):  # no delimiter for this long: line noise
            self.bad_frames += 1
            self._buf.clear()
        return bodies


class _Port:
    """One car's serial line: the pyserial port, its deframer and unsent bytes."""

    def __init__(self, port: Any) -> None:
        self.port = port
        self.fd: int = port.fileno()
        self.deframer = Deframer()
        self.pending = bytearray()


@register("serial")
class SerialTransport(Transport):
    """A wired serial line per car (the fleet's ``serial`` device) carrying whole frames."""

    def __init__(self, cars: Sequence[CarEntry], *, baudrate: int = 921_600) -> None:
        super().__init__(cars)
        self._serial = _driver("serial", "pyserial", "serial")
        missing = [c.car_id for c in cars if c.serial is None]
        if missing:
            raise TransportError(f"serial transport: car {missing[0]} has no serial device")
        self.baudrate = baudrate
        self._ports: dict[int, _Port] = {}

    async def open(self, on_frame: FrameHandler) -> None:
        """Open every car's device in raw mode and read it from the event loop."""
        await super().open(on_frame)
        loop = asyncio.get_running_loop()
        for car in self.cars.values():
            try:
                port = self._serial.Serial(car.serial, baudrate=self.baudrate, timeout=0)
            except (OSError, ValueError) as err:
                self.close()
                raise TransportError(f"car {car.car_id}: cannot open {car.serial}: {err}") from None
            line = _Port(port)
            self._ports[car.car_id] = line
            loop.add_reader(line.fd, self._readable, line)

    def _readable(self, line: _Port) -> None:
        try:
            data = os.read(line.fd, 4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the other end went away (a pty closed, a USB adapter unplugged)
            self.dropped["serial_io_error"] += 1
            asyncio.get_running_loop().remove_reader(line.fd)
            return
        bad_before = line.deframer.bad_frames
        bodies = line.deframer.feed(data)
        if line.deframer.bad_frames > bad_before:
            self.dropped["serial_bad_frames"] += line.deframer.bad_frames - bad_before
        for body in bodies:
            self._deliver(body)

    def send(self, car_id: int, frame: bytes) -> None:
        """Write the framed bytes; what the driver cannot take now is written when it can."""
        line = self._ports.get(car_id)
        if line is None:
            raise TransportError(f"car {car_id}: serial line not open")
        data = serial_frame(frame)
        if line.pending:
            line.pending += data
            return
        try:
            written = os.write(line.fd, data)
        except BlockingIOError:
            written = 0
        if written < len(data):
            line.pending += data[written:]
            asyncio.get_running_loop().add_writer(line.fd, self._writable, line)

    def _writable(self, line: _Port) -> None:
        try:
            written = os.write(line.fd, line.pending)
        except BlockingIOError:
            return
        except OSError:
            self.dropped["serial_io_error"] += 1
            written = len(line.pending)
        del line.pending[:written]
        if not line.pending:
            asyncio.get_running_loop().remove_writer(line.fd)

    def close(self) -> None:
        """Stop reading and close every port."""
        super().close()
        try:
            loop: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            loop = None
        for line in self._ports.values():
            if loop is not None:
                loop.remove_reader(line.fd)
                loop.remove_writer(line.fd)
            line.port.close()
        self._ports.clear()


# --- CAN FD (section 10) -----------------------------------------------------------------------
@register("can")
class CanTransport(Transport):
    """One python-can bus, CAN FD: each frame whole in one CAN FD frame, ids by type and car."""

    def __init__(
        self,
        cars: Sequence[CarEntry],
        *,
        interface: str = "socketcan",
        channel: str = "vcan0",
        bitrate: int | None = None,
        data_bitrate: int | None = None,
    ) -> None:
        super().__init__(cars)
        self._can = _driver("can", "python-can", "can")
        too_big = [c.car_id for c in cars if not 0 < c.car_id <= CAN_MAX_CAR]
        if too_big:
            raise TransportError(f"can transport: car id {too_big[0]} outside 1-{CAN_MAX_CAR}")
        self.interface, self.channel = interface, channel
        self._bus_options: dict[str, Any] = {"fd": True}
        if bitrate is not None:
            self._bus_options["bitrate"] = bitrate
        if data_bitrate is not None:
            self._bus_options["data_bitrate"] = data_bitrate
        if interface == "virtual":
            self._bus_options["protocol"] = self._can.CanProtocol.CAN_FD
        self._bus: Any = None
        self._notifier: Any = None

    async def open(self, on_frame: FrameHandler) -> None:
        """Connect to the bus and listen (file descriptor reader where the interface has one)."""
        await super().open(on_frame)
        try:
            self._bus = self._can.Bus(
                interface=self.interface, channel=self.channel, **self._bus_options
            )
        except (self._can.CanError, OSError, ImportError, ValueError) as err:
            raise TransportError(
                f"can transport: cannot open {self.interface}:{self.channel}: {err}"
            ) from None
        self._notifier = self._can.Notifier(
            self._bus, [self._received], timeout=0.05, loop=asyncio.get_running_loop()
        )

    def _received(self, msg: Any) -> None:
        if msg.is_extended_id or not 0 < msg.arbitration_id - CAN_CAR_BASE <= CAN_MAX_CAR:
            return  # not a car's frame (the edge's own traffic, other nodes): acceptance filter
        try:
            frame = can_unpack(msg.arbitration_id, bytes(msg.data))
        except FrameError as err:
            self.dropped[f"can_{err.reason}"] += 1
            return
        self._deliver(frame)

    def send(self, car_id: int, frame: bytes) -> None:
        """One CAN FD frame with bit-rate switch (``TransportError`` if the bus refuses it)."""
        if self._bus is None:
            raise TransportError("can transport is not open")
        can_id, data = can_pack(frame)
        msg = self._can.Message(
            arbitration_id=can_id, is_extended_id=False, is_fd=True, bitrate_switch=True, data=data
        )
        try:
            self._bus.send(msg, timeout=0)
        except self._can.CanError as err:
            raise TransportError(f"car {car_id}: CAN send failed: {err}") from None

    def close(self) -> None:
        """Stop listening and shut the bus down."""
        super().close()
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None


# --- in process --------------------------------------------------------------------------------
@register("loop")
class LoopTransport(Transport):
    """In-process stand-in (like pyserial's ``loop://``): cars are callables in the same loop.

    ``attach(car_id, handler)`` is a car's receiver; a car answers with ``car_send``. Frames are
    delivered from the event loop (after ``delay_s``), never inside ``send``, as on a real link.
    """

    def __init__(self, cars: Sequence[CarEntry], *, delay_s: float = 0.0) -> None:
        super().__init__(cars)
        self.delay_s = delay_s
        self.sent: list[tuple[int, bytes]] = []
        self._handlers: dict[int, FrameHandler] = {}

    def attach(self, car_id: int, handler: FrameHandler) -> None:
        """Route the edge's frames for ``car_id`` to ``handler``."""
        self._handlers[car_id] = handler

    def car_send(self, frame: bytes) -> None:
        """A car's frame towards the edge."""
        self._later(self._deliver, frame)

    def _later(self, handler: FrameHandler, frame: bytes) -> None:
        loop = asyncio.get_running_loop()
        if self.delay_s > 0:
            loop.call_later(self.delay_s, handler, frame)
        else:
            loop.call_soon(handler, frame)

    def send(self, car_id: int, frame: bytes) -> None:
        """Record the frame and deliver it to the car's handler from the loop."""
        handler = self._handlers.get(car_id)
        if handler is None:
            raise TransportError(f"car {car_id}: nothing attached to the loop transport")
        self.sent.append((car_id, frame))
        self._later(handler, frame)
