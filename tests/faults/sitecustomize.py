"""Faults for the batch tests, injected from outside the package: on
``PYTHONPATH``, Python imports this in every process it starts (the command
and each spawned worker).  ``SPHEROSEG_TEST_FAULTS="NAME=exit,NAME2=sleep:S"``
makes a worker die abruptly (SIGKILL, as a crash) when it reads the image
file ``NAME``, or spend ``S`` seconds in Python (a timeout interrupts it)
before reading ``NAME2``; ``*`` is every image."""

import os

FAULTS = os.environ.get("SPHEROSEG_TEST_FAULTS")

if FAULTS:
    import signal
    import time
    from pathlib import Path

    import spheroseg.io

    actions = dict(item.split("=", 1) for item in FAULTS.split(","))

    def faulty(read):
        def reader(path, **kwargs):
            action = actions.get(Path(str(path)).name, actions.get("*", ""))
            if action == "exit":
                os.kill(os.getpid(), signal.SIGKILL)
            if action.startswith("sleep:"):  # in small steps, as a long computation
                end = time.monotonic() + float(action.split(":", 1)[1])
                while time.monotonic() < end:
                    time.sleep(0.02)
            return read(path, **kwargs)

        return reader

    # a study's worker reads its image with these (imported from spheroseg.io when it runs)
    spheroseg.io.load = faulty(spheroseg.io.load)
    spheroseg.io.load_sequence = faulty(spheroseg.io.load_sequence)
