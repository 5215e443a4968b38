"""The flight recorder: ``udan-edge --record run.mcap``, written off the control loop.

Two sides, in two processes (:mod:`udan.edge.sidecar`'s shape):

- :class:`FlightRecorder`, in the edge's loop, is the control core's journal
  (:class:`udan.edge.core.CoreJournal`) and the telemetry's tap: inside a step it only keeps
  each entry (a tuple of the objects the core was given; nothing is copied or encoded); after
  each step, when the cars take a move before the next decision, :meth:`FlightRecorder.flush`
  offers them to the recorder process through an :class:`~udan.edge.sidecar.Outlet`, which
  never waits: a record the socket has no room for is dropped and counted (the journal's
  sequence numbers show the gap in the file). Recording never delays a command.
- The recorder process (``python -m udan.edge.recorder``, niced below the loop and the
  perception) turns the records into MCAP messages (:mod:`udan.edge.flightlog` says which),
  and takes the frames.

Frames never pass through the loop. The perception process remembers the last frames it
analysed (by reference, no copy); after each step the loop tells it which one the step used
(its capture time, one small message), and it copies that frame into shared memory
(:class:`udan.edge.perception.FrameRing`), and one frame every ``1 / rate`` seconds besides: a
few copies a second instead of one a frame. The recorder takes each decided frame from there as
soon as the decision's entry arrives and writes it losslessly and uncompressed
(``foxglove.RawImage``, 2.3 MB at 1920x1200), and the others as JPEGs of the quality asked (or
losslessly, if asked). The file's chunks are not compressed: sensor noise does not compress
well, and what does cost too much beside the loop (MCAP's zstd took 50-60 ms of CPU per decided
frame for 47 % less, and the loop's decision p99 measured 1.5 times higher for it in
interleaved runs; a PNG encoder took 70-135 ms for 55 % less). A decided frame that is not
found (the perception no longer remembered it, or the recorder fell behind) is counted as
missed, as is every record the outlet dropped; the counts are the recorder's reply when the
edge closes it, and the file's last metadata record.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from udan.edge import flightlog as fl
from udan.edge.camera import CameraError, attach_frames
from udan.edge.perception import RingSpec
from udan.edge.sidecar import Inlet, Outlet, ignore_interrupts

RECORDER_NICENESS = 10
"""How much nicer than the loop the recorder process runs: it has seconds, a command 10 ms, a
frame its period."""
RECORDER_BUFFER_BYTES = 4 << 20
"""What may wait in the socket for the recorder (a few seconds of a 5-car run's records)."""
CLOSE_TIMEOUT_S = 60.0
"""Longest the edge waits at exit for the recorder to write what it holds and close the file."""
DEFAULT_RATE = 2.0
"""Frames a second written besides the decided ones (JPEG), by default."""
DEFAULT_QUALITY = 80
"""JPEG quality of those frames, by default."""


# -- in the edge's loop -----------------------------------------------------------------------
class FlightRecorder:
    """The loop's side of the recorder; see the module docstring."""

    def __init__(
        self,
        path: Path,
        meta: dict[str, Any],
        *,
        ring: RingSpec | None,
        rate: float = DEFAULT_RATE,
        quality: int | None = DEFAULT_QUALITY,
    ) -> None:
        """``quality``: of the frames no decision used, JPEG 1-100, or None for lossless."""
        self.path = path
        args = ["--out", str(path), "--rate", str(rate), "--quality", str(quality or 0)]
        if ring is not None:
            args += ["--ring", ring.name]
        self._outlet = Outlet("udan.edge.recorder", args, buffer_bytes=RECORDER_BUFFER_BYTES)
        self._pending: list[tuple] = [("meta", meta)]
        self._seq = 0

    @property
    def pid(self) -> int:
        """The recorder process's."""
        return self._outlet.proc.pid

    def log(self, call: str, *inputs: Any) -> None:
        """The core's journal: keep the entry (sent by :meth:`flush`)."""
        self._pending.append(("core", self._seq, call, inputs))
        self._seq += 1

    def telemetry(self, record: dict[str, Any]) -> None:
        """The telemetry's tap: keep the record (sent by :meth:`flush`)."""
        self._pending.append(("telemetry", record))

    def flush(self, more_than: int = 0) -> None:
        """Offer what was kept since the last flush, if it is more than ``more_than`` records
        (the shell flushes after each step, when the loop has time)."""
        if len(self._pending) <= more_than:
            return
        pending, self._pending = self._pending, []
        for record in pending:
            self._outlet.offer(record)

    def close(self) -> dict[str, Any]:
        """Send the rest, let the recorder finish the file; what it wrote and what was lost."""
        self.flush()
        ended = self._outlet.close(CLOSE_TIMEOUT_S)
        counts = self._outlet.replies[-1] if self._outlet.replies else {}
        return {
            "file": str(self.path),
            "records_offered": self._outlet.sent + self._outlet.dropped,
            "records_dropped": self._outlet.dropped,
            "recorder": ended,
            **counts,
        }


# -- in the recorder process ------------------------------------------------------------------
class McapLog:
    """The MCAP file, written from the recorder's two threads under one lock."""

    def __init__(self, path: Path) -> None:
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from mcap.writer import CompressionType, Writer
        from mcap_protobuf.schema import register_schema

        self._compressed, self._raw = CompressedImage, RawImage
        self._stream = path.open("wb")
        self._writer = Writer(self._stream, compression=CompressionType.NONE)  # module docstring
        self._writer.start(profile=fl.PROFILE, library="udan-edge recorder")
        self._lock = threading.Lock()
        self._channels: dict[str, int] = {}
        for topic, schema in fl.SCHEMAS.items():
            schema_id = self._writer.register_schema(
                name=f"udan.{topic.strip('/').replace('/', '.')}",
                encoding="jsonschema",
                data=json.dumps(schema).encode(),
            )
            self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)
        for topic, kind in ((fl.LOSSLESS_TOPIC, RawImage), (fl.JPEG_TOPIC, CompressedImage)):
            schema_id = register_schema(self._writer, kind)
            self._channels[topic] = self._writer.register_channel(topic, "protobuf", schema_id)
        self.messages = 0

    def write(self, topic: str, log_time: int, body: dict[str, Any], sequence: int = 0) -> None:
        data = json.dumps(body, separators=(",", ":")).encode()
        self._add(topic, log_time, data, sequence)

    def image(self, t_capture_ns: int, index: int, image: np.ndarray, quality: int | None) -> None:
        """A frame: lossless (``quality`` None) or JPEG."""
        height, width = image.shape
        if quality is None:
            topic = fl.LOSSLESS_TOPIC
            message = self._raw(
                frame_id="camera", width=width, height=height, encoding="mono8", step=width,
                data=image.tobytes(),
            )  # fmt: skip
        else:
            topic = fl.JPEG_TOPIC
            _, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
            message = self._compressed(frame_id="camera", format="jpeg", data=jpeg.tobytes())
        message.timestamp.FromNanoseconds(t_capture_ns)
        self._add(topic, t_capture_ns, message.SerializeToString(), index & 0xFFFFFFFF)

    def _add(self, topic: str, log_time: int, data: bytes, sequence: int) -> None:
        with self._lock:
            self._writer.add_message(
                self._channels[topic], log_time=log_time, data=data, publish_time=log_time,
                sequence=sequence,
            )  # fmt: skip
            self.messages += 1

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        with self._lock:
            self._writer.add_metadata(name, {k: json.dumps(v) for k, v in values.items()})

    def attach(self, name: str, media_type: str, data: bytes) -> None:
        now = time.monotonic_ns()
        with self._lock:
            self._writer.add_attachment(now, now, name, media_type, data)

    def close(self) -> None:
        with self._lock:
            self._writer.finish()
            self._stream.close()


