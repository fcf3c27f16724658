"""The viewer's server against requests a hostile page or a broken client
could send, and its session without a browser."""

import base64
import http.client
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import interruptible

import spheroseg
from spheroseg.io import save_volume, write_markups
from spheroseg.tracking.epicardium import DARK_WALL
from spheroseg.synthetic.phantom import FORMATIONS, POSTPROCESSINGS, make_phantom, make_sequence
from spheroseg.apps.viewer import open_viewer
from spheroseg.apps.viewer.server import MAX_BODY
from spheroseg.apps.viewer.session import Points


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=3, spacing=2.0)


@pytest.fixture
def server(phantom, tmp_path):
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    (tmp_path / "out").mkdir()
    server = open_viewer(path, save_root=tmp_path / "out", token="secret-token")
    server.serve_in_thread()
    yield server
    server.close()


def request(server, method, path, *, body=None, headers=None, token=True, host=None):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
    conn.putheader("Host", host or f"127.0.0.1:{server.port}")
    if token:
        conn.putheader("X-Spheroseg-Token", server.token)
    for key, value in (headers or {}).items():
        conn.putheader(key, value)
    if body is not None:
        data = body if isinstance(body, bytes) else json.dumps(body).encode()
        if "Content-Type" not in (headers or {}):
            conn.putheader("Content-Type", "application/json")
        conn.putheader("Content-Length", str(len(data)))
        conn.endheaders(data)
    else:
        conn.endheaders()
    response = conn.getresponse()
    payload = response.read()
    conn.close()
    return response, payload


def alive(server):
    response, payload = request(server, "GET", "/api/study")
    return response.status == 200 and json.loads(payload)["frames"] == 1


