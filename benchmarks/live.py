"""Latency and drops of ``spheroseg live`` on loopback.

A :class:`spheroseg.apps.live.replay.Replay` streams a sequence at a frame rate,
looping, ``spheroseg live`` tracks it in its own process and a
:class:`spheroseg.apps.live.client.ResultClient` reads the results.  Per frame tracked: ``latency_ms`` as ``LVMetrics`` gives it (from
the IMAGE's last byte read to its results ready to send) and the end to
end time (from the frame's send time, its timestamp, to its ``LVMetrics``
read by the client); the drop rate is ``dropped / received``.  The first
``--warm`` seconds (the first frame's full segmentation) are left out.

    PYTHONPATH=src python benchmarks/live.py --sequence phantom --fps 30 60 --seconds 20
    PYTHONPATH=src python benchmarks/live.py --sequence devset --fps 30 60 --seconds 20
    PYTHONPATH=src python benchmarks/live.py --fps 30 --seconds 180 --restarts 2   # memory, reconnection
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from spheroseg.apps.warmup import load_kernels

DEVSET = Path(__file__).resolve().parents[2] / "shared" / "data" / "devset" / "dev_sequence"


def sequence(name: str, frames: int):
    """Volumes, apex and base of the sequence streamed: the phantom's cycle
    of ``frames`` frames (1.25 mm voxels, the annulus descending 10 mm; 30
    frames at 30 a second: 60 beats a minute), or the development set's
    12 frames."""
    if name == "phantom":
        from spheroseg.synthetic.phantom import make_sequence

        seq = make_sequence(seed=0, n_frames=frames, spacing=1.25, base_descent=10.0)
        return seq.volumes, seq.frames[0].apex, seq.frames[0].base
    from spheroseg.io import load

    case = json.loads((DEVSET / "case.json").read_text())
    volumes = [load(DEVSET / f"frame_{k:02d}.mha", no_data_value=None) for k in range(case["n_frames"])]
    return volumes, np.array(case["clicks"]["apex_mm"]), np.array(case["clicks"]["base_mm"])


def rss_mb(pid: int) -> float:
    """A process's resident memory (MB)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as probe:
        return probe.getsockname()[1]


def run(volumes, apex, base, *, fps: float, seconds: float, warm: float, restarts: int = 0) -> dict:
    """Stream for ``seconds`` after ``warm`` to ``spheroseg live`` in its
    own process (as beside a scanner); with ``restarts``, the source is
    closed and started again on its port that many times, evenly spaced
    (``resume_s``: from the new source's first frame sent to its metrics
    read).  ``rss_mb``: the live process's resident memory after the
    warm-up, at each restart and at the end."""
    from spheroseg.apps.live.client import ResultClient
    from spheroseg.apps.live.replay import Replay

    replay = Replay(volumes, fps=fps)
    port, serve = replay.address[1], free_port()
    command = [sys.executable, "-m", "spheroseg", "live", "--source", f"127.0.0.1:{port}", "--serve", str(serve),
               "--apex", *map(str, apex), "--base", *map(str, base), "--quiet",
               "--duration", str(warm + seconds + 30.0 * (restarts + 1))]
    live = subprocess.Popen(command)
    client = None
    resume = []
    try:
        deadline = time.monotonic() + 120
        while client is None:
            try:
                client = ResultClient(("127.0.0.1", serve))
            except OSError:
                if time.monotonic() > deadline or live.poll() is not None:
                    raise RuntimeError("spheroseg live did not start") from None
                time.sleep(0.2)
        while replay.clients < 1:
            time.sleep(0.01)
        replay.start()
        time.sleep(warm)
        count = len(client.metrics)
        rss = [rss_mb(live.pid)]
        for k in range(restarts + 1):
            time.sleep(seconds / (restarts + 1))
            rss.append(rss_mb(live.pid))
            if k == restarts:
                break
            replay.close()
            time.sleep(0.5)
            replay = Replay(volumes, port=port, fps=fps)
            while replay.clients < 1:
                time.sleep(0.005)
            first = time.time()
            replay.start()
            seen = len(client.metrics)
            client.wait_for(lambda c: len(c.metrics) > seen and c.metrics[-1]["timestamp"] >= first - 1e-3, 30)
            resume.append(client.metrics[-1]["arrived"] - first)
        metrics = list(client.metrics)[count:]
    finally:
        if client is not None:
            client.close()
        replay.close()
        live.terminate()
        live.wait(10)
    before, after = metrics[0], metrics[-1]
    latency = np.array([m["latency_ms"] for m in metrics])
    end_to_end = np.array([1000.0 * (m["arrived"] - m["timestamp"]) for m in metrics])
    received = after["received"] - before["received"]
    dropped = after["dropped"] - before["dropped"]
    return {"fps": fps, "frames_received": received, "frames_tracked": after["tracked"] - before["tracked"],
            "dropped": dropped, "drop_rate": dropped / max(received, 1), "period_ms": 1000.0 / fps,
            "latency_ms": {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99))},
            "end_to_end_ms": {"median": float(np.median(end_to_end)), "p99": float(np.percentile(end_to_end, 99))},
            "stages_ms_median": {k: float(np.median([m["stages_ms"][k] for m in metrics]))
                                 for k in metrics[0]["stages_ms"]},
            "rss_mb": [round(r, 1) for r in rss], "resume_s": resume,
            "edv_ml": after.get("edv_ml"), "esv_ml": after.get("esv_ml"), "ef": after.get("ef"),
            "cycle": after.get("cycle"), "heart_rate_bpm": after.get("heart_rate_bpm")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", choices=("phantom", "devset"), default="phantom")
    parser.add_argument("--fps", type=float, nargs="+", default=[30.0, 60.0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--frames", type=int, default=30, help="frames of the phantom's cycle")
    parser.add_argument("--warm", type=float, default=3.0)
    parser.add_argument("--restarts", type=int, default=0, help="source closed and started again, evenly spaced")
    args = parser.parse_args()
    load_kernels()  # (the live process loads them from numba's cache before it listens)
    volumes, apex, base = sequence(args.sequence, args.frames)
    nz, ny, nx = volumes[0].shape
    print(f"# {args.sequence}: {len(volumes)} frames of {nx} x {ny} x {nz} voxels, {args.seconds:g} s each rate")
    for fps in args.fps:
        row = run(volumes, apex, base, fps=fps, seconds=args.seconds, warm=args.warm, restarts=args.restarts)
        print(json.dumps(row))


if __name__ == "__main__":
    main()
