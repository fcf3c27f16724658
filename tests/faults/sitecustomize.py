"""Faults for the batch tests, injected from outside the package: on
``PYTHONPATH``, Python imports this in every process it starts (the command
and each spawned worker).  ``SPHEROSEG_TEST_FAULTS="ID=exit,ID2=sleep:S"``
makes a worker die abruptly (SIGKILL, as a crash) on study ``ID``, or spend
``S`` seconds in Python (a timeout interrupts it) before study ``ID2``."""

import os

FAULTS = os.environ.get("SPHEROSEG_TEST_FAULTS")

if FAULTS:
    import signal
    import time

    import spheroseg.batch as batch

    actions = dict(item.split("=", 1) for item in FAULTS.split(","))
    points = batch._points

    def faulty_points(study):
        action = actions.get(study.id, "")
        if action == "exit":
            os.kill(os.getpid(), signal.SIGKILL)
        if action.startswith("sleep:"):  # in small steps, as a long computation
            end = time.monotonic() + float(action.split(":", 1)[1])
            while time.monotonic() < end:
                time.sleep(0.02)
        return points(study)

    batch._points = faulty_points  # run_study reads its inputs' points first