def wait_for(server, frame=0, timeout=60.0):
    """The frame's final surface, polled as a page without events would."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        response, payload = request(server, "GET", f"/api/surface?frame={frame}")
        if response.status == 200:
            return json.loads(payload)
        time.sleep(0.05)
    raise AssertionError("no surface")


def test_listens_on_loopback_only(server):
    assert server.server_address[0] == "127.0.0.1"
    assert server.socket.family == socket.AF_INET
    assert server.url.startswith(f"http://127.0.0.1:{server.port}/?token=")


def test_token_required_everywhere(server):
    for path in ("/", "/api/study", "/api/volume.nii", "/static/viewer.js", "/api/events"):
        response, payload = request(server, "GET", path, token=False)
        assert response.status == 401, path
        assert "token" in json.loads(payload)["error"]
    response, _ = request(server, "POST", "/api/points", body={"apex": [0, 0, 0]}, token=False)
    assert response.status == 401
    response, _ = request(server, "GET", "/api/study", token=False, headers={"X-Spheroseg-Token": "guess"})
    assert response.status == 403
    response, _ = request(server, "GET", "/?token=guess", token=False)
    assert response.status == 403
    response, _ = request(server, "GET", "/api/study", token=False, headers={"Cookie": "spheroseg_token=guess"})
    assert response.status == 403
    assert alive(server)


def test_token_in_the_address_becomes_a_cookie(server):
    response, _ = request(server, "GET", f"/?token={server.token}", token=False)
    assert response.status == 303 and response.getheader("Location") == "/"
    cookie = response.getheader("Set-Cookie")
    assert f"spheroseg_token={server.token}" in cookie and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    response, payload = request(server, "GET", "/", token=False, headers={"Cookie": f"spheroseg_token={server.token}"})
    assert response.status == 200 and b"niivue.umd.js" in payload


def test_host_and_origin_checked(server):
    # DNS rebinding: a page of evil.example resolved to 127.0.0.1 sends its own Host
    response, _ = request(server, "GET", "/api/study", host=f"evil.example:{server.port}")
    assert response.status == 403
    response, _ = request(server, "GET", "/api/study", host="127.0.0.1:1")
    assert response.status == 403
    response, _ = request(server, "POST", "/api/track", body={"frame": 0}, headers={"Origin": "http://evil.example"})
    assert response.status == 403
    response, _ = request(server, "GET", "/api/study", host=f"localhost:{server.port}")
    assert response.status == 200


@pytest.mark.parametrize("path", [
    "/../../etc/passwd", "/static/../../../etc/passwd", "/static/..%2f..%2fsession.py", "//etc/passwd",
    "/etc/passwd", "/static/vendor/VERSION", "/static/", "/api/volume.nii/../../x", "/static/viewer.js/",
    "/api/../server.py", "/%00", "/api/surface/../../../../etc/passwd",
])
def test_paths_outside_the_routes(server, path):
    response, payload = request(server, "GET", path)
    assert 400 <= response.status < 500, path
    assert b"root:" not in payload
    assert alive(server)


def test_methods_and_bodies(server):
    response, _ = request(server, "PUT", "/api/points", body={"apex": [0, 0, 0]})
    assert response.status == 405
    response, _ = request(server, "GET", "/api/points")
    assert response.status == 405
    response, payload = request(server, "POST", "/api/points", body=b"{not json")
    assert response.status == 400 and "JSON" in json.loads(payload)["error"]
    response, _ = request(server, "POST", "/api/points", body=b"\xff\xfe\x00garbage")
    assert response.status == 400
    response, _ = request(server, "POST", "/api/points", body=b"[1, 2, 3]")
    assert response.status == 400
    response, _ = request(server, "POST", "/api/points", body={"apex": [0, 0, 0]}, headers={"Content-Type": "text/plain"})
    assert response.status == 415
    response, _ = request(server, "POST", "/api/points", body=b"x" * (MAX_BODY + 1))
    assert response.status == 413
    response, payload = request(server, "POST", "/api/points", body={"apex": ["a", 0, 0], "base": [1, 2]})
    assert response.status == 400 and "apex" in json.loads(payload)["error"]
    response, payload = request(server, "POST", "/api/points", body={"apex": [1e9, 0, 0], "base": [0, 0, 0]})
    assert response.status == 400 and "apex" in json.loads(payload)["error"]
    response, _ = request(server, "POST", "/api/points", body={"frame": 7, "apex": [0, 0, 0]})
    assert response.status == 400
    response, _ = request(server, "GET", "/api/surface?frame=abc")
    assert response.status == 400
    response, _ = request(server, "POST", "/api/track", body={"frame": 0})
    assert response.status == 400  # one frame: nothing to track
    assert alive(server)


def test_huge_and_garbage_requests_leave_the_server_up(server):
    response, _ = request(server, "GET", "/api/study", headers={"X-Padding": "a" * 70_000})
    assert response.status == 431
    response, _ = request(server, "GET", "/api/study", headers={f"X-{k}": "1" for k in range(120)})
    assert response.status == 431
    response, _ = request(server, "GET", "/api/study?" + "a" * 70_000)
    assert response.status == 414
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        raw.sendall(b"\x16\x03\x01\x02\x00garbage that is not HTTP\r\n\r\n")
        reply = b"".join(iter(lambda: raw.recv(4096), b""))
        assert b"400" in reply  # the standard library's error page (no status line: it looked like HTTP/0.9)
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        raw.sendall(b"POST /api/points HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 99999999999\r\n\r\n")
        assert b" 403 " in raw.recv(200)  # refused on the Host before any body is read
    assert alive(server)


def test_save_only_inside_the_save_root(server, phantom, tmp_path):
    apex, base = phantom.apex.tolist(), phantom.base.tolist()
    response, _ = request(server, "POST", "/api/points", body={"frame": 0, "apex": apex, "base": base})
    assert response.status == 200
    wait_for(server)
    for folder in ("../escape", "/tmp/escape", "a/../../escape", "", "   ", "a/./../..", 5):
        response, payload = request(server, "POST", "/api/save", body={"folder": folder, "report": False})
        assert response.status == 400, folder
    assert not (tmp_path / "escape").exists() and not list(tmp_path.glob("out/.spheroseg-save-*"))
    response, payload = request(server, "POST", "/api/save", body={"folder": "case/one", "report": False})
    assert response.status == 200, payload
    saved = json.loads(payload)
    assert saved["folder"] == str((tmp_path / "out" / "case" / "one").resolve())
    assert "mask.mha" in saved["files"] and "points.mrk.json" in saved["files"]
    response, payload = request(server, "POST", "/api/save", body={"folder": "case/one", "report": False})
    assert response.status == 400 and "exists" in json.loads(payload)["error"]
    assert sorted(p.name for p in (tmp_path / "out" / "case").iterdir()) == ["one"]  # nothing left half-written


def test_events_stream_surfaces(server, phantom):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    conn.request("GET", "/api/events", headers={"Host": f"127.0.0.1:{server.port}", "X-Spheroseg-Token": server.token})
    stream = conn.getresponse()
    assert stream.status == 200 and stream.getheader("Content-Type") == "text/event-stream"
    assert stream.fp.readline() == b"retry: 1000\n"
    apex, base = phantom.apex.tolist(), phantom.base.tolist()
    response, payload = request(server, "POST", "/api/points", body={"frame": 0, "apex": apex, "base": base})
    job = json.loads(payload)["job"]
    events = []
    while not (events and events[-1]["final"]):
        line = stream.fp.readline()
        if line.startswith(b"data: "):
            events.append(json.loads(line[6:]))
    conn.close()
    assert events[0]["iteration"] == 0 and not events[0]["final"] and all(e["job"] == job for e in events)
    final = events[-1]
    result = spheroseg.segment(server.session.frames[0], phantom.apex, phantom.base)
    vertices = np.frombuffer(base64.b64decode(final["vertices"]), "<f4").reshape(-1, 3)
    np.testing.assert_allclose(vertices, result.surface.mesh(48, 24)[0], atol=1e-3)
    assert final["volume_ml"] == pytest.approx(result.volume_ml, rel=1e-12)
    faces = np.frombuffer(base64.b64decode(json.loads(request(server, "GET", "/api/study")[1])["faces"]), "<u4")
    np.testing.assert_array_equal(faces.reshape(-1, 3), result.surface.mesh(48, 24)[1])


def test_display_image_round_trip(phantom, tmp_path):
    """The NIfTI the page shows is the study on its grid (its origin and
    spacing back through SimpleITK), grey levels scaled to 0-255."""
    seq = make_sequence(seed=1, n_frames=3, spacing=2.5)
    path = tmp_path / "cine.nrrd"
    save_volume(path, list(seq.volumes))
    server = open_viewer(path, save_root=tmp_path)
    try:
        data = server.session.nifti()
        (tmp_path / "shown.nii").write_bytes(data)
        image = sitk.ReadImage(str(tmp_path / "shown.nii"))
        assert image.GetDimension() == 4 and image.GetSize()[3] == 3
        assert image.GetPixelID() == sitk.sitkUInt8
        first = seq.volumes[0]
        np.testing.assert_allclose(image.GetSpacing()[:3], first.spacing)
        np.testing.assert_allclose(image.GetOrigin()[:3], first.origin, atol=1e-4)
        shown = sitk.GetArrayFromImage(image)  # [t, z, y, x]
        arrays = np.array([v.array for v in seq.volumes])
        lo, hi = arrays.min(), arrays.max()
        np.testing.assert_allclose(shown.astype(float), np.rint((arrays - lo) * 255 / (hi - lo)), atol=1)
    finally:
        server.close()


def test_session_tracks_like_the_api(tmp_path):
    seq = make_sequence(seed=4, n_frames=3, spacing=2.5)
    path = tmp_path / "cine.nrrd"
    save_volume(path, list(seq.volumes))
    first = seq.frames[0]
    write_markups(tmp_path / "points.mrk.json", apex=first.apex, base=first.base)
    server = open_viewer(path, save_root=tmp_path, points=tmp_path / "points.mrk.json")
    server.serve_in_thread()
    try:
        wait_for(server)  # the given points are segmented at once
        request(server, "POST", "/api/track", body={"frame": 1})
        end = time.monotonic() + 60
        while json.loads(request(server, "GET", "/api/study")[1])["tracking"] is None:
            assert time.monotonic() < end
            time.sleep(0.05)
        tracking = json.loads(request(server, "GET", "/api/study")[1])["tracking"]
        session = server.session
        # from frame 1: forwards to the end, then from frame 1 again backwards
        forward = spheroseg.track(session.frames[1:], first.apex, first.base)
        backward = spheroseg.track(session.frames[1::-1], first.apex, first.base)
        expected = [backward.volumes_ml[1], *forward.volumes_ml]
        np.testing.assert_allclose(tracking["volumes_ml"], expected, rtol=1e-12)
        assert Points.from_json(session.points.as_json()).same(session.points)
        # the start frame is the study's state, as the page shows and saves it
        state = json.loads(request(server, "GET", "/api/study")[1])["state"]
        assert tracking["start_frame"] == 1 and state["tracked"] and state["start_frame"] == 1
    finally:
        server.close()


def test_command_prints_the_address_and_stops_on_ctrl_c(phantom, tmp_path):
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    process = subprocess.Popen([sys.executable, "-m", "spheroseg", "view", str(path), "--no-browser"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                               preexec_fn=interruptible)
    try:
        first = process.stdout.readline().strip()
        assert first.startswith("http://127.0.0.1:") and "/?token=" in first
        port = int(first.split(":")[2].split("/")[0])
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        conn.request("GET", "/api/study", headers={"X-Spheroseg-Token": first.split("token=")[1]})
        assert conn.getresponse().status == 200
        conn.close()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 0
        assert "stopped" in process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()


def test_command_refuses_bad_input(tmp_path):
    result = subprocess.run([sys.executable, "-m", "spheroseg", "view", str(tmp_path / "missing.mha"), "--no-browser"],
                            capture_output=True, text=True, timeout=60, env={**os.environ})
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "missing.mha" in result.stderr


def test_vendored_niivue_is_the_recorded_one():
    import hashlib
    from importlib import resources

    vendor = resources.files("spheroseg.apps.viewer").joinpath("static", "vendor")
    record = vendor.joinpath("VERSION").read_text().split("\n")
    assert record[0] == "@niivue/niivue 0.69.0"
    digest = hashlib.sha256(vendor.joinpath("niivue.umd.js").read_bytes()).hexdigest()
    assert record[2] == f"sha256 {digest}"
    licences = vendor.joinpath("LICENSES.txt").read_text()
    assert "BSD 2-Clause License" in licences and "Copyright (c) 2021, Niivue" in licences


def test_a_beam_space_study_is_shown_scan_converted_and_segmented_in_its_beams(tmp_path):
    from spheroseg.volumes.beamspace import scan_convert
    from spheroseg.synthetic.phantom import FORMATIONS

    ph = make_phantom(seed=1, spacing=2.0, formation=FORMATIONS["default"], beam_space=True)
    path = tmp_path / "beams.mha"
    save_volume(path, ph.beam_volume)
    server = open_viewer(path, save_root=tmp_path)
    server.serve_in_thread()
    try:
        (tmp_path / "shown.nii").write_bytes(server.session.nifti())
        shown = sitk.ReadImage(str(tmp_path / "shown.nii"))
        grid = scan_convert(server.session.frames[0]).grid
        assert shown.GetSize() == grid.shape[::-1]
        np.testing.assert_allclose(shown.GetOrigin(), grid.origin, atol=1e-4)
        body = {"frame": 0, "apex": ph.apex.tolist(), "base": ph.base.tolist()}
        assert request(server, "POST", "/api/points", body=body)[0].status == 200
        final = wait_for(server)
        expected = spheroseg.segment(server.session.frames[0], ph.apex, ph.base)
        assert final["volume_ml"] == pytest.approx(expected.volume_ml, rel=1e-12)
    finally:
        server.close()


def test_a_viewer_that_cannot_listen_stops_its_worker_first(phantom, tmp_path):
    # the command then exits with no thread inside numba (an exit during its
    # loading could abort in LLVM's teardown: 4 to 7 exits in 50 did)
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    before = set(threading.enumerate())
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(OSError):
            open_viewer(path, port=taken.getsockname()[1])
    assert not [t for t in set(threading.enumerate()) - before if t.name == "spheroseg-viewer-worker"]


def test_command_refuses_a_port_in_use(phantom, tmp_path):
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run([sys.executable, "-m", "spheroseg", "view", str(path), "--no-browser", "--port",
                                 str(port)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip() == f"spheroseg: error: cannot listen on 127.0.0.1:{port}: Address already in use"


def test_a_slow_page_loses_intermediate_surfaces_only():
    from spheroseg.apps.viewer.session import EventStream

    stream = EventStream(capacity=4)
    stream.put("surface", {"final": True, "n": 0})
    for n in range(1, 7):
        stream.put("surface", {"final": False, "n": n})
    stream.put("tracked", {"n": 7})
    got = [stream.get(timeout=0.1) for _ in range(4)]
    assert [(kind, data["n"]) for kind, data in got] == [("surface", 0), ("surface", 5), ("surface", 6), ("tracked", 7)]
    with pytest.raises(queue.Empty):
        stream.get(timeout=0.01)


def test_a_burst_of_connections_is_answered(server):
    """200 connections at once (a page's reload, a script): all answered
    within 5 s (a listen backlog of 5 dropped some for many seconds of TCP
    retries)."""
    get = (f"GET /api/study HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
               f"X-Spheroseg-Token: {server.token}\r\nConnection: close\r\n\r\n").encode()
    sockets = []
    for _ in range(200):  # every connection opened before any is served
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", server.port))
        sockets.append(s)
    answered = 0
    end = time.monotonic() + 5.0
    try:
        for s in sockets:
            s.settimeout(max(0.01, end - time.monotonic()))
            try:
                s.sendall(get)
                answered += s.recv(12).startswith(b"HTTP/1.0 200")
            except OSError:
                pass
    finally:
        for s in sockets:
            s.close()
    assert answered == 200
    # still locked down
    assert request(server, "GET", "/api/study", token=False)[0].status == 401
    assert request(server, "GET", "/api/study", host="evil.example:80")[0].status == 403


def test_points_outside_the_data_are_refused(server, phantom):
    """Outside the image, and in the padding around the echo sector: a
    one-line 400 naming the point in LPS mm, and the points unchanged."""
    session = server.session
    lo, hi = session.display[0].bounds
    corner = lo + 0.02 * (hi - lo)  # the phantom's sector leaves its corners empty
    assert session.display[0].no_data_mask is not None
    for apex, words in ((hi + 10.0, "outside the image"), (corner, "outside the echo's data")):
        response, payload = request(server, "POST", "/api/points", body={"frame": 0, "apex": apex.tolist()})
        assert response.status == 400
        message = json.loads(payload)["error"]
        assert words in message and f"{apex[0]:.1f}, {apex[1]:.1f}, {apex[2]:.1f} LPS mm" in message, message
        assert session.points.apex is None
    response, _ = request(server, "POST", "/api/points", body={"frame": 0, "apex": phantom.apex.tolist()})
    assert response.status == 200 and np.array_equal(session.points.apex, phantom.apex)


class _NoVentricle(ValueError):
    pass


def test_find_places_apex_and_base_from_the_locator(server, phantom, monkeypatch):
    """``/api/find`` calls ``spheroseg.locate.locate`` (stubbed here: the
    locator has its own tests) and segments from what it returns."""
    import spheroseg.apps.viewer.session as session_module
    from spheroseg.tracking.locate import Located

    calls = []

    def found(volume):
        calls.append(volume)
        return Located(apex=phantom.apex, base=phantom.base, normal=np.array([0.0, 0.0, 1.0]),
                       confidence=0.75, reason="stub")

    monkeypatch.setattr(session_module, "locate", found)
    response, payload = request(server, "POST", "/api/find", body={"frame": 0})
    assert response.status == 200, payload
    data = json.loads(payload)
    assert calls == [server.session.display[0]]
    assert data["apex"] == phantom.apex.tolist() and data["base"] == phantom.base.tolist()
    assert data["confidence"] == 0.75 and data["reason"] == "stub"
    assert wait_for(server)["job"] == data["job"]
    api = spheroseg.segment(server.session.frames[0], phantom.apex, phantom.base)
    np.testing.assert_allclose(server.session.results[0][1].surface.coefficients, api.surface.coefficients,
                               atol=1e-9)

    def nothing(volume):
        raise _NoVentricle("no ventricle found: no dark cavity")

    monkeypatch.setattr(session_module, "locate", nothing)
    response, payload = request(server, "POST", "/api/find", body={"frame": 0})
    assert response.status == 400 and json.loads(payload)["error"] == "no ventricle found: no dark cavity"
    assert alive(server)


def test_given_points_are_checked_against_the_located_ventricle(server, phantom):
    """As :func:`spheroseg.segment` does: apex and base swapped make the
    result poor, with a warning naming the point, and the page's banner
    gets it; the right points are not flagged.  The ventricle is located
    once a frame, while the user places the base after the apex."""
    import spheroseg.apps.viewer.session as session_module

    calls = []
    real = session_module.locate

    def counted(volume):
        calls.append(volume)
        return real(volume)

    session_module.locate, restore = counted, real
    try:
        response, _ = request(server, "POST", "/api/points", body={"frame": 0, "apex": phantom.apex.tolist()})
        assert response.status == 200
        end = time.monotonic() + 60
        while not calls and time.monotonic() < end:
            time.sleep(0.05)
        assert len(calls) == 1  # located after the apex alone
        for apex, base in ((phantom.base, phantom.apex), (phantom.apex, phantom.base)):
            response, payload = request(server, "POST", "/api/points",
                                        body={"frame": 0, "apex": apex.tolist(), "base": base.tolist()})
            assert response.status == 200, payload
            event = wait_for(server)
            api = spheroseg.segment(server.session.frames[0], apex, base)
            assert event["poor"] == api.quality["poor"]
            assert event["warnings"] == api.quality["warnings"]
            if apex is phantom.base:
                assert event["poor"] and any("swapped" in w for w in event["warnings"])
            else:
                assert not any("swapped" in w or "mitral plane" in w for w in event["warnings"])
    finally:
        session_module.locate = restore
    assert len(calls) == 1


def test_a_dark_wall_is_flagged_as_the_api_flags_it(tmp_path):
    """The viewer's checks are segment's (:func:`spheroseg.segment.add_checks`):
    a myocardium darker than the tissue beyond it, smoothed so that the
    intensity interface cannot tell the wall from that tissue, is a warning
    on the page too."""
    ph = make_phantom(seed=0, spacing=2.0, formation=FORMATIONS["contrast_low"],
                      **POSTPROCESSINGS["gaussian_2mm"])
    path = tmp_path / "dark.mha"
    save_volume(path, ph.volume)
    write_markups(tmp_path / "points.mrk.json", apex=ph.apex, base=ph.base)
    server = open_viewer(path, save_root=tmp_path, points=tmp_path / "points.mrk.json")
    server.serve_in_thread()
    try:
        event = wait_for(server)
        api = spheroseg.segment(server.session.frames[0], ph.apex, ph.base)
        assert DARK_WALL in api.quality["warnings"]
        assert event["poor"] and event["warnings"] == api.quality["warnings"]
    finally:
        server.close()

def test_command_prints_the_address_once_it_answers(phantom, tmp_path):
    """The kernels load before the address is printed (a first run compiles
    them for tens of seconds; here the loading is made 3 s slow): the page's
    address answers as soon as it is printed."""
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    code = ("import sys, time, spheroseg.warmup as w; load = w.load_kernels\n"
            "w.load_kernels = lambda **k: (time.sleep(3), load(**k))[1]\n"
            "from spheroseg.apps.cli import main; sys.exit(main(sys.argv[1:]))")
    process = subprocess.Popen([sys.executable, "-c", code, "view", str(path), "--no-browser"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                               preexec_fn=interruptible)
    try:
        address = process.stdout.readline().strip()
        port = int(address.split(":")[2].split("/")[0])
        connection = socket.create_connection(("127.0.0.1", port), timeout=5)
        connection.settimeout(1.0)  # the kernels are loaded: no more waiting than a request's
        connection.sendall(f"GET /api/study HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                           f"X-Spheroseg-Token: {address.split('token=')[1]}\r\n\r\n".encode())
        assert connection.recv(12) == b"HTTP/1.0 200"
        connection.close()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 0
        # a cold start is not silent: each long step is said before it starts
        said = process.stderr.read()
        assert said.index(f"{path} read; loading the numerical kernels") < said.index("serving")
    finally:
        if process.poll() is None:
            process.kill()


def test_every_answer_carries_the_state_it_applies_to(server, phantom):
    """Points accepted or refused, the study, a save: each answer carries the
    session's state (points, options, start frame), and a refusal's is the
    state it left unchanged, so that the page shows what the server holds
    (round-4 defect 1: a drag released in the padding)."""
    session = server.session
    first = {"frame": 0, "apex": phantom.apex.tolist(), "base": phantom.base.tolist()}
    response, payload = request(server, "POST", "/api/points", body=first)
    assert response.status == 200
    state = json.loads(payload)["state"]
    assert state["points"] == {**session.points.as_json()} and state["points"]["apex"] == phantom.apex.tolist()
    assert state["options"] == session.options.as_parameters() and state["start_frame"] is None
    lo, hi = session.display[0].bounds
    corner = lo + 0.02 * (hi - lo)  # the sector's padding
    response, payload = request(server, "POST", "/api/points", body={**first, "apex": corner.tolist()})
    assert response.status == 400
    refused = json.loads(payload)
    assert "outside the echo's data" in refused["error"]
    assert refused["state"]["points"] == state["points"] and refused["state"]["job"] == state["job"]
    assert json.loads(request(server, "GET", "/api/study")[1])["state"] == refused["state"]
    wait_for(server)
    response, payload = request(server, "POST", "/api/save", body={"folder": "one", "frame": 0})
    assert response.status == 200, payload
    saved = json.loads(payload)
    marks = spheroseg.io.read_markups(os.path.join(saved["folder"], "points.mrk.json"))
    np.testing.assert_array_equal(marks["apex"], saved["state"]["points"]["apex"])
    np.testing.assert_array_equal(marks["base"], saved["state"]["points"]["base"])
    # the final surface names the points it was made from
    assert wait_for(server)["points"] == state["points"]


def test_find_with_low_confidence_is_poor_as_the_api_says(server, phantom, monkeypatch):
    """A location the locator is not confident of: Find's answer says poor
    with the API's warning at once, and the segmentation from its points is
    poor with it (as ``spheroseg.segment`` of the volume alone: locate.annotate),
    round-4 defect 3; the points dragged, they are given ones, which such a
    location cannot check: said on the banner, not poor."""
    import spheroseg.apps.viewer.session as session_module
    from spheroseg.tracking.locate import Located
    from spheroseg.tracking.segment import add_checks

    located = Located(apex=phantom.apex, base=phantom.base, normal=np.array([0.0, 0.0, 1.0]), confidence=0.2,
                      reason="stub reason")
    monkeypatch.setattr(session_module, "locate", lambda volume: located)
    response, payload = request(server, "POST", "/api/find", body={"frame": 0})
    assert response.status == 200, payload
    found = json.loads(payload)
    # the API's words for it: segment's checks of a result from located points
    volume = server.session.frames[0]
    api = spheroseg.segment(volume, phantom.apex, phantom.base, check=False)
    add_checks(api, volume, {"method": "located", "apex": phantom.apex.tolist(), "base": phantom.base.tolist(),
                             "located": located.as_dict()}, located)
    assert api.quality["poor"] and found["poor"]
    assert found["warnings"] == [w for w in api.quality["warnings"] if "low confidence" in w]
    event = wait_for(server)
    assert event["poor"] and event["warnings"] == api.quality["warnings"]
    # moved by the user: given points now, which a location without confidence does not check
    moved = {"frame": 0, "apex": (phantom.apex + [0.0, 0.0, 1.0]).tolist(), "base": phantom.base.tolist()}
    response, _ = request(server, "POST", "/api/points", body=moved)
    assert response.status == 200
    end = time.monotonic() + 60
    while (event := wait_for(server))["points"]["apex"] != moved["apex"]:
        assert time.monotonic() < end
        time.sleep(0.05)
    # not poor: only said, on the banner, that a location without confidence could not check them
    assert not event["poor"]
    assert [w for w in event["warnings"] if "low confidence" in w] == [
        w for w in event["warnings"] if w.startswith("the clicked points could not be checked")]


def test_the_lv_mass_carries_its_caveats(phantom, tmp_path):
    """The epicardium's answer says the LV mass rests on an assumed spacing
    when the user gave it, and that the myocardium is validated on phantoms
    only (round-4 defect 9)."""
    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    write_markups(tmp_path / "points.mrk.json", apex=phantom.apex, base=phantom.base)
    for spacing in (None, (2.0, 2.0, 2.0)):
        server = open_viewer(path, save_root=tmp_path, points=tmp_path / "points.mrk.json", spacing=spacing)
        server.serve_in_thread()
        try:
            wait_for(server)
            response, payload = request(server, "GET", "/api/epicardium?frame=0")
            assert response.status == 200, payload
            caveats = json.loads(payload)["caveats"]
            assert any("phantoms only" in c for c in caveats)
            assert any("spacing assumed" in c for c in caveats) == (spacing is not None)
            assert json.loads(request(server, "GET", "/api/study")[1])["spacing_assumed"] == (spacing is not None)
        finally:
            server.close()


def test_the_standard_views_go_through_the_long_axis(phantom, tmp_path):
    """Stretch of issue 52: the 4C plane of a phantom's segmentation contains
    the phantom's true apex and base within a voxel; the 2C and 3C planes
    contain the axis too, the short-axis planes are perpendicular to it;
    pixels map to the world and back; the contour lies on the plane's image."""
    from spheroseg.apps.viewer.views import View

    path = tmp_path / "study.mha"
    save_volume(path, phantom.volume)
    write_markups(tmp_path / "points.mrk.json", apex=phantom.apex, base=phantom.base)
    server = open_viewer(path, save_root=tmp_path, points=tmp_path / "points.mrk.json")
    server.serve_in_thread()
    try:
        wait_for(server)
        response, payload = request(server, "GET", "/api/views?frame=0")
        assert response.status == 200, payload
        views = json.loads(payload)["views"]
        assert [v["name"] for v in views] == ["4C", "2C", "3C", "SAX basal", "SAX mid", "SAX apical"]
        voxel = float(min(phantom.volume.spacing))
        axis = (phantom.apex - phantom.base) / np.linalg.norm(phantom.apex - phantom.base)
        for data in views:
            view = View(data["name"], np.array(data["centre"]), np.array(data["u"]), np.array(data["v"]),
                        data["pixel_mm"], data["rows"], data["cols"])
            if data["name"] in ("4C", "2C", "3C"):
                for point in (phantom.apex, phantom.base):
                    assert abs((point - view.centre) @ view.normal) < voxel, (data["name"], point)
            else:
                assert abs(abs(view.normal @ axis) - 1) < 0.01
            pixel = np.array([12.5, 100.25])
            np.testing.assert_allclose(view.to_pixel(view.to_world(*pixel)), pixel, atol=1e-9)
            image = np.frombuffer(base64.b64decode(data["image"]), np.uint8).reshape(data["rows"], data["cols"])
            segments = np.reshape(data["contour"], (-1, 4))
            assert len(segments) > 20 and image.max() > 100
            # the cavity is dark inside the contour: its mid-points sit on the wall's edge, the centre is blood
            inside = image[data["rows"] // 2 - 3:data["rows"] // 2 + 4, data["cols"] // 2 - 3:data["cols"] // 2 + 4]
            assert inside.mean() < np.percentile(image[image > 0], 60), data["name"]
    finally:
        server.close()
