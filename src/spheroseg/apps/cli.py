"""The command line: ``spheroseg segment | track | batch | scan-convert | view | demo | live | replay``.

Every failure is one line on stderr and a non-zero exit status.  Outputs
are written to temporary files and renamed; existing outputs are kept
unless ``--force``; an input is never overwritten.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from .._version import __version__
from ..descent.options import MODES, SMOOTHNESS_REFERENCES, SYSTEMS, SegmentOptions

EXIT_ERROR = 2
#: the run completed and wrote its outputs, but a result is poor (its quality
#: report has warnings): a pipeline stops here unless --allow-poor
EXIT_POOR = 3
#: the exit statuses of segment and track, for their --help
_EXIT_HELP = ("Exit status: 0 done; 2 an error, one line on stderr (nothing written); 3 done, outputs written, but the "
              "result is poor (a warning line on stderr, quality in results.json; --allow-poor makes it 0); "
              "130 interrupted (nothing written).")
#: thread counts of the linear algebra libraries, set to 1 for batch workers unless given
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


class CliError(Exception):
    """A user-facing error: printed as one line."""


# -- arguments ---------------------------------------------------------------


def _point(text):
    return np.asarray(text, dtype=float)


def _no_data(text: str):
    if text.lower() in ("auto", "none"):
        return None if text.lower() == "none" else "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto, none or a number, got {text!r}") from None


class _Once(argparse.Action):
    """An option given at most once (a second ``--apex`` would silently win)."""

    def __call__(self, parser, namespace, values, option_string=None):
        if getattr(namespace, self.dest, None) is not None:
            parser.error(f"{option_string} given twice; give it once")
        setattr(namespace, self.dest, values)


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--apex", nargs=3, type=float, action=_Once, metavar=("X", "Y", "Z"),
                   help="apex point, world mm (LPS); with no points the ventricle is located")
    p.add_argument("--base", nargs=3, type=float, action=_Once, metavar=("X", "Y", "Z"),
                   help="centre of the mitral plane, world mm")
    p.add_argument("--annulus", nargs=3, type=float, action="append", default=[], metavar=("X", "Y", "Z"),
                   help="a point of the mitral annulus, world mm (repeatable, 3 or more): the cavity is closed at "
                        "their plane, whose normal is the long axis; --base may then be omitted")
    p.add_argument("--points", metavar="MRK_JSON",
                   help="3D Slicer markups with points labelled apex, base, annulus..., landmark...")
    p.add_argument("--landmark", nargs=3, type=float, action="append", default=[], metavar=("X", "Y", "Z"),
                   help="a point of the wall the surface is drawn to (repeatable); quality in results.json "
                        "gives how far the surface ends from each, more than 2 mm is a warning")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs in DIR")
    p.add_argument("--spacing", nargs=3, type=float, metavar=("SX", "SY", "SZ"),
                   help="voxel spacing in mm (required for .npy, overrides the file's)")
    _add_options(p)


def _add_model_options(p: argparse.ArgumentParser, *, no_data_help: str) -> None:
    """The model's options, defaults from :class:`SegmentOptions` (segment,
    track, batch, view)."""
    p.add_argument("--system", default=SegmentOptions.system, choices=SYSTEMS)
    p.add_argument("--patches", nargs=2, type=int, default=SegmentOptions.patches, metavar=("N_THETA", "N_MU"))
    p.add_argument("--mode", default=SegmentOptions.mode, choices=MODES, help="data term")
    p.add_argument("--no-data", default="auto", type=_no_data, metavar="auto|none|VALUE", help=no_data_help)


def _add_options(p: argparse.ArgumentParser) -> None:
    """The segmentation and output options (segment, track, batch)."""
    _add_model_options(p, no_data_help="voxels without data: 'auto' (default) the zero padding around an echo "
                                       "sector (a beam-space file's NoDataValue key), 'none', or a voxel value")
    p.add_argument("--step", type=float, default=SegmentOptions.step, help="largest surface motion per iteration, mm")
    p.add_argument("--max-iterations", type=int, default=SegmentOptions.max_iterations,
                   help="per coarse-to-fine level")
    p.add_argument("--smoothness", type=float, default=SegmentOptions.smoothness,
                   help="thin-plate prior weight (0: the paper's method)")
    p.add_argument("--smoothness-reference", default=SegmentOptions.smoothness_reference,
                   choices=SMOOTHNESS_REFERENCES,
                   help="the shape the finest patches are smoothed towards: the clicked half-ellipsoid ('start'), "
                        "or it widened or narrowed to the volume the coarse levels found ('fitted': an "
                        "end-systole segmented on its own comes out less large)")
    p.add_argument("--threads", type=int, metavar="N",
                   help="threads of the compiled kernels (default: the cores no other process is using; a batch of "
                        "several workers: 1 each); the results do not depend on it")
    p.add_argument("--mask-format", metavar="EXT", help="mask file type, e.g. .nii.gz (default: the input's)")
    p.add_argument("--stl", action="store_true", help="also write the mesh as STL")
    p.add_argument("--no-report", action="store_true", help="skip the PNG report")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stdout")
    p.add_argument("--progress", action="store_true",
                   help="progress bars on stderr even when it is not a terminal (default: only on a terminal)")
    p.add_argument("--allow-poor", action="store_true",
                   help="exit 0 when a result is poor (its quality report has warnings); default: exit 3")
    p.add_argument("--profile", action="store_true",
                   help="print the time of every stage (import, read, padding, segment, mask, meshes, writes, "
                        "report) on stderr; they are in results.json's seconds block either way")


def _shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (e.g. 2/4), got {text!r}") from None
    if not 1 <= i <= n:
        raise argparse.ArgumentTypeError(f"expected I/N with 1 <= I <= N, got {text!r}")
    return i, n


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not value > 0 or value != value:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
        return value

    return parse


def _add_myocardium(parser, outputs: str) -> None:
    parser.add_argument("--myocardium", action="store_true", help=f"also segment the epicardium: {outputs}")
    parser.add_argument("--rv-insertion", nargs=3, type=float, action=_Once, metavar=("X", "Y", "Z"),
                        help="with --myocardium: the anterior insertion of the right ventricle, world mm, where "
                             "segment 1 starts (default: the model frame's first axis; docs/segments.png)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="spheroseg",
        description="Left-ventricle segmentation in 3D echocardiography (prolate spheroidal Hermite surfaces).",
    )
    parser.add_argument("--version", action="version", version=f"spheroseg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    seg = sub.add_parser("segment", help="segment one 3D image", description="Segment one 3D image. " + _EXIT_HELP)
    seg.add_argument("image", help="3D image (.mhd, .mha, .nii[.gz], .nrrd, .npy, DICOM folder)")
    _add_common(seg)
    _add_myocardium(seg, "the myocardium mask, LV mass, wall thickness and the 17 segments (results.json), the "
                         "epicardial mesh and the heart as CMISS volume elements")
    tr = sub.add_parser("track", help="segment every frame of a 3D+t sequence; EDV, ESV, EF",
                        description="Segment every frame of a 3D+t sequence; EDV, ESV, EF. " + _EXIT_HELP)
    tr.add_argument("sequence", help="4D image, .seq.nrrd, folder of 3D frames (ordered by the numbers in their "
                                     "names), DICOM folder, or with --glob a pattern")
    tr.add_argument("--glob", action="store_true",
                    help="SEQUENCE is a pattern ('frame_*.mha', quoted) whose matches are the frames; without it a "
                         "name is a name, *?[ included")
    _add_common(tr)
    tr.add_argument("--iterations-per-frame", type=int, default=20)
    tr.add_argument("--start-frame", type=int, default=0, metavar="K",
                    help="the frame the points are placed on (0-based; tracked forwards, then backwards from it; "
                         "recorded in results.json)")
    _add_myocardium(tr, "every frame's myocardium mask (masks/frame_TTT_myocardium*), and in results.json the LV "
                        "mass per frame, the 17 segments' volume curves, their times to minimum volume and the SDI")
    sc = sub.add_parser("scan-convert", help="resample a beam-space image or 3D+t sequence on a Cartesian grid")
    sc.add_argument("image", help="beam-space .mha/.nrrd (ITK PhasedArray3D header keys), 3D or 3D+t")
    sc.add_argument("output", help="Cartesian image to write (.mha, .mhd, .nrrd, .nii, .nii.gz)")
    sc.add_argument("--voxel-size", type=float, metavar="MM",
                    help="isotropic voxel size in mm (default: the beams' spacing at mid depth)")
    sc.add_argument("--nearest", action="store_true", help="nearest sample instead of trilinear in [r, e, a]")
    sc.add_argument("--force", action="store_true", help="overwrite an existing output")
    sc.add_argument("--quiet", action="store_true")
    batch = sub.add_parser("batch", help="segment or track every study of a manifest (JSON or CSV), resumably",
                           description="Segment or track every study of a manifest; DIR/<id>/ per study, "
                                       "DIR/summary.json and .csv (a poor column). Exit status: 0 every study ok, 1 some "
                                       "failed, 2 a bad manifest or bad options (nothing run), 3 none failed but some "
                                       "result is poor (--allow-poor makes it 0); 130 interrupted.")
    batch.add_argument("manifest", help="JSON (a list of studies) or CSV; keys id, image, apex, base, landmarks, "
                                        "points, spacing, track")
    batch.add_argument("--out", required=True, metavar="DIR", help="cohort folder (created if missing)")
    where = batch.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive(int), metavar="N", help="local worker processes (default: one per core)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="a Dask scheduler, e.g. tcp://host:8786 (spheroseg[dask])")
    batch.add_argument("--shard", type=_shard, metavar="I/N", help="run only studies I, I+N, I+2N... (1-based); "
                                                                  "summary-I-of-N.json/.csv")
    batch.add_argument("--timeout", type=_positive(float), metavar="S", help="seconds a study may take")
    batch.add_argument("--iterations-per-frame", type=int, default=20)
    _add_options(batch)
    view = sub.add_parser("view", help="open a study in a local web page: click apex and base, watch the surface, "
                                       "add landmarks, track, save",
                          description="Serve a page on 127.0.0.1 for one 3D image or 3D+t sequence; the first line "
                                      "printed is its address (with its access token). Ctrl-C stops it.")
    view.add_argument("image", help="3D image or 3D+t sequence (any format segment and track read)")
    view.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: a free one)")
    view.add_argument("--no-browser", action="store_true", help="only print the address")
    view.add_argument("--points", metavar="MRK_JSON", help="3D Slicer markups to start from (apex, base, landmarks)")
    view.add_argument("--save-root", metavar="DIR", help="the folder the page saves under (default: the current one)")
    view.add_argument("--spacing", nargs=3, type=float, metavar=("SX", "SY", "SZ"),
                      help="voxel spacing in mm (required for .npy)")
    _add_model_options(view, no_data_help="voxels without data, as for segment")
    demo = sub.add_parser("demo", help="track a built-in synthetic sequence and compare with its truth")
    demo.add_argument("--out", metavar="DIR", help="output folder (default: a new ./spheroseg-demo*)")
    demo.add_argument("--force", action="store_true")
    demo.add_argument("--quiet", action="store_true")
    demo.add_argument("--progress", action="store_true", help="progress bars on stderr even when it is not a terminal")
    from .live.commands import add_live_parsers  # argparse only: the tracking is imported when they run

    add_live_parsers(sub, model_options=lambda p: _add_model_options(
        p, no_data_help="voxels without data: 'auto' (default) the zero padding around an echo sector, 'none', or "
                        "a voxel value"))
    return parser


# -- helpers -----------------------------------------------------------------


def _say(args, *lines) -> None:
    if not getattr(args, "quiet", False):
        for line in lines:
            print(line)


def _make_folder(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise CliError(f"output folder {out} is a file")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"cannot create output folder {out}: {exc.strerror}") from None


def _output_set() -> list[str]:
    """Every entry ``segment`` or ``track`` may leave in ``--out``: what
    ``--force`` replaces as one set."""
    from ..io import MASK_SUFFIXES

    return (["results.json", "report.png", "masks", "meshes", "surface.json", "surface.exnode", "surface.exelem",
             "mesh.vtk", "mesh.ply", "mesh.stl", "mask.raw", "mask.zraw", "epicardium.vtk", "epicardium.ply",
             "epicardium.json", "heart.exnode", "heart.exelem", "myocardium.raw", "myocardium.zraw"]
            + ["mask" + s for s in MASK_SUFFIXES] + ["myocardium" + s for s in MASK_SUFFIXES])


def _inputs(args) -> list[Path]:
    """Every path a command reads: the image (a folder, a pattern's matches,
    a header's data file) and the points file."""
    from ..io import image_files

    image = getattr(args, "image", None) or args.sequence
    glob = getattr(args, "glob", False)
    paths = ([] if glob else [Path(image)]) + image_files(image, glob=glob)
    return paths + ([Path(args.points)] if getattr(args, "points", None) else [])


def _prepare_out(out: Path, names: list[str], force: bool, inputs: list[Path]) -> None:
    """Refuse an output folder the outputs ``names`` cannot go to (before any
    input is read); nothing is created."""
    from ..io.atomic import refuse_overwriting_inputs

    out = Path(os.path.abspath(out))
    if out.exists() and not out.is_dir():
        raise CliError(f"output folder {out} is a file")
    anchor = out
    while not anchor.exists() and anchor != anchor.parent:
        anchor = anchor.parent
    if not anchor.is_dir() or not os.access(anchor, os.W_OK):
        raise CliError(f"output folder {out} is not writable" if anchor == out else
                       f"cannot create output folder {out}: {anchor} is not a writable folder")
    if anchor == out and not os.access(out.parent, os.W_OK):
        raise CliError(f"cannot write beside output folder {out}: {out.parent} is not writable")
    refuse_overwriting_inputs([out / name for name in names], inputs)
    for name in names:
        target = (out / name).resolve()
        if target.exists() and not force:
            raise CliError(f"{target} exists; use --force to overwrite")


def _points(args):
    apex = None if args.apex is None else _point(args.apex)
    base = None if args.base is None else _point(args.base)
    from ..io.markups import points_with_markups

    apex, base, landmarks, annulus = points_with_markups(
        args.points, apex=apex, base=base, landmarks=[_point(p) for p in args.landmark],
        annulus=[_point(p) for p in args.annulus])
    if apex is None and base is None and not annulus:
        apex = base = annulus = None  # none: the ventricle is located
    elif apex is None or (base is None and not annulus):
        raise CliError("give the apex and the base (--apex X Y Z --base X Y Z) or the apex and 3 or more points of "
                       "the mitral annulus (--annulus X Y Z, repeated), or --points with those labels, or no "
                       "points to locate the ventricle")
    return apex, base, (np.array(landmarks) if landmarks else None), (np.array(annulus) if annulus else None)


def _check_options(args) -> None:
    """Bad options: one line naming the command-line option, before any input is read."""
    from ..descent.options import LIMITS

    if getattr(args, "rv_insertion", None) is not None and not args.myocardium:
        raise CliError("--rv-insertion numbers the myocardium's segments: give --myocardium too")
    per_frame = getattr(args, "iterations_per_frame", 1)
    if not 1 <= per_frame <= LIMITS["max_iterations"]:
        raise CliError(f"--iterations-per-frame must be from 1 to {LIMITS['max_iterations']}, got {per_frame}")
    try:
        SegmentOptions(**_segment_kwargs(args))
    except ValueError as exc:
        name, _, rest = str(exc).partition(" ")
        if name in vars(args):
            raise CliError(f"--{name.replace('_', '-')} {rest}") from None
        raise


def _segment_kwargs(args) -> dict:
    return dict(system=args.system, patches=tuple(args.patches), mode=args.mode, step=args.step,
                max_iterations=args.max_iterations, smoothness=args.smoothness,
                smoothness_reference=args.smoothness_reference, threads=args.threads)


def _mask_suffix(args, source: Path) -> str:
    from ..io import MASK_SUFFIXES
    from ..io.outputs import default_mask_suffix

    if args.mask_format:
        suffix = args.mask_format if args.mask_format.startswith(".") else "." + args.mask_format
        if suffix.lower() not in MASK_SUFFIXES:
            raise CliError(f"--mask-format must be one of {', '.join(MASK_SUFFIXES)}, got {args.mask_format}")
        return suffix.lower()
    return default_mask_suffix(source)


# -- commands ----------------------------------------------------------------


def _kernels_loaded(seconds: dict) -> None:
    """Load the numerical path before any timed work (:func:`~spheroseg.apps.warmup.load_kernels`)."""
    from .warmup import load_kernels

    seconds["kernels"] = load_kernels()["seconds"]


def _load_timed(source, args, seconds: dict):
    """``load``, the kernels, then the padding search, each timed apart."""
    from ..io import load
    from .._compiled.raster import outside_sector
    from ..volumes.volume import Volume

    t0 = time.perf_counter()
    auto = isinstance(args.no_data, str)
    volume = load(source, spacing=args.spacing, no_data_value=None if auto else args.no_data)
    seconds["read"] = time.perf_counter() - t0
    _kernels_loaded(seconds)
    if auto and not isinstance(volume, Volume):  # a beam-space file: its NoDataValue key, read with it
        t0 = time.perf_counter()
        volume = load(source, spacing=args.spacing, no_data_value="auto")
        seconds["read"] += time.perf_counter() - t0
    elif auto:
        t0 = time.perf_counter()
        no_data = outside_sector(volume.array)  # None: no padding (an image with no zeros)
        if no_data is not None and no_data.all():  # refused here, before the points' check reads nothing
            raise ValueError(f"{source}: every voxel is 0: the image holds no echo data")
        volume = Volume(volume.array, spacing=volume.spacing, origin=volume.origin, direction=volume.direction,
                        no_data_mask=no_data)
        seconds["padding"] = time.perf_counter() - t0
    return volume


def shows_progress(args) -> bool:
    """Progress bars: on a terminal's stderr, or anywhere with --progress; never with --quiet."""
    return not getattr(args, "quiet", False) and (getattr(args, "progress", False) or sys.stderr.isatty())


def _progress_bar(args, **kwargs):
    """A tqdm bar on stderr when :func:`shows_progress`, else None."""
    if not shows_progress(args):
        return None
    from tqdm import tqdm

    # leave=False: the bar clears itself, so an error after it is the only line
    return tqdm(file=sys.stderr, leave=False, **kwargs)


@contextlib.contextmanager
def progress_callback(args, **kwargs):
    """A ``progress(done, total)`` callback drawing a bar (None without one), the bar closed after."""
    bar = _progress_bar(args, **kwargs)
    try:
        yield (lambda done, total: bar.update(done - bar.n)) if bar is not None else None
    finally:
        if bar is not None:
            bar.close()


def _report_worker(args):
    """What draws the command's report: a second process that imports
    matplotlib while this one loads and segments (:mod:`spheroseg.report_worker`),
    or nothing without a report."""
    if args.no_report:
        return contextlib.nullcontext()
    from .report_worker import ReportWorker

    return ReportWorker()


def cmd_segment(args) -> int:
    # CPU time of the main thread so far: the interpreter and the package
    # imports (the process's would add BLAS's and OpenMP's threads, and could
    # exceed the wall time it stands for)
    seconds = {"import": time.thread_time()}
    t0 = time.perf_counter()
    from ..io import write_folder_atomically
    from ..io.outputs import write_segmentation_outputs
    from ..tracking.segment import segment

    seconds["import"] += time.perf_counter() - t0
    source = Path(args.image)
    _check_options(args)
    suffix = _mask_suffix(args, source)
    apex, base, landmarks, annulus = _points(args)
    out = Path(args.out)
    _prepare_out(out, _output_set(), args.force, _inputs(args))
    with _report_worker(args) as worker:
        volume = _load_timed(source, args, seconds)
        t0 = time.perf_counter()
        result = segment(volume, apex, base, annulus=annulus, landmarks=landmarks, myocardium=args.myocardium,
                         rv_insertion=args.rv_insertion, **_segment_kwargs(args))
        seconds["segment"] = time.perf_counter() - t0
        seconds["descent"] = result.seconds
        written = write_folder_atomically(out, lambda tmp: write_segmentation_outputs(
            tmp, volume, result, source=source, apex=apex, base=base, annulus=annulus, landmarks=landmarks,
            mask_suffix=suffix, stl=args.stl, report=not args.no_report, seconds=seconds, report_worker=worker),
            replaces=_output_set())
    if args.profile:
        print(profile_lines(written["seconds"]), file=sys.stderr)
    _say(args, f"{_located(result)}cavity volume {result.volume_ml:.1f} mL ({result.iterations} iterations, "
               f"{1000 * result.seconds:.0f} ms); outputs in {out}")
    return _warn_quality([result], args)


def _located(result) -> str:
    """What the summary line says first when the apex and base were
    located rather than given (results.json has the points and the reason)."""
    start = result.initialisation or {}
    if start.get("method") != "located":
        return ""
    return f"apex and base located (confidence {start['located']['confidence']:.2f}); "


def _warn_quality(frames, args) -> int:
    """One line on stderr when a result is poor (results.json has the
    report); the exit status: :data:`EXIT_POOR` then, unless ``--allow-poor``."""
    from ..descent.quality import quality_notes, quality_warning

    for note in quality_notes(frames):
        print(f"spheroseg: note: {note}", file=sys.stderr)
    line = quality_warning(frames)
    if line:
        print(f"spheroseg: warning: {line}", file=sys.stderr)
    return EXIT_POOR if line and not args.allow_poor else 0


def profile_lines(seconds: dict) -> str:
    """The ``seconds`` block of results.json as a table, milliseconds."""
    order = ["import", "read", "kernels", "padding", "segment", "descent", "mask", "meshes", "writes", "report"]
    stages = [k for k in order if k in seconds] + [k for k in seconds if k not in order]
    total = sum(v for k, v in seconds.items() if k != "descent")
    lines = [f"  {k:<8} {1000 * seconds[k]:8.1f} ms" + ("  (inside segment)" if k == "descent" else "")
             for k in stages]
    return "\n".join(["spheroseg: seconds by stage"] + lines + [f"  {'total':<8} {1000 * total:8.1f} ms"])


def cmd_track(args) -> int:
    from ..io import load_sequence, write_folder_atomically
    from ..io.outputs import write_tracking_outputs
    from ..tracking.segment import track

    source = Path(args.sequence)
    _check_options(args)
    suffix = _mask_suffix(args, source)
    apex, base, landmarks, annulus = _points(args)
    out = Path(args.out)
    _prepare_out(out, _output_set(), args.force, _inputs(args))
    with _report_worker(args) as worker:
        t0 = time.perf_counter()
        volumes = load_sequence(args.sequence, spacing=args.spacing, no_data_value=args.no_data, glob=args.glob)
        t_load = time.perf_counter() - t0
        timings = {"load": t_load}
        _kernels_loaded(timings)
        bar = _progress_bar(args, total=len(volumes), unit="frame", desc="tracking")
        progress = (lambda done, total: bar.update(done - bar.n)) if bar is not None else None
        try:
            result = track(volumes, apex, base, annulus=annulus, landmarks=landmarks,
                           iterations_per_frame=args.iterations_per_frame, progress=progress,
                           myocardium=args.myocardium, rv_insertion=args.rv_insertion, start_frame=args.start_frame,
                           **_segment_kwargs(args))
        finally:
            if bar is not None:
                bar.close()
        written = write_folder_atomically(out, lambda tmp: write_tracking_outputs(
            tmp, volumes, result, source=source, apex=apex, base=base, annulus=annulus, landmarks=landmarks,
            mask_suffix=suffix, stl=args.stl, report=not args.no_report, seconds=timings, report_worker=worker),
            replaces=_output_set())
    if args.profile:
        seconds = written["seconds"]
        print(profile_lines({"load": seconds["load"], "kernels": seconds["kernels"],
                             "segment": sum(seconds["segment"])}), file=sys.stderr)
    _say(args, f"{_located(result)}EDV {result.edv_ml:.1f} mL (frame {result.ed_frame}), ESV {result.esv_ml:.1f} mL "
               f"(frame {result.es_frame}), EF {result.ef:.1f} %; outputs in {out}")
    return _warn_quality(result.frames, args)


def cmd_scan_convert(args) -> int:
    from ..volumes.beamspace import BeamVolume, check_scan_conversion, scan_convert
    from ..io import MASK_SUFFIXES, image_format, load, load_sequence, save_volume

    source, target = Path(args.image), Path(args.output)
    if image_format(target) not in MASK_SUFFIXES or image_format(target) == ".npy":
        raise CliError(f"output {target} must be one of {', '.join(s for s in MASK_SUFFIXES if s != '.npy')}")
    from ..io.atomic import refuse_overwriting_inputs
    from ..io import image_files

    refuse_overwriting_inputs([target] + ([target.with_suffix(".raw")] if image_format(target) == ".mhd" else []),
                              [source] + image_files(source), hint="choose another output")
    if target.exists() and not args.force:
        raise CliError(f"{target} exists; use --force to overwrite")
    if not target.parent.is_dir():
        raise CliError(f"output folder {target.parent} does not exist")
    if args.voxel_size is not None and not args.voxel_size > 0:
        raise CliError(f"--voxel-size must be positive, got {args.voxel_size}")
    t0 = time.perf_counter()
    try:
        volumes = [load(source)]
    except ValueError as exc:
        if "3D+t" not in str(exc):
            raise
        volumes = load_sequence(source)
    if not all(isinstance(v, BeamVolume) for v in volumes):
        raise CliError(f"{source} is not a beam-space file (no AzimuthAngularSeparation, ElevationAngularSeparation, "
                       "RadiusSampleSize, FirstSampleDistance keys)")
    grid = volumes[0].geometry.cartesian_grid(args.voxel_size)
    check_scan_conversion(grid, len(volumes))
    converted = [scan_convert(v, grid, order=0 if args.nearest else 1) for v in volumes]
    save_volume(target, converted if len(converted) > 1 else converted[0])
    nz, ny, nx = grid.shape
    _say(args, f"{len(converted)} frame(s) of {nx} x {ny} x {nz} voxels of {grid.spacing[0]:.3g} mm "
               f"in {time.perf_counter() - t0:.2f} s; wrote {target}")
    return 0


def cmd_batch(args) -> int:
    from tqdm import tqdm

    from .batch import read_manifest, segment_many, select_shard, warm_up, write_summary

    studies = select_shard(read_manifest(args.manifest), args.shard)
    _check_options(args)
    options = {**_segment_kwargs(args), "iterations_per_frame": args.iterations_per_frame,
               "no_data_value": args.no_data, "mask_suffix": _mask_suffix(args, Path("")) if args.mask_format else None,
               "stl": args.stl, "report": not args.no_report}
    out = Path(args.out)
    name = "summary" if args.shard is None else "summary-{}-of-{}".format(*args.shard)
    from ..io.atomic import refuse_overwriting_inputs
    from .batch import check_study_folders

    check_study_folders(studies, out, [args.manifest])
    refuse_overwriting_inputs([out / f"{name}.json", out / f"{name}.csv"],
                              [Path(args.manifest)] + [Path(s.image) for s in studies]
                              + [Path(s.points) for s in studies if s.points], hint="choose another --out")
    _make_folder(out)
    for variable in BLAS_THREADS:  # one worker per core: single-threaded BLAS in each (as Dask's workers)
        os.environ.setdefault(variable, "1")
    client = executor = None
    if args.scheduler:
        try:
            from distributed import Client
        except ImportError:
            raise CliError('--scheduler needs Dask: pip install "spheroseg[dask]"') from None
        try:
            client = Client(args.scheduler, timeout=30)
        except OSError as exc:
            raise CliError(f"cannot reach the Dask scheduler {args.scheduler}: {exc}") from None
        client.run(warm_up)
        executor = client.get_executor()
    rows = {}
    bar = tqdm(total=len(studies), unit="study", desc="batch", file=sys.stderr, disable=args.quiet)
    outcomes = segment_many(studies, out=out, executor=executor, workers=args.workers, timeout=args.timeout,
                            options=options, protect=[args.manifest])
    try:
        for outcome in outcomes:
            rows[outcome.id] = outcome.row
            bar.update(1)
            if outcome.status != "ok":
                bar.write(f"{outcome.id}: failed: {outcome.row['error']}", file=sys.stderr)
    except KeyboardInterrupt:
        outcomes.close()  # running studies finish; no partial folder stays
        bar.close()
        print("spheroseg: interrupted; finished studies are complete, run again to go on", file=sys.stderr)
        return 130
    finally:
        bar.close()
        if client is not None:
            client.close()
    write_summary(out, [rows[s.id] for s in studies], name=name)
    failed = sum(row["status"] != "ok" for row in rows.values())
    poor = sum(bool(row.get("poor")) for row in rows.values())
    _say(args, f"{len(rows) - failed} ok ({poor} poor), {failed} failed; summary in {out / name}.json and .csv")
    if poor:
        print(f"spheroseg: warning: {poor} poor result(s): see the poor column of {out / name}.csv", file=sys.stderr)
    return 1 if failed else (EXIT_POOR if poor and not args.allow_poor else 0)


def _fresh_demo_folder() -> Path:
    base = Path("spheroseg-demo")
    candidate, k = base, 2
    while candidate.exists():
        candidate = Path(f"{base}-{k}")
        k += 1
    return candidate


def cmd_demo(args) -> int:
    from ..surfaces.metrics import dice, surface_distances
    from ..io.outputs import versions, write_frame_files, write_json
    from ..synthetic.phantom import make_sequence
    from ..io.report import save_report
    from ..tracking.segment import track

    out = Path(args.out) if args.out else _fresh_demo_folder()
    _prepare_out(out, ["results.json", "report.png", "masks", "meshes"], args.force, [])
    _make_folder(out)
    _say(args, "spheroseg demo: a synthetic apical 3D+t echo sequence (10 frames, 1.25 mm voxels, speckle), tracked "
               "from its apex and base points and compared with its exact truth")
    t0 = time.perf_counter()
    with progress_callback(args, total=10, unit="frame", desc="making the sequence") as progress:
        seq = make_sequence(seed=0, n_frames=10, spacing=1.25, progress=progress)
    t_make = time.perf_counter() - t0
    timings = {"make_phantom": t_make}
    _kernels_loaded(timings)
    first = seq.frames[0]
    with progress_callback(args, total=len(seq.volumes), unit="frame", desc="tracking") as progress:
        result = track(seq.volumes, first.apex, first.base, progress=progress)
    ed = result.ed_frame
    rows = []
    for t, (frame, truth) in enumerate(zip(result.frames, seq.frames)):
        d = dice(frame.mask(truth.volume), truth.truth_mask)
        rows.append({"frame": t, "volume_ml": frame.volume_ml, "truth_ml": truth.truth_volume_ml, "dice": d,
                     "iterations": frame.iterations, "ms": 1000 * frame.seconds})
    sd = surface_distances(result.frames[ed].mesh(closed=False), seq.frames[ed].truth_mesh)
    write_frame_files(out, seq.volumes, result)
    save_report(out / "report.png", seq.volumes[ed], result.frames[ed].surface, volumes_ml=result.volumes_ml,
                ed_frame=ed, es_frame=result.es_frame, truth_mask=seq.frames[ed].truth_mask,
                title=f"demo: EF {result.ef:.1f} % (truth {seq.truth_ef:.1f} %); yellow spheroseg, red truth")
    seg_ms = 1000 * sum(f.seconds for f in result.frames)
    summary = {
        "frames": rows, "edv_ml": result.edv_ml, "esv_ml": result.esv_ml, "ef_percent": result.ef,
        "truth": {"edv_ml": float(seq.truth_volumes_ml.max()), "esv_ml": float(seq.truth_volumes_ml.min()),
                  "ef_percent": seq.truth_ef},
        "ed_surface_distance_mm": sd, "seconds": {**timings, "segment_all_frames": seg_ms / 1000},
        "versions": versions(),
    }
    write_json(out / "results.json", summary)
    dices = np.array([r["dice"] for r in rows])
    _say(args,
         f"  Dice per frame: median {np.median(dices):.3f}, worst {dices.min():.3f}",
         f"  ED frame {ed}: mean surface distance {sd['mean']:.2f} mm, Hausdorff {sd['hausdorff']:.2f} mm",
         f"  EDV {result.edv_ml:.1f} mL (truth {seq.truth_volumes_ml.max():.1f}), "
         f"ESV {result.esv_ml:.1f} mL (truth {seq.truth_volumes_ml.min():.1f})",
         f"  EF {result.ef:.1f} % (truth {seq.truth_ef:.1f} %)",
         f"  segmentation of all {len(rows)} frames: {seg_ms:.0f} ms",
         f"  outputs in {out}/: results.json, report.png, masks/ (NIfTI), meshes/ (.vtk, .ply, JSON, CMISS)")
    return 0


def cmd_view(args) -> int:
    from .viewer import open_viewer

    if not 0 <= args.port <= 65535:
        raise CliError(f"--port must be from 0 to 65535, got {args.port}")
    if args.save_root is not None and not Path(args.save_root).is_dir():
        raise CliError(f"--save-root {args.save_root} is not a folder")
    try:
        server = open_viewer(args.image, port=args.port, points=args.points, save_root=args.save_root,
                             spacing=args.spacing, no_data_value=args.no_data, system=args.system,
                             patches=tuple(args.patches), mode=args.mode)
    except OSError as exc:
        if exc.errno is not None and exc.filename is None:  # the socket, not a file
            raise CliError(f"cannot listen on 127.0.0.1:{args.port}: {exc.strerror}") from None
        raise
    # said before it starts: the kernels load (and the reference path's matrices are made) meanwhile
    print(f"spheroseg: {args.image} read; loading the numerical kernels", file=sys.stderr, flush=True)
    from .warmup import load_kernels

    load_kernels()
    print(server.url, flush=True)  # once the kernels are loaded: a pasted address answers at once
    if not args.no_browser:
        import webbrowser

        webbrowser.open(server.url)
    print("spheroseg: serving; Ctrl-C stops", file=sys.stderr)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("spheroseg: stopped", file=sys.stderr)
    finally:
        server.session.close()
        server.server_close()
    return 0


def cmd_live(args) -> int:
    """``live`` and ``replay`` (:mod:`spheroseg.apps.live.commands`), given what
    the other commands share: the options checked, the points, the kernels
    loading, and the demo's sequence for a replay of no file."""
    from .live.commands import run

    if args.command == "replay":
        from ..synthetic.phantom import make_sequence

        return run(args, demo=lambda: make_sequence(seed=0, n_frames=10, spacing=1.25).volumes)
    _check_options(args)
    apex, base, landmarks, annulus = _points(args)
    return run(args, points=dict(apex=apex, base=base, landmarks=landmarks, annulus=annulus),
               options=_segment_kwargs(args), prepare=lambda: _kernels_loaded({}))


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handlers = {"segment": cmd_segment, "track": cmd_track, "batch": cmd_batch, "scan-convert": cmd_scan_convert,
                "demo": cmd_demo, "view": cmd_view, "live": cmd_live, "replay": cmd_live}
    try:
        # numpy's warnings on extreme input (an overflow of 1e300) would be
        # lines before the error: the checks say what is wrong, in one
        with _owning(args), np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return handlers[args.command](args)
    except KeyboardInterrupt:
        print("spheroseg: interrupted", file=sys.stderr)
        return 130
    except (CliError, ValueError, TypeError, OSError, RuntimeError, MemoryError) as exc:
        print(f"spheroseg: error: {error_line(exc)}", file=sys.stderr)
        return EXIT_ERROR


def error_line(exc: BaseException) -> str:
    """An error as one line of text, a path's bytes that are not UTF-8
    shown as ``\\xff`` (never an encoding error, whatever the path)."""
    message = " ".join(str(exc).split()) or type(exc).__name__
    return message.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _owning(args):
    """The run's hold on its output folder (:mod:`spheroseg.io.lock`): a second
    run on the same ``--out`` is refused while this one runs."""
    if getattr(args, "out", None) is not None and not str(args.out).strip():
        raise CliError("--out must name a folder, got ''")  # '' would be the working folder, unasked
    if args.command not in ("segment", "track", "batch", "demo") or not getattr(args, "out", None):
        return contextlib.nullcontext()
    from ..io.lock import hold_output

    return hold_output(args.out, f"spheroseg {args.command}")


#: commands that leave nothing running when they return (no server, no
#: cluster): the console exits after them without the interpreter's teardown
_QUICK_EXIT = ("segment", "track", "scan-convert", "demo")


def console() -> None:
    """The ``spheroseg`` command: :func:`main`, then exit.  After a command
    that leaves nothing running, the process ends without tearing the
    interpreter down (the finalisers of the modules it loaded; they took
    a tenth of a segmentation command), its outputs written and closed and the
    standard streams flushed."""
    argv = sys.argv[1:]
    code = main(argv)
    if argv and argv[0] in _QUICK_EXIT:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console()
