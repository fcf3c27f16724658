"""Progress bars: on a terminal or with --progress, never with --quiet; the
phantom sequence reports each frame made, unchanged by being watched."""

import io
from argparse import Namespace

import numpy as np

from spheroseg.apps.cli import progress_callback, shows_progress
from spheroseg.synthetic.phantom import make_sequence


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_bars_show_on_a_terminal_or_when_asked_and_never_when_quiet(monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert not shows_progress(Namespace(quiet=False, progress=False))  # a pipe, a log file, a test
    assert shows_progress(Namespace(quiet=False, progress=True))
    assert not shows_progress(Namespace(quiet=True, progress=True))
    monkeypatch.setattr("sys.stderr", Terminal())
    assert shows_progress(Namespace(quiet=False, progress=False))
    assert not shows_progress(Namespace(quiet=True, progress=False))


def test_a_bar_is_drawn_on_stderr_only_when_shown(monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    with progress_callback(Namespace(quiet=False, progress=False), total=3, desc="quiet") as progress:
        assert progress is None
    assert "quiet" not in __import__("sys").stderr.getvalue()
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    with progress_callback(Namespace(quiet=False, progress=True), total=3, desc="making") as progress:
        for done in (1, 2, 3):
            progress(done, 3)
    assert "making" in stderr.getvalue() and "/3" in stderr.getvalue()


def test_the_sequence_reports_each_frame_and_is_the_same_watched():
    calls = []
    watched = make_sequence(n_frames=3, seed=4, spacing=4.0, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    plain = make_sequence(n_frames=3, seed=4, spacing=4.0)
    for a, b in zip(watched.volumes, plain.volumes):
        np.testing.assert_array_equal(a.array, b.array)
