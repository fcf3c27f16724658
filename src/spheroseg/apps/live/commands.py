"""The ``spheroseg live`` and ``spheroseg replay`` subcommands.

Their parsers are built with nothing but argparse (``spheroseg --help``
stays light); the tracking is imported when a command runs.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading

__all__ = ["add_live_parsers", "run"]

#: OpenIGTLink's port by convention (PlusServer's), where ``replay`` serves
SOURCE_PORT = 18944
#: where ``live`` serves its results by default (beside the source's)
SERVE_PORT = 18945


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def add_live_parsers(sub, *, model_options) -> None:
    """Add ``live`` and ``replay`` to the ``spheroseg`` subparsers ``sub``;
    ``model_options(parser)`` adds the model's options, as for ``track``."""
    from ...descent.options import SMOOTHNESS_REFERENCES, SegmentOptions

    live = sub.add_parser(
        "live", help="track the left ventricle in a 3D IMAGE stream over OpenIGTLink and serve the results",
        description="Connect to an OpenIGTLink server streaming 3D IMAGE messages (a PlusServer, spheroseg replay), "
                    "track the left ventricle frame by frame and serve to every client of --serve (3D Slicer's "
                    "OpenIGTLinkIF): POLYDATA LVEndo (and LVEpi), IMAGE LVLabel, TRANSFORM LVToImage and STRING "
                    "LVMetrics (JSON: volume, EDV, ESV, EF over the last cycle, dropped frames, latency). Frames "
                    "arriving faster than they are tracked are dropped, the newest kept. Ctrl-C stops it.")
    live.add_argument("--source", default=f"127.0.0.1:{SOURCE_PORT}", metavar="HOST:PORT",
                      help=f"the image server (default 127.0.0.1:{SOURCE_PORT})")
    live.add_argument("--serve", default=str(SERVE_PORT), metavar="[HOST:]PORT",
                      help=f"where result clients connect (default {SERVE_PORT} on 127.0.0.1; 0.0.0.0:PORT for "
                           "other machines)")
    live.add_argument("--device", metavar="NAME", help="track only the images of this device name")
    live.add_argument("--apex", nargs=3, type=float, metavar=("X", "Y", "Z"),
                      help="apex point, world mm (LPS); with no points the ventricle is located in the first frames")
    live.add_argument("--base", nargs=3, type=float, metavar=("X", "Y", "Z"), help="centre of the mitral plane")
    live.add_argument("--annulus", nargs=3, type=float, action="append", default=[], metavar=("X", "Y", "Z"),
                      help="a point of the mitral annulus (repeatable, 3 or more)")
    live.add_argument("--points", metavar="MRK_JSON", help="3D Slicer markups with points labelled apex, base...")
    live.add_argument("--landmark", nargs=3, type=float, action="append", default=[], metavar=("X", "Y", "Z"),
                      help="a point of the wall the surface is drawn to (repeatable)")
    live.add_argument("--coordinates", choices=("ras", "lps"), default="ras",
                      help="world frame of the results sent (default ras, 3D Slicer's); images are read in the "
                           "frame their messages state")
    live.add_argument("--myocardium", action="store_true",
                      help="also segment the epicardium: POLYDATA LVEpi, the 17-segment number of each point, "
                           "label 2 in LVLabel, the LV mass in LVMetrics")
    live.add_argument("--rv-insertion", nargs=3, type=float, metavar=("X", "Y", "Z"),
                      help="with --myocardium: the anterior RV insertion, world mm, where segment 1 starts")
    live.add_argument("--no-label", action="store_true", help="do not send the labelmap LVLabel")
    live.add_argument("--record", metavar="DIR",
                      help="also write each tracked frame to DIR (metrics JSON, mask, mesh; atomically); "
                           "nothing is written without it")
    live.add_argument("--iterations-per-frame", type=int, default=20)
    live.add_argument("--stall", type=_seconds, default=5.0, metavar="S",
                      help="reconnect to a source silent this long (default 5 s)")
    live.add_argument("--duration", type=_seconds, metavar="S", help="stop after S seconds")
    live.add_argument("--quiet", action="store_true", help="only warnings on stderr")
    model_options(live)
    live.add_argument("--step", type=float, default=SegmentOptions.step, help="largest surface motion per iteration")
    live.add_argument("--max-iterations", type=int, default=SegmentOptions.max_iterations,
                      help="per coarse-to-fine level")
    live.add_argument("--smoothness", type=float, default=SegmentOptions.smoothness)
    live.add_argument("--smoothness-reference", default=SegmentOptions.smoothness_reference,
                      choices=SMOOTHNESS_REFERENCES)
    live.add_argument("--threads", type=int, metavar="N")

    replay = sub.add_parser(
        "replay", help="stream a 3D+t sequence as OpenIGTLink IMAGE messages, PLUS-like, looping",
        description="Serve a 3D+t sequence (or, with no file, the demo's synthetic one) as OpenIGTLink IMAGE "
                    "messages at a set frame rate, looping, stamped with each frame's time: a source for "
                    "spheroseg live without a scanner. Ctrl-C stops it.")
    replay.add_argument("sequence", nargs="?",
                        help="4D image, .seq.nrrd, folder or glob of 3D frames (default: the demo's synthetic "
                             "sequence)")
    replay.add_argument("--serve", default=str(SOURCE_PORT), metavar="[HOST:]PORT",
                        help=f"where clients connect (default {SOURCE_PORT} on 127.0.0.1)")
    replay.add_argument("--fps", type=float, default=30.0, help="frames a second (default 30)")
    replay.add_argument("--device", default="Image_Reference", help="the images' device name (PLUS's default)")
    replay.add_argument("--coordinates", choices=("ras", "lps"), default="ras",
                        help="the frame of the image matrix sent (default ras)")
    replay.add_argument("--once", action="store_true", help="stop after the last frame instead of looping")
    replay.add_argument("--spacing", nargs=3, type=float, metavar=("SX", "SY", "SZ"),
                        help="voxel spacing in mm (required for .npy)")
    replay.add_argument("--duration", type=_seconds, metavar="S", help="stop after S seconds")
    replay.add_argument("--quiet", action="store_true")


