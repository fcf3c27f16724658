"""The viewer's HTTP server: the standard library's ``ThreadingHTTPServer`` on
the loopback interface, a fixed set of routes, and Server-Sent Events.

Security (any web page open in the user's browser can send requests to a
port on 127.0.0.1, so every request is checked):

* bound to 127.0.0.1 only;
* a random token is required on every request: in the URL once (``?token=``),
  then as the ``spheroseg_token`` cookie (HttpOnly, SameSite=Strict) or the
  ``X-Spheroseg-Token`` header; without it 401, with a wrong one 403;
* the ``Host`` header must name this server (127.0.0.1 or localhost and its
  port), which defeats DNS rebinding; a cross-site ``Origin`` is refused;
* only fixed routes exist: the page's own files (by name, from the package)
  and the study's API; nothing maps a request path onto the file system, and
  the only writes are :meth:`Session.save`'s, under its ``save_root``;
* bodies are JSON of at most :data:`MAX_BODY` bytes; anything else gets a 4xx
  and the server goes on (the standard library refuses over-long request
  and header lines itself, 414 and 431).
"""

from __future__ import annotations

import hmac
import json
import queue
import secrets
import threading
from http import HTTPStatus
from http.cookies import CookieError, SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

from .session import Points, Session

MAX_BODY = 64 * 1024
#: the page's files: route -> (file in the package, content type)
STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/static/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
    "/static/viewer.css": ("viewer.css", "text/css; charset=utf-8"),
    "/static/niivue.umd.js": ("vendor/niivue.umd.js", "text/javascript; charset=utf-8"),
}
COOKIE = "spheroseg_token"
#: seconds between keep-alive comments on an idle event stream
KEEPALIVE = 10.0


class RequestError(Exception):
    """A request refused: its status and a one-line reason."""

    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


class ViewerServer(ThreadingHTTPServer):
    """Serves one :class:`Session` on ``127.0.0.1:port`` (``port`` 0: any free one).

    Attributes
    ----------
    token : str
        The secret every request must carry.
    url : str
        The page's address, with the token.
    """

    daemon_threads = True
    allow_reuse_address = True
    #: the listen backlog: a page opens a burst of connections at once (and
    #: a full backlog drops connections for seconds of TCP retries)
    request_queue_size = 256

    def __init__(self, session: Session, *, port: int = 0, token: str | None = None):
        self.session = session
        self.token = token or secrets.token_urlsafe(24)
        self.serving = False
        self._static: dict[str, bytes] = {}
        super().__init__(("127.0.0.1", port), ViewerHandler)
        self.port = self.server_address[1]
        self.hosts = {f"127.0.0.1:{self.port}", f"localhost:{self.port}"}
        self.origins = {f"http://{h}" for h in self.hosts}
        self.url = f"http://127.0.0.1:{self.port}/?token={self.token}"

    def static(self, name: str) -> bytes:
        if name not in self._static:
            self._static[name] = resources.files("spheroseg.viewer").joinpath("static", *name.split("/")).read_bytes()
        return self._static[name]

    def serve_forever(self, poll_interval: float = 0.5) -> None:
        self.serving = True
        try:
            super().serve_forever(poll_interval)
        finally:
            self.serving = False

    def close(self) -> None:
        """End the event streams and the worker, then stop serving."""
        self.session.close()
        if self.serving:  # shutdown() waits for a serve_forever loop, forever if none runs
            self.shutdown()
        self.server_close()

    def serve_in_thread(self) -> threading.Thread:
        """Serve from a daemon thread (tests, notebooks); :meth:`close` stops it."""
        thread = threading.Thread(target=self.serve_forever, name="spheroseg-viewer", daemon=True)
        self.serving = True  # before the thread runs: close() must wait for it
        thread.start()
        return thread