class FrameTaker:
    """Takes frames out of the perception's shared memory (:class:`FrameRing`) into the file.
    One thread copies them out: each decided frame as soon as its decision's entry arrives
    (found by its capture time), and the previews as they come (polled at twice their rate),
    into a queue of at most `QUEUE_BYTES`; another writes them (lossless; the previews as
    JPEG of ``quality``, or lossless for None). A decided frame not found (the perception no
    longer remembered it, or the recorder fell `DECIDED_SLOTS` decisions behind) or without
    room in the queue is counted as missed."""

    QUEUE_BYTES = 256 << 20
    FIND_WAIT_S = 0.5

    def __init__(
        self, ring: RingSpec | None, log: McapLog, rate: float, quality: int | None
    ) -> None:
        self.ring = ring
        self.log = log
        self.poll_s = 0.5 / rate if rate > 0 else None
        self.quality = quality
        self.lossless = 0
        self.lossy = 0
        self.missed = 0
        """Decided frames not written: not found in time, no room in the queue, no ring."""
        self.skipped = 0
        """Previews not written for want of room in the queue."""
        self._rings: dict[str, tuple[Any, Any]] = {}  # attached: name -> (mapping, layout)
        self._wanted: queue.Queue[tuple[int, int] | None] = queue.Queue()
        self._taken: queue.Queue[tuple[int, int, np.ndarray, bool] | None] = queue.Queue()
        self._queued_bytes = 0
        self._lock = threading.Lock()
        self._written = {lossless: deque(maxlen=256) for lossless in (True, False)}
        """Capture times taken lately, losslessly or at all."""
        self._taker = threading.Thread(target=self._take, name="frames", daemon=True)
        self._writer = threading.Thread(target=self._write, name="frame writer", daemon=True)
        self._taker.start()
        self._writer.start()

    def want(self, index: int, t_capture_ns: int) -> None:
        """A decision used this frame: write it losslessly."""
        self._wanted.put((index, t_capture_ns))

    def close(self) -> None:
        """Take and write the decided frames still asked for, then stop."""
        self._wanted.put(None)
        self._taker.join()
        self._writer.join()
        for buf, _ in self._rings.values():
            buf.close()

    def _ring(self, name: str) -> tuple[Any, Any] | None:
        """The shared memory ``name`` (mapped once; kept when the perception removes it)."""
        if name not in self._rings:
            with contextlib.suppress(CameraError):
                self._rings[name] = attach_frames(name)
        return self._rings.get(name)

    def _take(self) -> None:
        due = time.monotonic()
        while True:
            timeout = None if self.poll_s is None else max(0.0, due - time.monotonic())
            try:
                wanted = self._wanted.get(timeout=timeout)
            except queue.Empty:
                due = max(due + self.poll_s, time.monotonic())
                self._preview()
                continue
            if wanted is None:
                self._taken.put(None)
                return
            if not self._decided(*wanted):
                self.missed += 1

    def _decided(self, index: int, t_ns: int) -> bool:
        """The decided frame captured at ``t_ns`` into the queue. The edge asks the perception
        for it right after the step, before it sends the step's entries here, so it is
        normally there already; wait a little for it while nothing newer is."""
        deadline = time.monotonic() + self.FIND_WAIT_S
        while self.ring is not None:
            ring = self._ring(self.ring.decided)
            if ring is not None:
                buf, layout = ring
                number, newest = layout.find(buf, t_ns)
                if number is not None:
                    got = layout.read(buf, number)
                    return got is not None and self._queue(got, index, decided=True)
                if newest > t_ns:
                    return False
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return False

    def _preview(self) -> None:
        ring = None if self.ring is None else self._ring(self.ring.previews)
        if ring is not None:
            buf, layout = ring
            number = layout.latest(buf)
            got = layout.read(buf, number) if number else None
            if got is not None:
                self._queue(got, number, decided=False)

    def _queue(self, got: tuple[np.ndarray, int], index: int, *, decided: bool) -> bool:
        """A frame (image, capture time) into the writer's queue; whether it is written."""
        image, t_ns = got
        lossless = decided or self.quality is None
        if t_ns in self._written[lossless]:
            return True  # taken already (a decided frame may have gone out as a preview too)
        with self._lock:
            if self._queued_bytes + image.nbytes > self.QUEUE_BYTES:
                self.skipped += not decided
                return False
            self._queued_bytes += image.nbytes
        if lossless:
            self._written[True].append(t_ns)
        self._written[False].append(t_ns)
        self._taken.put((t_ns, index, image, decided))
        return True

    def _write(self) -> None:
        while (item := self._taken.get()) is not None:
            t_ns, index, image, decided = item
            quality = None if decided else self.quality
            self.log.image(t_ns, index, image, quality)
            if quality is None:
                self.lossless += 1
            else:
                self.lossy += 1
            with self._lock:
                self._queued_bytes -= image.nbytes