def _console(args) -> None:
    logger = logging.getLogger("spheroseg.apps.live")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("spheroseg: %(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.WARNING if args.quiet else logging.INFO)


def _wait(duration: float | None, done=lambda: False) -> None:
    """Until ``duration`` has passed, ``done()`` holds, or Ctrl-C."""
    stop = threading.Event()
    waited = 0.0
    try:
        while (duration is None or waited < duration) and not done():
            stop.wait(0.1)
            waited += 0.1
    except KeyboardInterrupt:
        print("spheroseg: stopped", file=sys.stderr)


def run(args, *, points: dict | None = None, options: dict | None = None, prepare=None, demo=None) -> int:
    """Run ``spheroseg live`` (``points``: apex, base, landmarks, annulus;
    ``options``: the segmentation's, both checked; ``prepare()`` once the
    arguments are, before listening: the kernels loaded) or ``spheroseg
    replay`` (``demo()``: the volumes to stream without a file).  A bad
    input raises ValueError, one line."""
    _console(args)
    if args.command == "live":
        return _live(args, points or {}, options or {}, prepare)
    return _replay(args, demo)


def _listening(make, address):
    try:
        return make()
    except OSError as exc:
        raise ValueError(f"cannot listen on {address[0]}:{address[1]}: {exc.strerror or exc}") from None


def _live(args, points: dict, options: dict, prepare) -> int:
    import numpy as np

    from .fanout import parse_address
    from .server import LiveServer

    source, serve = parse_address(args.source), parse_address(args.serve)
    if prepare is not None:
        prepare()
    from .crc import crc64

    crc64(b"\0")  # the compiled kernel loaded before the first frame waits for it
    server = _listening(lambda: LiveServer(
        source, serve=serve, device=args.device, coordinates=args.coordinates, label=not args.no_label,
        record=args.record, no_data_value=args.no_data, stall_seconds=args.stall,
        iterations_per_frame=args.iterations_per_frame, myocardium=args.myocardium,
        rv_insertion=None if args.rv_insertion is None else np.asarray(args.rv_insertion), **points, **options),
        serve)
    print(f"spheroseg: tracking the images of {source[0]}:{source[1]}; results on {server.address[0]}:"
          f"{server.address[1]} (Ctrl-C stops)", file=sys.stderr, flush=True)
    server.start()
    try:
        _wait(args.duration)
    finally:
        server.close()
    if not args.quiet:
        print(f"spheroseg: {server.status()}", file=sys.stderr)
    return 0


def _replay(args, demo) -> int:
    from .fanout import parse_address
    from .messages import check_device
    from .replay import Replay

    if not (args.fps > 0 and args.fps < 1000):
        raise ValueError(f"--fps must be a number of frames a second from 0 to 1000, got {args.fps}")
    serve = parse_address(args.serve)
    check_device(args.device)
    if args.sequence is None:
        if demo is None:
            raise ValueError("give a sequence to replay")
        volumes, what = demo(), "the demo's synthetic sequence"
    else:
        from ...io import load_sequence

        volumes = load_sequence(args.sequence, spacing=args.spacing, no_data_value=None)
        what = args.sequence
    replay = _listening(lambda: Replay(volumes, host=serve[0], port=serve[1], fps=args.fps, loop=not args.once,
                                       device=args.device, coordinates=args.coordinates), serve)
    nz, ny, nx = volumes[0].shape
    if not args.quiet:
        print(f"spheroseg: streaming {what} ({len(volumes)} frames of {nx} x {ny} x {nz} voxels) at {args.fps:g} "
              f"frames a second on {replay.address[0]}:{replay.address[1]} as {args.device!r} (Ctrl-C stops)",
              file=sys.stderr, flush=True)
    replay.start()
    try:
        _wait(args.duration, done=lambda: args.once and replay.wait(0))
    finally:
        replay.close()
    return 0
