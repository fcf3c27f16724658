"""A client of ``spheroseg live``: the results as they arrive (the tests'
and the benchmark's 3D Slicer)."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections import deque

from .messages import Message, MessageReader, WireError, decode_string

__all__ = ["ResultClient"]


class ResultClient:
    """Connect to ``address`` and keep what comes: ``metrics`` (the
    ``LVMetrics`` JSON of each frame, with ``arrived``, the
    :func:`time.time` it was read), ``latest`` (the newest message of each
    device) and ``errors``; at most ``keep`` metrics are held."""

    def __init__(self, address, *, keep: int = 10000, timeout: float = 5.0):
        self.sock = socket.create_connection(tuple(address), timeout=timeout)
        self.sock.settimeout(0.1)
        self.metrics: deque = deque(maxlen=keep)
        self.latest: dict[str, Message] = {}
        self.errors: list[WireError] = []
        self._changed = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="spheroseg-live-client", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        reader = MessageReader()
        while not self._stop.is_set():
            try:
                data = self.sock.recv(1 << 20)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            for item in reader.feed(data):
                with self._changed:
                    if isinstance(item, WireError):
                        self.errors.append(item)
                        continue
                    self.latest[item.device] = item
                    if item.device == "LVMetrics":
                        self.metrics.append({**json.loads(decode_string(item)), "arrived": time.time()})
                    self._changed.notify_all()

    def wait_for(self, predicate, timeout: float = 10.0) -> bool:
        """Wait until ``predicate(self)`` holds; whether it did in time."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._changed.wait(min(left, 0.1))
            return True

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.sock.close()