class Writer:
    """The recorder process's work: each record the edge offers into the MCAP file."""

    def __init__(self, log: McapLog, frames: FrameTaker) -> None:
        self.log = log
        self.frames = frames
        self.last_ns = 0
        self.seen: list[int] = []  # journal sequence numbers received
        self.gaps = 0

    def take(self, record: tuple) -> None:
        kind = record[0]
        if kind == "core":
            self._core(*record[1:])
        elif kind == "telemetry":
            body = record[1]
            topic = fl.TELEMETRY_TOPICS.get(body.get("kind"), fl.EVENT_TOPIC)
            self.log.write(topic, body.get("t_ns", self.last_ns), body)
        elif kind == "meta":
            self._meta(record[1])

    def _meta(self, meta: dict[str, Any]) -> None:
        self.log.metadata(fl.META, meta)
        calibration = meta.get("calibration_file")
        if calibration:
            with contextlib.suppress(OSError):
                data = Path(calibration).read_bytes()
                self.log.attach(fl.CALIBRATION_ATTACHMENT, "application/x-yaml", data)

    def _core(self, seq: int, call: str, inputs: tuple) -> None:
        if self.seen and seq != self.seen[-1] + 1:
            self.gaps += seq - self.seen[-1] - 1
        self.seen.append(seq)
        now = inputs[0] if call in ("see", "due", "decide", "wait_for_moves", "new_episode") else 0
        self.last_ns = now or self.last_ns
        at = self.last_ns
        if call == "see":
            self.log.write(fl.SCENE_TOPIC, at, fl.scene_json(seq, *inputs), seq)
        elif call == "due":
            self.log.write(fl.DUE_TOPIC, at, {"seq": seq, "now_ns": now,
                                              "moving": sorted(inputs[1])}, seq)  # fmt: skip
        elif call == "decide":
            _, decided_ns, state, decision = inputs
            self.frames.want(state.frame, state.t_capture_ns)  # first: the ring moves on
            self.log.write(fl.STATE_TOPIC, at, fl.state_json(seq, state), seq)
            self.log.write(
                fl.DECISION_TOPIC, at, fl.decision_json(seq, now, decided_ns, state, decision), seq
            )
        elif call == "dispatched":
            state_ns, report = inputs
            self.log.write(fl.DISPATCH_TOPIC, report.decision_ns,
                           fl.dispatch_json(seq, state_ns, report), seq)  # fmt: skip
        elif call == "recentred":
            recentring, report = inputs
            self.log.write(fl.RECENTRED_TOPIC, report.decision_ns,
                           fl.recentred_json(seq, recentring, report), seq)  # fmt: skip
        else:
            if call == "start":
                self.last_ns = inputs[0]
                at = self.last_ns
            self.log.write(fl.CONTROL_TOPIC, at, fl.control_json(seq, call, inputs), seq)

    def counts(self, path: Path) -> dict[str, Any]:
        frames = self.frames
        return {
            "messages": self.log.messages,
            "frames_lossless": frames.lossless,
            "frames_lossy": frames.lossy,
            "frames_missed": frames.missed,
            "frames_skipped": frames.skipped,
            "journal_entries": len(self.seen),
            "journal_gaps": self.gaps,
            "bytes": path.stat().st_size if path.exists() else 0,
        }