class ViewerHandler(BaseHTTPRequestHandler):
    server: ViewerServer
    server_version = "spheroseg-viewer"
    sys_version = ""
    timeout = 60  # a client that stops sending mid-request frees its thread

    def log_message(self, format, *args):  # noqa: A002 - the standard library's name
        pass  # the page reports what happens; stdout carries only the address

    # dispatch -------------------------------------------------------------

    def do_GET(self):
        self._handle("GET")

    def do_POST(self):
        self._handle("POST")

    def do_PUT(self):
        self._refuse(HTTPStatus.METHOD_NOT_ALLOWED, "only GET and POST")

    do_DELETE = do_PATCH = do_HEAD = do_OPTIONS = do_PUT

    def _handle(self, method: str) -> None:
        try:
            parts = urlsplit(self.path)
            query = parse_qs(parts.query, max_num_fields=8)
            self._check_host()
            first_visit = self._check_token(query, parts.path)
            route = (method, parts.path)
            if method == "GET" and parts.path in STATIC:
                if first_visit:  # the token leaves the address bar for a cookie
                    return self._redirect_with_cookie()
                name, kind = STATIC[parts.path]
                return self._send(HTTPStatus.OK, self.server.static(name), kind)
            handler = ROUTES.get(route)
            if handler is None:
                known = {path for _, path in ROUTES} | set(STATIC)
                raise RequestError(HTTPStatus.METHOD_NOT_ALLOWED if parts.path in known else HTTPStatus.NOT_FOUND,
                                   f"no such route: {method} {parts.path[:100]}")
            body = self._json_body() if method == "POST" else None
            handler(self, query, body)
        except RequestError as exc:
            self._refuse(exc.status, str(exc))
        except ValueError as exc:  # the session's one-line refusals, with the state they left unchanged
            self._refuse(HTTPStatus.BAD_REQUEST, " ".join(str(exc).split())[:500],
                         state=self.server.session.state() if parts.path.startswith("/api/") else None)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as exc:  # never kill the server
            self._refuse(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}")

    # checks ---------------------------------------------------------------

    def _check_host(self) -> None:
        if self.headers.get("Host", "") not in self.server.hosts:
            raise RequestError(HTTPStatus.FORBIDDEN, "wrong Host header")
        origin = self.headers.get("Origin")
        if origin is not None and origin not in self.server.origins:
            raise RequestError(HTTPStatus.FORBIDDEN, "cross-origin request refused")

    def _check_token(self, query: dict, path: str) -> bool:
        """True when the token came in the URL (the first visit)."""
        given = query.get("token", [None])[0]
        from_url = given is not None
        if given is None:
            given = self.headers.get("X-Spheroseg-Token")
        if given is None:
            try:
                morsel = SimpleCookie(self.headers.get("Cookie", "")).get(COOKIE)
            except CookieError:
                morsel = None
            given = None if morsel is None else morsel.value
        if given is None:
            raise RequestError(HTTPStatus.UNAUTHORIZED, "missing token: open the address spheroseg view printed")
        if not hmac.compare_digest(given.encode(), self.server.token.encode()):
            raise RequestError(HTTPStatus.FORBIDDEN, "wrong token")
        return from_url and path == "/"

    def _json_body(self):
        if self.headers.get("Transfer-Encoding"):
            raise RequestError(HTTPStatus.BAD_REQUEST, "chunked bodies are not accepted")
        length = self.headers.get("Content-Length")
        if length is None or not length.isdigit():
            raise RequestError(HTTPStatus.LENGTH_REQUIRED, "a Content-Length is required")
        if int(length) > MAX_BODY:
            raise RequestError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"body over {MAX_BODY} bytes")
        if not self.headers.get("Content-Type", "").startswith("application/json"):
            raise RequestError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "the body must be application/json")
        raw = self.rfile.read(int(length))
        try:
            return json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            raise RequestError(HTTPStatus.BAD_REQUEST, "the body is not valid JSON") from None

    # responses ------------------------------------------------------------

    def _send(self, status: HTTPStatus, body: bytes, kind: str, headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, data, status: HTTPStatus = HTTPStatus.OK) -> None:
        self._send(status, json.dumps(data, allow_nan=False).encode(), "application/json")

    def _refuse(self, status: HTTPStatus, message: str, *, state: dict | None = None) -> None:
        try:
            self.close_connection = True
            self._json({"error": message} if state is None else {"error": message, "state": state}, status)
        except (BrokenPipeError, ConnectionResetError):
            pass

    def _redirect_with_cookie(self) -> None:
        self.send_response(HTTPStatus.SEE_OTHER)
        self.send_header("Location", "/")
        self.send_header("Set-Cookie", f"{COOKIE}={self.server.token}; HttpOnly; SameSite=Strict; Path=/")
        self.send_header("Content-Length", "0")
        self.send_header("Referrer-Policy", "no-referrer")
        self.end_headers()

    # routes ---------------------------------------------------------------

    def study(self, query, body) -> None:
        self._json(self.server.session.describe())

    def volume(self, query, body) -> None:
        self._send(HTTPStatus.OK, self.server.session.nifti(), "application/octet-stream")

    def surface(self, query, body) -> None:
        self._frame_event(query, self.server.session.surface_event)

    def epicardium(self, query, body) -> None:
        self._frame_event(query, self.server.session.epicardium_event)

    def views(self, query, body) -> None:
        self._frame_event(query, self.server.session.views_event)

    def _frame_event(self, query, event) -> None:
        """``event(frame)`` of the query's frame, or 404 before it is segmented."""
        frame = self.server.session.check_frame(_integer(query.get("frame", ["0"])[0], "frame"))
        data = event(frame)
        if data is None:
            raise RequestError(HTTPStatus.NOT_FOUND, f"frame {frame} is not segmented with the current points")
        self._json(data)

    def points(self, query, body) -> None:
        body = _object(body)
        job = self.server.session.set_points(Points.from_json(body), frame=body.get("frame", 0))
        self._json({"job": job, "state": self.server.session.state()})

    def find(self, query, body) -> None:
        self._json({**self.server.session.find(frame=_object(body).get("frame", 0)),
                    "state": self.server.session.state()})

    def track(self, query, body) -> None:
        job = self.server.session.track(frame=_object(body).get("frame", 0))
        self._json({"job": job, "state": self.server.session.state()})

    def save(self, query, body) -> None:
        body = _object(body)
        self._json({**self.server.session.save(body.get("folder"), frame=body.get("frame", 0),
                                               report=bool(body.get("report", True))),
                    "state": self.server.session.state()})

    def events(self, query, body) -> None:
        session = self.server.session
        stream = session.events.subscribe()
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(b"retry: 1000\n\n")
            self.wfile.flush()
            while not session.events.closed:
                try:
                    kind, data = stream.get(timeout=KEEPALIVE)
                except queue.Empty:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    continue
                if kind == "close":
                    break
                self.wfile.write(f"event: {kind}\ndata: {json.dumps(data, allow_nan=False)}\n\n".encode())
                self.wfile.flush()
        finally:
            session.events.unsubscribe(stream)
            self.close_connection = True


def _object(body) -> dict:
    if not isinstance(body, dict):
        raise RequestError(HTTPStatus.BAD_REQUEST, "the body must be a JSON object")
    return body


def _integer(text: str, name: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise RequestError(HTTPStatus.BAD_REQUEST, f"{name} must be an integer, got {text[:20]!r}") from None


ROUTES = {
    ("GET", "/api/study"): ViewerHandler.study,
    ("GET", "/api/volume.nii"): ViewerHandler.volume,
    ("GET", "/api/surface"): ViewerHandler.surface,
    ("GET", "/api/epicardium"): ViewerHandler.epicardium,
    ("GET", "/api/views"): ViewerHandler.views,
    ("GET", "/api/events"): ViewerHandler.events,
    ("POST", "/api/points"): ViewerHandler.points,
    ("POST", "/api/find"): ViewerHandler.find,
    ("POST", "/api/track"): ViewerHandler.track,
    ("POST", "/api/save"): ViewerHandler.save,
}
