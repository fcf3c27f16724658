"""A PLUS-like sender: a 3D+t sequence streamed as OpenIGTLink IMAGE
messages at a set frame rate, looping, to every client connected.

Each frame is encoded once (its body and CRC do not change); only the
header's timestamp is set as it is sent: the frame's acquisition time on a
nominal clock, ``start + k / fps``, as a scanner stamps its frames.  A
client slower than the stream skips frames (at most ``backlog`` wait for
it), as PlusServer's do.
"""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np

from .fanout import Broadcaster
from .messages import check_device, encode_image, set_timestamp

__all__ = ["Replay", "wire_array", "DEVICE"]

#: PlusServer's usual name of a scanner's image
DEVICE = "Image_Reference"


def wire_array(volume) -> np.ndarray:
    """The voxels as they are sent: as 8 or 16-bit integers when they all
    are such (a scanner's), else float32."""
    array = volume.array
    lo, hi = float(array.min()), float(array.max())
    if np.array_equal(array, np.round(array)):
        for dtype in (np.uint8, np.int16, np.uint16):
            info = np.iinfo(dtype)
            if info.min <= lo and hi <= info.max:
                return array.astype(dtype)
    return array


class Replay:
    """Stream ``volumes`` as IMAGE messages.

    Parameters
    ----------
    volumes : sequence of Volume
    host, port : str, int
        Where clients connect (port 0: a free one, see :attr:`address`).
    fps : float
        Frames a second, for :meth:`start` and the timestamps.
    loop : bool
        Start again after the last frame (else :meth:`start` stops there).
    device : str
        The messages' device name.
    coordinates : str
        ``"ras"`` (3D Slicer's, PLUS's usual) or ``"lps"``: the frame of the
        image matrix sent.
    backlog : int
        Frames a slow client may have waiting; older ones are skipped.
    """

    def __init__(self, volumes, *, host: str = "127.0.0.1", port: int = 0, fps: float = 30.0, loop: bool = True,
                 device: str = DEVICE, coordinates: str = "ras", backlog: int = 2):
        volumes = list(volumes)
        if not volumes:
            raise ValueError("a replay needs at least one frame")
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        check_device(device)
        self.fps = float(fps)
        self.loop = loop
        self.frames = [encode_image(wire_array(v), v.grid, device=device, timestamp=0.0, coordinates=coordinates)
                       for v in volumes]
        self._server = Broadcaster(host, port, backlog=backlog)
        self.address = self._server.address
        self.sent = 0
        self._keys = itertools.count()
        self._start = time.time()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def clients(self) -> int:
        return self._server.clients

    def send(self, k: int, *, timestamp: float | None = None) -> None:
        """Send frame ``k`` (modulo the sequence's length) now, stamped
        ``timestamp`` (default: the nominal clock's time of frame ``k``)."""
        stamp = self._start + k / self.fps if timestamp is None else timestamp
        self._server.publish(next(self._keys), set_timestamp(self.frames[k % len(self.frames)], stamp))
        self.sent += 1

    def send_raw(self, data: bytes) -> None:
        """Send bytes as they are (the tests' bad input)."""
        self._server.publish(next(self._keys), bytes(data))

    def start(self) -> Replay:
        """Send the frames at :attr:`fps` in a background thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="spheroseg-replay", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        clock = time.perf_counter()
        self._start = time.time()
        for k in itertools.count():
            if not self.loop and k == len(self.frames):
                return
            delay = clock + k / self.fps - time.perf_counter()
            if self._stop.wait(max(delay, 0.0)):
                return
            self.send(k)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for a stream without ``loop`` to end; whether it did."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._server.close()
