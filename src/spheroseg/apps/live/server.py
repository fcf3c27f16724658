"""``spheroseg live``: a source's IMAGE stream tracked frame by frame, the
results served to every client.

Three threads.  The *source* thread connects to the image server (with
back-off while it cannot, again after a disconnection or a stall), splits
and checks the stream (:class:`spheroseg.apps.live.messages.MessageReader`),
decodes each IMAGE and puts it in a one-frame slot: a frame not yet taken
when the next arrives is dropped and counted, so the newest always wins and
nothing queues (an image's header is checked as it comes, its voxels read
only when it is tracked).  The *worker* thread takes the slot, tracks the frame
(:class:`spheroseg.apps.live.session.LiveTracker`) and publishes its results;
the *fan-out* (:class:`spheroseg.apps.live.fanout.Broadcaster`) sends them to
every client, the latest at once to one that connects.

Per frame, with the source frame's timestamp: POLYDATA ``LVEndo`` (and
``LVEpi`` with ``myocardium``; with it, each point's 17-segment number as
the point scalar ``Segment``), TRANSFORM ``LVToImage`` (the model's
long-axis frame: its first axis from the base towards the apex, its origin
on the mitral plane), STRING ``LVMetrics`` (JSON) and then IMAGE
``LVLabel`` (1 the cavity, 2 the myocardium, on the frame's grid and
matrix; left out when a newer frame already waits).
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections import Counter, deque
from pathlib import Path

import numpy as np

from .fanout import Broadcaster
from .messages import (MAX_BODY_BYTES, MessageReader, SectorCache, WireError, check_image, decode_image,
                       encode_image, encode_polydata, encode_string, encode_transform, lps_to)
from .session import LiveTracker, StartError

__all__ = ["LiveServer", "DEVICES"]

log = logging.getLogger("spheroseg.apps.live")

#: the device names of the results
DEVICES = {"endo": "LVEndo", "epi": "LVEpi", "label": "LVLabel", "pose": "LVToImage", "metrics": "LVMetrics"}


def _percentile(values, q: float) -> float | None:
    return float(np.percentile(list(values), q)) if values else None


class LiveServer:
    """Track the IMAGE stream of ``source`` and serve the results on ``serve``.

    Parameters
    ----------
    source : (host, port)
        The image server (a PlusServer, :class:`spheroseg.apps.live.replay.Replay`).
    serve : (host, port)
        Where result clients connect (port 0: a free one, see :attr:`address`).
    device : str, optional
        Track only the images of this device name.
    coordinates : str
        ``"ras"`` (3D Slicer's) or ``"lps"``: the world frame of the results.
    label : bool
        Send ``LVLabel``.
    record : path, optional
        Folder each tracked frame is also written to, atomically:
        ``frame_NNNNNN.json`` (the metrics), ``frame_NNNNNN_mask.nii.gz``,
        ``frame_NNNNNN.vtk``.  Nothing is written without it.
    no_data_value
        As :func:`spheroseg.load` (default ``"auto"``: the sector's padding).
    stall_seconds : float
        A source silent this long is reconnected.
    backoff : (float, float)
        First and longest wait between connection attempts, seconds (the
        longest bounds how long a restarted source's first frames wait).
    max_body_bytes : int
        The largest message read.
    status_seconds : float
        Seconds between the console's status lines.
    **tracking
        :class:`spheroseg.apps.live.session.LiveTracker`'s keywords (points,
        ``myocardium``, segmentation options).
    """

    def __init__(self, source, *, serve=("127.0.0.1", 18945), device: str | None = None, coordinates: str = "ras",
                 label: bool = True, record=None, no_data_value="auto", stall_seconds: float = 5.0,
                 backoff=(0.1, 0.5), max_body_bytes: int = MAX_BODY_BYTES, status_seconds: float = 5.0,
                 **tracking):
        lps_to(coordinates)  # checked
        self.source = (str(source[0]), int(source[1]))
        self.device = device
        self.coordinates = coordinates
        self.label = label
        self.record = None if record is None else Path(record)
        self.no_data_value = no_data_value
        self.stall_seconds = float(stall_seconds)
        self.backoff = (float(backoff[0]), float(backoff[1]))
        self.max_body_bytes = int(max_body_bytes)
        self.status_seconds = float(status_seconds)
        self.tracker = LiveTracker(**tracking)
        if self.record is not None:
            try:
                self.record.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ValueError(f"cannot create the record folder {self.record}: {exc.strerror or exc}") from None
        self.received = self.processed = self.dropped = self.connections = 0
        self.skipped: Counter = Counter()
        self.latencies_ms = deque(maxlen=2000)
        self.last_metrics: dict | None = None
        self._stamps = deque(maxlen=64)  # the source's timestamps, for its frame rate
        self._reported: set = set()
        self._slot = None
        self._sector = SectorCache()
        self._ready = threading.Condition()
        self._stop = threading.Event()
        self._fanout = Broadcaster(*serve, backlog=len(DEVICES), retain=True)
        self.address = self._fanout.address
        self._threads = []

    # -- the console ---------------------------------------------------------

    def _once(self, key, level: int, message: str) -> None:
        """Log ``message`` the first time ``key`` comes (a bad input is
        reported once with its reason, then counted)."""
        if key not in self._reported:
            self._reported.add(key)
            log.log(level, message)

    def status(self) -> str:
        m = self.last_metrics or {}
        ef = f"; EF {m['ef']:.1f} % ({m['cycle']})" if m.get("ef") is not None else ""
        latency = (f"; latency median {_percentile(self.latencies_ms, 50):.1f} ms, "
                   f"p99 {_percentile(self.latencies_ms, 99):.1f} ms" if self.latencies_ms else "")
        skipped = f", {sum(self.skipped.values())} skipped" if self.skipped else ""
        return (f"{self.received} frames received, {self.processed} tracked, {self.dropped} dropped (newest "
                f"kept){skipped}{latency}{ef}")

    # -- running -------------------------------------------------------------

    def start(self) -> LiveServer:
        for name, target in (("source", self._source_loop), ("worker", self._work_loop)):
            thread = threading.Thread(target=target, name=f"spheroseg-live-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        self._stop.set()
        with self._ready:
            self._ready.notify_all()
        for thread in self._threads:
            thread.join(timeout=5.0)
        self._fanout.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    @property
    def frame_rate(self) -> float | None:
        """The source's frame rate (frames a second) from its timestamps."""
        steps = np.diff(np.asarray(self._stamps))
        steps = steps[steps > 0]
        return float(1.0 / np.median(steps)) if len(steps) else None

    # -- the source ----------------------------------------------------------

    def _source_loop(self) -> None:
        host, port = self.source
        delay = self.backoff[0]
        while not self._stop.is_set():
            try:
                sock = socket.create_connection(self.source, timeout=1.0)
            except OSError as exc:
                self._once("unreachable", logging.WARNING,
                           f"source {host}:{port} unreachable ({exc.strerror or exc}); retrying, every "
                           f"{self.backoff[1]:g} s at most")
                self._stop.wait(delay)
                delay = min(2 * delay, self.backoff[1])
                continue
            delay = self.backoff[0]
            self._reported.discard("unreachable")
            self.connections += 1
            log.info("connected to source %s:%d", host, port)
            try:
                self._read(sock)
            except Exception as exc:  # noqa: BLE001 (whatever the stream held, the source is connected again)
                log.warning("source stream failed (%s: %s): reconnecting", type(exc).__name__,
                            " ".join(str(exc).split()))
            finally:
                sock.close()

    def _read(self, sock: socket.socket) -> None:
        reader = MessageReader(max_body_bytes=self.max_body_bytes)
        sock.settimeout(0.2)
        heard = time.monotonic()
        while not self._stop.is_set():
            try:
                data = sock.recv(1 << 20)
            except TimeoutError:
                if time.monotonic() - heard > self.stall_seconds:
                    log.warning("source silent for %g s: reconnecting", self.stall_seconds)
                    return
                continue
            except OSError as exc:
                log.warning("source connection lost (%s): reconnecting", exc.strerror or exc)
                return
            if not data:
                log.warning("source closed the connection: reconnecting")
                return
            heard = time.monotonic()
            for item in reader.feed(data):
                self._take(item)

    def _skip(self, error: WireError) -> None:
        reason = error.reason if error.reason in self.skipped or len(self.skipped) < 32 else "other"
        self.skipped[reason] += 1  # (a bounded count however many device names or types a stream makes up)
        if reason == "other":
            return
        self._once(("wire", error.reason), logging.WARNING, f"{error} (reported once; counted in LVMetrics)")

    def _take(self, item) -> None:
        if isinstance(item, WireError):
            return self._skip(item)
        if item.type != "IMAGE":
            return self._skip(WireError(f"type {item.type}", f"a message of type {item.type} is not an image: skipped"))
        if self.device is not None and item.device != self.device:
            return self._skip(WireError(f"device {item.device}",
                                        f"images from device {item.device!r} skipped (--device {self.device})"))
        try:
            checked = check_image(item)  # the header only: the voxels are read if the frame is tracked
        except WireError as error:
            return self._skip(error)
        self._stamps.append(item.timestamp)
        with self._ready:
            index = self.received
            self.received += 1
            if self._slot is not None:
                self.dropped += 1
            self._slot = (item, checked, index)
            self._ready.notify()

    # -- the worker ----------------------------------------------------------

    def _work_loop(self) -> None:
        shown = time.monotonic()
        while not self._stop.is_set():
            with self._ready:
                while self._slot is None and not self._stop.is_set():
                    self._ready.wait(0.2)
                if self._stop.is_set():
                    return
                message, checked, index = self._slot
                self._slot = None
            taken = time.perf_counter()
            try:
                volume, _ = decode_image(message, no_data_value=self.no_data_value, checked=checked,
                                         sector=self._sector)
            except WireError as error:
                self._skip(error)
                continue
            timestamp, received = message.timestamp, message.received
            decoded = time.perf_counter()
            try:
                frame = self.tracker.process(volume, index=index, timestamp=timestamp, frame_rate=self.frame_rate)
            except StartError as exc:
                self._once("start", logging.WARNING, f"frame {index}: {exc}; trying the next frames (reported once)")
                continue
            except Exception as exc:  # noqa: BLE001 (a frame that fails must not end a server that runs for hours)
                log.warning("frame %d: tracking failed (%s: %s): starting again", index, type(exc).__name__,
                            " ".join(str(exc).split()))
                self.tracker.restart()
                continue
            self._reported.discard("start")  # started: a later failure to start is reported again
            if frame.restarted:
                log.warning("frame %d: the image geometry changed: tracking started again", index)
            frame.metrics["stages_ms"] = {"wait": 1000.0 * (taken - received), "decode": 1000.0 * (decoded - taken),
                                          "track": 1000.0 * (time.perf_counter() - decoded)}
            try:
                self._publish(frame, received)
            except Exception as exc:  # noqa: BLE001 (as above)
                log.warning("frame %d: its results could not be sent (%s: %s)", index, type(exc).__name__,
                            " ".join(str(exc).split()))
            if time.monotonic() - shown >= self.status_seconds:
                shown = time.monotonic()
                log.info(self.status())

    def _publish(self, frame, received: float) -> None:
        flip = lps_to(self.coordinates)
        result, stamp = frame.result, frame.timestamp
        out = []
        points, faces = result.mesh()
        scalars = self._segments(result, points) if self.tracker.myocardium else None
        out.append((DEVICES["endo"], encode_polydata(points @ flip.T, faces, device=DEVICES["endo"], timestamp=stamp,
                                                     point_scalars=scalars)))
        if result.epicardium is not None:
            epi_points, epi_faces = result.epicardium.mesh()
            out.append((DEVICES["epi"], encode_polydata(epi_points @ flip.T, epi_faces, device=DEVICES["epi"],
                                                        timestamp=stamp,
                                                        point_scalars=self._segments(result, epi_points))))
        pose = np.eye(4)
        pose[:3, :3] = flip @ result.surface.pose.rotation
        pose[:3, 3] = flip @ result.surface.pose.origin
        out.append((DEVICES["pose"], encode_transform(pose, device=DEVICES["pose"], timestamp=stamp)))
        self.processed += 1
        metrics = {**frame.metrics, "received": self.received, "tracked": self.processed, "dropped": self.dropped,
                   "skipped": dict(self.skipped), "source_fps": self.frame_rate, "coordinates": self.coordinates}
        metrics["latency_ms"] = 1000.0 * (time.perf_counter() - received)
        metrics["stages_ms"]["send"] = metrics["latency_ms"] - sum(metrics["stages_ms"].values())
        out.append((DEVICES["metrics"], encode_string(json.dumps(metrics, default=float), device=DEVICES["metrics"],
                                                      timestamp=stamp)))
        for device, data in out:
            self._fanout.publish(device, data)
        self.latencies_ms.append(metrics["latency_ms"])
        self.last_metrics = metrics
        # the labelmap (a rasterisation of the frame's grid) after the metrics, which it would delay; not at
        # all when a newer frame is already waiting, whose own labelmap comes next
        mask = None
        if self.label and self._slot is None:
            mask = result.mask(frame.volume)
            label = mask.astype(np.uint8)
            if result.epicardium is not None:
                label[result.myocardium_mask(frame.volume)] = 2
            self._fanout.publish(DEVICES["label"], encode_image(label, frame.volume.grid, device=DEVICES["label"],
                                                                timestamp=stamp, coordinates=self.coordinates))
        if self.record is not None:
            self._write(frame, metrics, points, faces, mask)

    @staticmethod
    def _segments(result, points) -> dict:
        from ...surfaces.myocardium import cavity_length, segment_labels

        local = result.surface.pose.to_local(points)
        labels = segment_labels(local, length=cavity_length(result.surface), convention=result.segment_convention)
        return {"Segment": labels.astype(float)}

    def _write(self, frame, metrics: dict, points, faces, mask=None) -> None:
        from ...io import save_mask, write_atomically
        from ...io.outputs import write_json
        from ...io.surface_io import write_mesh

        stem = self.record / f"frame_{frame.index:06d}"
        try:
            mask = frame.result.mask(frame.volume) if mask is None else mask
            write_atomically(f"{stem}_mask.nii.gz", lambda tmp: save_mask(tmp, mask, frame.volume))
            write_mesh(f"{stem}.vtk", points, faces)
            write_json(Path(f"{stem}.json"), metrics)  # last: a frame with its JSON is whole
        except OSError as exc:
            self._once("record", logging.ERROR, f"cannot write to {self.record}: {exc.strerror or exc}")
