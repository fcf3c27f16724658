"""Latency and drops of ``spheroseg live`` on loopback.

A :class:`spheroseg.live.replay.Replay` streams a sequence at a frame rate,
looping, a :class:`spheroseg.live.server.LiveServer` tracks it and a
:class:`spheroseg.live.client.ResultClient` reads the results, all in this
process.  Per frame tracked: ``latency_ms`` as ``LVMetrics`` gives it (from
the IMAGE's last byte read to its results ready to send) and the end to
end time (from the frame's send time, its timestamp, to its ``LVMetrics``
read by the client); the drop rate is ``dropped / received``.  The first
``--warm`` seconds (the first frame's full segmentation) are left out.

    PYTHONPATH=src python benchmarks/live.py --sequence phantom --fps 30 60 --seconds 20
    PYTHONPATH=src python benchmarks/live.py --sequence devset --fps 30 60 --seconds 20
    PYTHONPATH=src python benchmarks/live.py --fps 30 --seconds 180 --restarts 2   # memory, reconnection

``rss_mb``: the process's resident memory after the warm-up and at each
restart and the end.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from spheroseg.warmup import load_kernels

DEVSET = Path(__file__).resolve().parents[2] / "shared" / "data" / "devset" / "dev_sequence"


def sequence(name: str):
    """Volumes, apex and base of the sequence streamed."""
    if name == "phantom":
        from spheroseg.synthetic.phantom import make_sequence

        seq = make_sequence(seed=0, n_frames=10, spacing=1.25)  # the demo's
        return seq.volumes, seq.frames[0].apex, seq.frames[0].base
    from spheroseg.io import load

    case = json.loads((DEVSET / "case.json").read_text())
    volumes = [load(DEVSET / f"frame_{k:02d}.mha", no_data_value=None) for k in range(case["n_frames"])]
    return volumes, np.array(case["clicks"]["apex_mm"]), np.array(case["clicks"]["base_mm"])


def rss_mb() -> float:
    """This process's resident memory (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run(volumes, apex, base, *, fps: float, seconds: float, warm: float, restarts: int = 0) -> dict:
    """Stream for ``seconds`` after ``warm``; with ``restarts``, the source
    is closed and started again on its port that many times, evenly spaced
    (``resume_s``: from the new source's first frame sent to its metrics
    read)."""
    from spheroseg.live.client import ResultClient
    from spheroseg.live.replay import Replay
    from spheroseg.live.server import LiveServer

    replay = Replay(volumes, fps=fps)
    port = replay.address[1]
    live = LiveServer(replay.address, serve=("127.0.0.1", 0), apex=apex, base=base, status_seconds=1e9,
                      backoff=(0.05, 0.5)).start()
    client = ResultClient(live.address)
    resume = []
    try:
        while replay.clients < 1:
            time.sleep(0.01)
        replay.start()
        time.sleep(warm)
        before = live.last_metrics or {"received": 0, "dropped": 0, "tracked": 0}
        count = len(client.metrics)
        rss = [rss_mb()]
        for k in range(restarts + 1):
            time.sleep(seconds / (restarts + 1))
            rss.append(rss_mb())
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
        after = dict(live.last_metrics)
        metrics = [m for m in list(client.metrics)[count:]]
    finally:
        client.close()
        live.close()
        replay.close()
    latency = np.array([m["latency_ms"] for m in metrics])
    end_to_end = np.array([1000.0 * (m["arrived"] - m["timestamp"]) for m in metrics])
    received = after["received"] - before["received"]
    dropped = after["dropped"] - before["dropped"]
    period = 1000.0 / fps
    return {"fps": fps, "frames_received": received, "frames_tracked": after["tracked"] - before["tracked"],
            "dropped": dropped, "drop_rate": dropped / max(received, 1), "period_ms": period,
            "latency_ms": {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99))},
            "end_to_end_ms": {"median": float(np.median(end_to_end)), "p99": float(np.percentile(end_to_end, 99))},
            "stages_ms_median": {k: float(np.median([m["stages_ms"][k] for m in metrics])) for k in metrics[0]["stages_ms"]},
            "rss_mb": rss, "resume_s": resume,
            "edv_ml": after.get("edv_ml"), "esv_ml": after.get("esv_ml"), "ef": after.get("ef"),
            "cycle": after.get("cycle"), "heart_rate_bpm": after.get("heart_rate_bpm")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", choices=("phantom", "devset"), default="phantom")
    parser.add_argument("--fps", type=float, nargs="+", default=[30.0, 60.0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--warm", type=float, default=3.0)
    parser.add_argument("--restarts", type=int, default=0, help="source closed and started again, evenly spaced")
    args = parser.parse_args()
    load_kernels()
    volumes, apex, base = sequence(args.sequence)
    nz, ny, nx = volumes[0].shape
    print(f"# {args.sequence}: {len(volumes)} frames of {nx} x {ny} x {nz} voxels, {args.seconds:g} s each rate")
    for fps in args.fps:
        row = run(volumes, apex, base, fps=fps, seconds=args.seconds, warm=args.warm, restarts=args.restarts)
        print(json.dumps(row))


if __name__ == "__main__":
    main()
