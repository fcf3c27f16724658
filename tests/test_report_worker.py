"""The report drawn in a second process: the same picture as drawn here,
errors raised where they are waited for, and a dead process replaced by
drawing here."""

import multiprocessing
import os
import signal
import subprocess
import sys
import time

import matplotlib.image
import numpy as np
import pytest

import spheroseg
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.io.report import report_parts, save_parts
from spheroseg.apps.report_worker import ReportWorker


@pytest.fixture(scope="module")
def parts():
    ph = make_phantom(seed=2, spacing=2.0)
    result = spheroseg.segment(ph.volume, ph.apex, ph.base)
    return report_parts(ph.volume, result.surface, title="phantom", volumes_ml=[130.0, 90.0, 60.0], ed_frame=0,
                        es_frame=2)


def workers() -> list:
    return [p for p in multiprocessing.active_children() if p.name == "spheroseg-report"]


def test_worker_draws_what_is_drawn_here(parts, tmp_path):
    save_parts(tmp_path / "here.png", parts)
    with ReportWorker(parallel=True) as worker:
        assert worker.parallel and len(workers()) == 1
        worker.save(tmp_path / "there.png", parts)()
    np.testing.assert_array_equal(matplotlib.image.imread(tmp_path / "there.png"),
                                  matplotlib.image.imread(tmp_path / "here.png"))
    assert workers() == []


def test_worker_raises_what_drawing_raised_and_goes_on(parts, tmp_path):
    with ReportWorker(parallel=True) as worker:
        wait = worker.save(tmp_path / "missing" / "report.png", parts)
        with pytest.raises(FileNotFoundError):
            wait()
        worker.save(tmp_path / "report.png", parts)()
    assert (tmp_path / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "missing").exists()


def test_a_dead_worker_is_replaced_by_drawing_here(parts, tmp_path):
    with ReportWorker(parallel=True) as worker:
        (process,) = workers()
        process.kill()
        process.join()
        worker.save(tmp_path / "report.png", parts)()
        assert not worker.parallel
    assert (tmp_path / "report.png").is_file()


def test_an_error_stops_the_worker_at_once():
    with pytest.raises(KeyError):
        with ReportWorker(parallel=True):
            (process,) = workers()
            raise KeyError("the command failed")
    assert workers() == [] and process.exitcode == -signal.SIGTERM  # terminated, not asked to finish


def test_the_end_of_a_command_lets_the_worker_finish():
    with ReportWorker(parallel=True):
        (process,) = workers()
    assert process.exitcode == 0


def test_without_parallel_the_report_is_drawn_here(parts, tmp_path):
    with ReportWorker(parallel=False) as worker:
        assert not worker.parallel and workers() == []
        wait = worker.save(tmp_path / "report.png", parts)
        assert not (tmp_path / "report.png").exists()  # drawn when waited for, after the other files
        wait()
    assert (tmp_path / "report.png").is_file()


def test_a_forked_worker_does_not_repeat_what_was_printed():
    # text still buffered when the process starts is written once, not again by it
    code = ("import sys\nfrom spheroseg.apps.report_worker import ReportWorker\nprint('before', end='')\n"
            "with ReportWorker(parallel=True):\n    pass\nprint(' after')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "before after\n"


def test_the_worker_leaves_ctrl_c_to_the_command():
    # Ctrl-C reaches the whole process group: the worker must neither die
    # of it nor print a traceback; the command stops it (as after any error)
    with ReportWorker(parallel=True):
        (process,) = workers()
        time.sleep(1.0)  # into its loop
        os.kill(process.pid, signal.SIGINT)
        time.sleep(0.5)
        assert process.is_alive()
    assert process.exitcode == 0
