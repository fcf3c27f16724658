"""An OpenIGTLink server that sends messages to every client connected.

A message is published under a key.  Each client holds at most one pending
message per key, the newest (an older one still unsent is replaced), and at
most ``backlog`` keys: a slow client skips messages, it never makes a queue
grow.  With ``retain``, the newest message of each key is kept and sent at
once to a client that connects (3D Slicer joining mid-stream gets the
latest results).  What clients send is read and dropped.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
from collections import OrderedDict

__all__ = ["Broadcaster", "parse_address"]

log = logging.getLogger("spheroseg.apps.live")


def parse_address(text: str, *, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``HOST:PORT`` or ``PORT`` as ``(host, port)``; a one-line error otherwise."""
    host, _, port = str(text).rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"expected HOST:PORT or PORT, got {text!r}") from None
    if not 0 <= number <= 65535:
        raise ValueError(f"a port is from 0 to 65535, got {number}")
    return host or default_host, number


class _Client:
    def __init__(self, sock: socket.socket, address, backlog: int):
        self.sock = sock
        self.address = address
        self.backlog = backlog
        self.pending: OrderedDict[object, bytes] = OrderedDict()
        self.skipped = 0
        self.ready = threading.Condition()
        self.closed = False

    def put(self, key, data: bytes) -> None:
        with self.ready:
            if self.pending.pop(key, None) is not None:
                self.skipped += 1
            self.pending[key] = data
            while len(self.pending) > self.backlog:
                self.pending.popitem(last=False)
                self.skipped += 1
            self.ready.notify()

    def take(self, timeout: float) -> list[bytes]:
        with self.ready:
            if not self.pending:
                self.ready.wait(timeout)
            items = list(self.pending.values())
            self.pending.clear()
            return items


class Broadcaster:
    """Listen on ``(host, port)`` and send what is published to every client.

    Parameters
    ----------
    host, port : str, int
        Where to listen (port 0: a free one, see :attr:`address`).
    backlog : int
        Keys a client may have pending.
    retain : bool
        Send a connecting client the newest message of every key.
    send_timeout : float
        Seconds a client may take to accept a message before it is dropped.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, backlog: int = 16, retain: bool = False,
                 send_timeout: float = 5.0):
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self.address = self._listener.getsockname()[:2]
        self.backlog = int(backlog)
        self.retain = retain
        self.send_timeout = float(send_timeout)
        self._latest: OrderedDict[object, bytes] = OrderedDict()
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closing = threading.Event()
        self._threads = [threading.Thread(target=self._accept, name="spheroseg-live-accept", daemon=True)]
        self._threads[0].start()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, key, data: bytes) -> None:
        """Send ``data`` to every client (replacing one still pending under ``key``)."""
        with self._lock:
            if self.retain:
                self._latest.pop(key, None)
                self._latest[key] = data
            clients = list(self._clients)
        for client in clients:
            client.put(key, data)

    def _accept(self) -> None:
        while not self._closing.is_set():
            try:
                sock, address = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self._closing.is_set():
                sock.close()
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(self.send_timeout)
            client = _Client(sock, address, max(self.backlog, len(self._latest)))
            with self._lock:
                for key, data in self._latest.items():
                    client.put(key, data)
                self._clients.append(client)
            log.info("client %s:%d connected", *address[:2])
            thread = threading.Thread(target=self._serve, args=(client,), name="spheroseg-live-client", daemon=True)
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]  # bounded over hours
            thread.start()

    def _serve(self, client: _Client) -> None:
        reason = "stopped"
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select([client.sock], [], [], 0)
                if readable and not client.sock.recv(1 << 16):
                    reason = "disconnected"
                    return
                for data in client.take(0.05):
                    client.sock.sendall(data)
        except TimeoutError:
            reason = f"did not accept data for {self.send_timeout:g} s"
        except OSError as exc:
            reason = f"disconnected ({exc.strerror or exc})"
        finally:
            with self._lock:
                if client in self._clients:
                    self._clients.remove(client)
            client.sock.close()
            log.info("client %s:%d %s", client.address[0], client.address[1], reason)

    def close(self) -> None:
        """Stop listening and disconnect every client."""
        # no connection accepted any more (not even by the kernel's backlog) before the clients are let go:
        # one reconnecting at once is refused, as by a server that is gone
        self._closing.set()
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._threads[0].join(timeout=2.0)
        self._listener.close()
        self._stop.set()
        for thread in self._threads[1:]:
            thread.join(timeout=2.0)