def record(fd: int, out: Path, ring: RingSpec | None, rate: float, quality: int | None) -> int:
    """The recorder process: every record until the edge closes its end, then the file's end
    and a reply with the counts."""
    ignore_interrupts()
    with contextlib.suppress(OSError):
        os.nice(RECORDER_NICENESS)
    inlet = Inlet(fd)
    try:
        log = McapLog(out)
    except OSError as err:
        inlet.reply({"error": f"cannot write {out}: {err.strerror or err}"})
        inlet.close()
        return 2
    writer = Writer(log, FrameTaker(ring, log, rate, quality))
    try:
        for item in inlet:
            writer.take(item)
    finally:
        writer.frames.close()
        counts = writer.counts(out)
        log.metadata("udan-recorder", counts)
        log.close()
        counts["bytes"] = out.stat().st_size
        inlet.reply(counts)
        inlet.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m udan.edge.recorder --fd N --out run.mcap [--ring NAME]`` (started by the
    edge, not by hand)."""
    parser = argparse.ArgumentParser(prog="udan.edge.recorder", description=__doc__)
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--ring")
    parser.add_argument("--rate", type=float, default=DEFAULT_RATE)
    parser.add_argument("--quality", type=int, default=DEFAULT_QUALITY, help="0: lossless")
    args = parser.parse_args(argv)
    quality = args.quality or None
    ring = None if args.ring is None else RingSpec(args.ring, args.rate)
    return record(args.fd, args.out, ring, args.rate, quality)


if __name__ == "__main__":
    sys.exit(main())
