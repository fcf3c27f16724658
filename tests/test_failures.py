"""The rules of docs/failures.md against the round-4 hostile-input review
(``../shared/notes/reliability-round4.md``): each test names its case and
fails without the rule's check."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import cli

from spheroseg.synthetic.phantom import make_phantom

SRC = str(Path(__file__).resolve().parents[1] / "src")
FAST = ["--no-report", "--quiet", "--allow-poor"]


def run(*args, env=None, timeout=120, **kwargs):
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "PYTHONPATH": SRC, **(env or {})}
    return subprocess.run([sys.executable, "-m", "spheroseg", *args], capture_output=True, env=env,
                          timeout=timeout, **kwargs)


def one_error_line(stderr) -> str:
    text = stderr.decode(errors="surrogateescape") if isinstance(stderr, bytes) else stderr
    lines = text.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spheroseg: error:"), text
    return lines[0]


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    """A small phantom written as .mha, its apex and base as arguments."""
    folder = tmp_path_factory.mktemp("phantom")
    ph = make_phantom(seed=1, spacing=3.0)
    image = sitk.GetImageFromArray(ph.volume.array.astype(np.uint8))
    image.SetSpacing(tuple(ph.volume.spacing))
    sitk.WriteImage(image, str(folder / "p1.mha"))
    points = ["--apex", *map(str, ph.apex), "--base", *map(str, ph.base)]
    return folder / "p1.mha", points, ph


# 1. batch replaced an input with a study folder --------------------------------


@pytest.mark.parametrize("ident", ["p1.mha", "m.json", "P1.MHA"])
def test_batch_never_replaces_an_input_with_a_study_folder(capfd, phantom, tmp_path, ident):
    """Round 4: ``id: p1.mha`` with ``--out`` the images' folder made the
    image a folder of outputs (the manifest too, with ``id: m.json``)."""
    image, _, ph = phantom
    folder = tmp_path / "X"
    folder.mkdir()
    (folder / "p1.mha").write_bytes(image.read_bytes())
    (folder / "p2.mha").write_bytes(image.read_bytes())
    entry = {"apex": list(map(float, ph.apex)), "base": list(map(float, ph.base))}
    manifest = folder / "m.json"
    studies = [{"id": ident, "image": "p1.mha", **entry}, {"id": "s2", "image": "p2.mha", **entry}]
    manifest.write_text(json.dumps(studies))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    if ident == "P1.MHA" and (folder / "P1.MHA").exists():
        pytest.skip("a case-insensitive file system: the id is the input's name")
    proc = cli(capfd, "batch", manifest, "--out", folder, "--workers", "1", *FAST)
    if ident == "P1.MHA":  # another name on a case-sensitive file system: no input in the way
        assert proc.returncode in (0, 3), proc.stderr
        assert (folder / "P1.MHA" / "results.json").exists()
    else:
        assert proc.returncode == 2
        assert "would overwrite an input" in one_error_line(proc.stderr)
    after = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file() and not p.name.startswith("summary")}
    assert after == before  # every input as it was


def test_segment_refuses_an_out_inside_the_input_folder_of_frames(capfd, phantom, tmp_path):
    """A folder of frames gaining a mask.mha would gain a frame."""
    image, points, _ = phantom
    frames = tmp_path / "frames"
    frames.mkdir()
    for t in range(2):
        (frames / f"frame_{t}.mha").write_bytes(image.read_bytes())
    proc = cli(capfd, "track", frames, *points, "--out", frames, *FAST)
    assert proc.returncode == 2 and "would overwrite an input" in one_error_line(proc.stderr)
    assert sorted(p.name for p in frames.iterdir()) == ["frame_0.mha", "frame_1.mha"]


# 3. non-UTF-8 paths aborted in C++ -------------------------------------------


def test_a_path_that_is_not_utf8_is_an_error_line_never_an_abort(phantom, tmp_path):
    """Round 4: exit 134 (SimpleITK's abort), no ``spheroseg:`` line."""
    image, points, _ = phantom
    bad = os.fsencode(tmp_path) + b"/bad\xffname.mha"
    with open(bad, "wb") as handle:
        handle.write(image.read_bytes())
    proc = run("segment", bad, *points, "--out", str(tmp_path / "o"), *FAST)
    assert proc.returncode == 2, proc.stderr
    assert "bad\\xffname.mha: the path is not UTF-8" in one_error_line(proc.stderr)
    folder = os.fsencode(tmp_path) + b"/seq"
    os.mkdir(folder)
    os.link(bad, folder + b"/frame_\xfe1.mha")
    proc = run("track", folder, *points, "--out", str(tmp_path / "o2"), *FAST)
    assert proc.returncode == 2 and "frame_\\xfe1.mha" in one_error_line(proc.stderr)
    assert sorted(os.listdir(os.fsencode(tmp_path))) == [b"bad\xffname.mha", b"seq"]


def test_an_out_folder_that_is_not_utf8_is_written(phantom, tmp_path):
    """Round 4: ``--out $'o\\xfe'`` aborted and left ``.o\\xfe.partial-*``."""
    image, points, _ = phantom
    out = os.fsencode(tmp_path) + b"/o\xfe"
    proc = run("segment", str(image), *points, "--out", out, *FAST)
    assert proc.returncode in (0, 3), proc.stderr
    assert b"results.json" in os.listdir(out) and b"mask.mha" in os.listdir(out)
    assert os.listdir(os.fsencode(tmp_path)) == [b"o\xfe"]


# 4. a points file without apex/base labels ------------------------------------


@pytest.mark.parametrize("labels", [["F-1", "F-2"], ["apex1", "base"], []])
def test_a_points_file_without_apex_and_base_is_refused(capfd, phantom, tmp_path, labels):
    """Round 4: Slicer's default labels F-1/F-2 were ignored and the
    ventricle located instead (exit 0); batch refused the same file."""
    image, _, ph = phantom
    points = tmp_path / "p.mrk.json"
    control = [{"label": label, "position": list(map(float, p)), "positionStatus": "defined"}
               for label, p in zip(labels, [ph.apex, ph.base])]
    points.write_text(json.dumps({"markups": [{"type": "Fiducial", "controlPoints": control}]}))
    proc = cli(capfd, "segment", image, "--points", points, "--out", tmp_path / "o", *FAST)
    line = one_error_line(proc.stderr)
    assert proc.returncode == 2 and "no control points labelled apex and base" in line
    assert ("'F-1', 'F-2'" in line) if labels == ["F-1", "F-2"] else True
    assert not (tmp_path / "o").exists()


# 9. two runs on one --out ------------------------------------------------------


def test_a_second_run_on_the_same_out_is_refused_and_a_stale_lock_taken_over(capfd, phantom, tmp_path):
    """Round 4: two batches deleted each other's folders; two segments into
    a missing folder both exited 0, the second replacing the first."""
    from spheroseg.io.lock import hold_output

    image, points, _ = phantom
    out = tmp_path / "o"
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, time
        from spheroseg.io.lock import hold_output
        with hold_output({str(out)!r}, "spheroseg segment"):
            print("held", flush=True)
            time.sleep(60)
    """)], stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": SRC})
    try:
        assert holder.stdout.readline().strip() == b"held"
        proc = cli(capfd, "segment", image, *points, "--out", out, *FAST)
        line = one_error_line(proc.stderr)
        assert proc.returncode == 2 and f"is in use by process {holder.pid}" in line and "spheroseg segment" in line
        assert not out.exists()
        holder.kill()  # as kill -9: its lock file stays, the lock does not
        holder.wait()
        assert (tmp_path / ".o.lock").exists()
        proc = cli(capfd, "segment", image, *points, "--out", out, *FAST)
        assert proc.returncode in (0, 3), proc.stderr
        assert (out / "results.json").exists() and not (tmp_path / ".o.lock").exists()
    finally:
        holder.kill()
    with hold_output(out, "test"):  # and held, it refuses this process too
        with pytest.raises(OSError, match="is in use by process"):
            with hold_output(out, "test"):
                pass


# 11. --force all or nothing under kill -9 ------------------------------------


KILLER = """
import os, signal, sys
from pathlib import Path
import spheroseg.io.atomic as atomic

out, k = Path(sys.argv[1]), int(sys.argv[2])
calls = [0]

def counted(function):
    def call(*args, **kwargs):
        calls[0] += 1
        if calls[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)
        return function(*args, **kwargs)
    return call

for name in ("replace", "link", "symlink", "mkdir"):
    setattr(atomic.os, name, counted(getattr(os, name)))
atomic._exchange = counted(atomic._exchange)
atomic.shutil.rmtree = counted(atomic.shutil.rmtree)

def write(folder):
    (folder / "masks").mkdir()
    for t in range(3):
        (folder / "masks" / f"frame_{t}.mha").write_text("new")
    (folder / "mask.mha").write_text("new")
    (folder / "results.json").write_text("new")

atomic.write_folder_atomically(out, write, replaces=["results.json", "mask.mha", "masks", "report.png"])
print(calls[0])
"""


def test_force_replaces_a_set_all_or_nothing_under_kill_at_every_step(tmp_path):
    """Round 4: SIGKILL at 15 of 28 points of the swap left --out partial.
    Killed at each file-system step of the replacement, --out holds the old
    set or the new one, whole, and the user's own file."""
    script = tmp_path / "killer.py"
    script.write_text(KILLER)

    def old_set(out):
        (out / "masks").mkdir(parents=True)
        for t in range(5):  # a longer earlier sequence: its stale frames go with it
            (out / "masks" / f"frame_{t}.mha").write_text("old")
        for name in ("mask.mha", "results.json", "report.png"):
            (out / name).write_text("old")
        (out / "mine.txt").write_text("the user's")

    def state(out):
        return {str(p.relative_to(out)): p.read_text() for p in sorted(out.rglob("*")) if p.is_file()}

    old_out = tmp_path / "reference-old"
    old_set(old_out)
    old = state(old_out)
    new = {"mask.mha": "new", "masks/frame_0.mha": "new", "masks/frame_1.mha": "new", "masks/frame_2.mha": "new",
           "mine.txt": "the user's", "results.json": "new"}
    env = {**os.environ, "PYTHONPATH": SRC}
    full = subprocess.run([sys.executable, str(script), str(tmp_path / "dry"), "0"], env=env, capture_output=True,
                          text=True, check=True)
    seen = set()
    for k in range(1, 40):
        out = tmp_path / f"run{k}" / "o"
        old_set(out)
        proc = subprocess.run([sys.executable, str(script), str(out), str(k)], env=env, capture_output=True,
                              text=True, cwd=tmp_path)
        found = state(out)
        assert found in (old, new), (k, found)
        seen.add("new" if found == new else "old")
        if proc.returncode == 0:
            break
    assert proc.returncode == 0 and seen == {"old", "new"} and int(full.stdout) > 0


# 8. batch --timeout -----------------------------------------------------------


DEADLINE = """
import sys, time
sys.path.insert(0, sys.argv[1])
from spheroseg.apps.batch import StudyTimeout, _Deadline

# a module whose import outlasts the deadline: the timeout waits for it
open(sys.argv[1] + "/slow_module.py", "w").write("import time\\ntime.sleep(0.4)\\nDONE = True\\n")
deadline = _Deadline(0.05)
try:
    try:
        deadline.start()
        import slow_module
        time.sleep(5)
    finally:
        deadline.stop()
except StudyTimeout:
    print("timed out", slow_module.DONE)
# a deadline of a microsecond, at any line: always stopped, never kills the process
for _ in range(200):
    deadline = _Deadline(1e-6)
    try:
        try:
            deadline.start()
            sum(range(1000))
        finally:
            deadline.stop()
    except StudyTimeout:
        pass
time.sleep(0.2)
print("alive")
"""


def test_a_timeout_never_lands_in_an_import_nor_outlives_its_study(tmp_path):
    """Round 4: --timeout 0.3 poisoned a worker mid-import (later studies:
    module 'matplotlib' has no attribute '_docstring'), 0.001 hung."""
    script = tmp_path / "deadline.py"
    script.write_text(DEADLINE)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": SRC})
    assert proc.stdout.split("\n")[:2] == ["timed out True", "alive"], proc.stderr


def test_an_infinite_timeout_is_no_limit(capfd, tmp_path):
    """Round 4: --timeout inf printed thread tracebacks (OverflowError)."""
    from spheroseg.apps.batch import segment_many

    with pytest.raises(ValueError, match="timeout must be at most"):
        segment_many([], out=tmp_path, timeout=1e300)
    assert list(segment_many([], out=tmp_path, timeout=float("inf"))) == []


# 10. orphan workers -------------------------------------------------------------


PARENT = """
import sys, time
from spheroseg.apps.batch import _local_pool
from spheroseg.apps.report_worker import ReportWorker
import os

if __name__ == "__main__":  # the pool's workers are spawned: they import this file
    report = ReportWorker(parallel=True)
    pool = _local_pool(1)
    print(report._process.pid, pool.submit(os.getpid).result(), flush=True)
    time.sleep(120)
"""


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    state = Path(f"/proc/{pid}/stat").read_text().split()[2] if Path(f"/proc/{pid}/stat").exists() else "?"
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's parent-death signal")
def test_workers_die_with_their_parent_under_kill_9(tmp_path):
    """Round 4: kill -9 of the batch left its workers (~300 MB each) under
    PID 1 for minutes."""
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": SRC})
    children = []
    try:
        children = [int(p) for p in parent.stdout.readline().split()]
        assert len(children) == 2 and all(_alive(p) for p in children)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        end = time.monotonic() + 10
        while any(_alive(p) for p in children) and time.monotonic() < end:
            time.sleep(0.1)
        assert not any(_alive(p) for p in children)
    finally:
        parent.kill()
        for pid in children:  # without the rule they outlive the test: end them
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


# 6. memory -------------------------------------------------------------------------


def test_a_scan_conversion_grid_over_the_budget_is_refused_before_it_is_made(tmp_path):
    """Round 4: --voxel-size 0.2 grew to 7.8 GB; the grid was never checked."""
    from spheroseg.io import save_volume

    from spheroseg.volumes.beamspace import BeamGeometry, BeamVolume

    geometry = BeamGeometry((60, 21, 21), 1.5, 10.0, 0.05, 0.05)
    save_volume(tmp_path / "beam.mha", BeamVolume(np.ones(geometry.shape), geometry))
    proc = run("scan-convert", str(tmp_path / "beam.mha"), str(tmp_path / "o.mha"), "--voxel-size", "0.2",
               env={"SPHEROSEG_MAX_IMAGE_GB": "0.5"})
    line = one_error_line(proc.stderr)
    assert proc.returncode == 2 and "a scan conversion of 1 frame(s) onto" in line and "over the memory budget" in line
    assert not (tmp_path / "o.mha").exists()


def test_locate_reads_the_image_in_slabs_to_the_same_result(monkeypatch):
    """locate's coarse copy is read slab by slab, its temporaries those of a
    slab, not of the image (round 4: an 800^3 image peaked at 7.6 GB in
    locate): one block row a slab finds what the whole image at once does."""
    import importlib

    from spheroseg.tracking.locate import locate

    module = importlib.import_module("spheroseg.locate")
    ph = make_phantom(seed=1, spacing=1.5)
    monkeypatch.setattr(module, "_SLAB_VOXELS", 1 << 40)  # all at once
    whole = locate(ph.volume)
    monkeypatch.setattr(module, "_SLAB_VOXELS", 1)  # a row of blocks at a time
    sliced = locate(ph.volume)
    np.testing.assert_array_equal(sliced.apex, whole.apex)
    np.testing.assert_array_equal(sliced.base, whole.base)
    assert sliced.confidence == whole.confidence


def test_locate_holds_less_than_the_image_beside_it(monkeypatch):
    """What locate allocates at its peak (numpy's arrays, as tracemalloc
    counts them), in slabs of a block row: under the image's own bytes (the
    whole image at once: 3.2 times them, masks and float copies)."""
    import importlib
    import tracemalloc

    from spheroseg.tracking.locate import locate

    module = importlib.import_module("spheroseg.locate")
    ph = make_phantom(seed=1, spacing=1.0)
    monkeypatch.setattr(module, "_SLAB_VOXELS", 1)
    tracemalloc.start()
    try:
        locate(ph.volume)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < ph.volume.array.nbytes


# 7. the hang of locate's waist ----------------------------------------------------------


def test_a_huge_spacing_is_no_ventricle_not_a_hang(tmp_path):
    """Round 4: ElementSpacing 1e6 hung in locate._waist (O(n^2) over 5e7 sections)."""
    ph = make_phantom(seed=1, spacing=3.0)
    image = sitk.GetImageFromArray(ph.volume.array.astype(np.uint8))
    image.SetSpacing((1e6, 1e6, 1e6))
    sitk.WriteImage(image, str(tmp_path / "huge.mha"))
    proc = run("segment", str(tmp_path / "huge.mha"), "--out", str(tmp_path / "o"), *FAST, timeout=90)
    assert proc.returncode == 2 and "no left ventricle found" in one_error_line(proc.stderr)


# the minor list ---------------------------------------------------------------------


def _markups(path, control, **markup):
    path.write_text(json.dumps({"markups": [{"type": "Fiducial", "controlPoints": control, **markup}]}))
    return path


@pytest.mark.parametrize("system, status, error", [
    ("IJK", "defined", "coordinateSystem must be LPS or RAS, got 'IJK'"),
    (0, "defined", "coordinateSystem must be LPS or RAS, got 0"),
    ("LPS", "preview", "positionStatus 'preview', not 'defined'"),
    ("LPS", "missing", "positionStatus 'missing', not 'defined'"),
])
def test_markups_read_as_what_they_say_or_refused(tmp_path, system, status, error):
    """Round 4: "IJK" or 0 read as LPS, "preview" points used."""
    from spheroseg.io import read_markups

    path = _markups(tmp_path / "p.mrk.json", [{"label": "apex", "position": [1, 2, 3], "positionStatus": status}],
                    coordinateSystem=system)
    with pytest.raises(ValueError, match=error):
        read_markups(path)


def test_markups_with_a_byte_order_mark_and_a_padded_system(tmp_path):
    from spheroseg.io import read_markups

    path = tmp_path / "p.mrk.json"
    doc = {"markups": [{"coordinateSystem": "RAS ", "controlPoints": [{"label": "apex", "position": [1, 2, 3]}]}]}
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(doc).encode())
    np.testing.assert_array_equal(read_markups(path)["apex"], [-1, -2, 3])  # "RAS " is RAS, not LPS


def test_a_csv_manifest_with_a_column_twice_is_refused(tmp_path):
    from spheroseg.apps.batch import ManifestError, read_manifest

    path = tmp_path / "m.csv"
    path.write_text("id,image,apex,base,apex\ns1,a.mha,1 2 3,4 5 6,7 8 9\n")
    with pytest.raises(ManifestError, match="column\\(s\\) apex appear twice"):
        read_manifest(path)


def test_metaimage_headers_that_itk_reads_wrongly_are_refused(tmp_path):
    """Round 4: CompressedData = True on raw data gave "Uncompress failed"
    then "every voxel is 0"; Offset nan was read as 0."""
    from spheroseg.io import ImageFileError, load

    sitk.WriteImage(sitk.GetImageFromArray(np.ones((4, 5, 6), np.float32)), str(tmp_path / "a.mhd"))
    header = (tmp_path / "a.mhd").read_text()
    (tmp_path / "c.mhd").write_text(header.replace("CompressedData = False", "CompressedData = True"))
    (tmp_path / "n.mhd").write_text(header.replace("Offset = 0 0 0", "Offset = nan 0 0"))
    with pytest.raises(ImageFileError, match=r"c.mhd: cannot read image \(Uncompress failed"):
        load(tmp_path / "c.mhd")
    with pytest.raises(ImageFileError, match=r"n.mhd: header key Offset must be finite numbers, got 'nan 0 0'"):
        load(tmp_path / "n.mhd")


@pytest.mark.parametrize("args, error", [
    (["--out", ""], "--out must name a folder, got ''"),
    (["--rv-insertion", "1", "2", "3", "--out", "o"], "--rv-insertion numbers the myocardium's segments"),
    (["--smoothness", "1e308", "--out", "o"], "--smoothness must be at most 1e+06"),
])
def test_options_the_method_cannot_use_are_one_line_errors(capfd, monkeypatch, phantom, tmp_path, args, error):
    image, points, _ = phantom
    monkeypatch.chdir(tmp_path)
    proc = cli(capfd, "segment", image, *points, *args, *FAST)
    assert proc.returncode == 2 and error in one_error_line(proc.stderr)
    assert list(tmp_path.iterdir()) == []


def test_a_point_given_twice_is_refused(capfd, phantom, tmp_path):
    image, points, _ = phantom
    proc = cli(capfd, "segment", image, *points, "--apex", "1", "2", "3", "--out", tmp_path / "o", *FAST)
    assert proc.returncode == 2 and "--apex given twice" in proc.stderr


def test_api_misuse_is_a_clear_error():
    """Round 4: segment(ndarray) raised AttributeError, order 1 or 2
    LinAlgError, a NaN origin "negative dimensions are not allowed"."""
    from spheroseg import SegmentOptions, segment, track

    with pytest.raises(TypeError, match="volume must be a spheroseg.Volume, got ndarray"):
        segment(np.zeros((10, 10, 10)), [1, 1, 1], [5, 5, 5])
    with pytest.raises(TypeError, match="got ndarray"):
        track([np.zeros((10, 10, 10))] * 2, [1, 1, 1], [5, 5, 5])
    for order in (1, 2):
        with pytest.raises(ValueError, match="order must be from 3 to 16"):
            SegmentOptions(order=order)


def test_a_black_frame_is_named(phantom):
    """Round 4: one black frame failed the whole track without naming it."""
    from spheroseg._compiled.raster import outside_sector
    from spheroseg.tracking.segment import track
    from spheroseg.synthetic.phantom import make_sequence
    from spheroseg.volumes.volume import Volume

    seq = make_sequence(seed=2, n_frames=3, spacing=3.0)
    volumes = list(seq.volumes)
    black = np.zeros_like(volumes[2].array)
    volumes[2] = Volume(black, spacing=volumes[2].spacing, no_data_mask=outside_sector(black))
    with pytest.raises(ValueError, match=r"^frame 2: no image data around the surface"):
        track(volumes, seq.frames[0].apex, seq.frames[0].base)


def test_batch_track_false_on_a_sequence_says_the_manifest_key(tmp_path):
    """Round 4: the advice was "use spheroseg track", in a batch."""
    from spheroseg.apps.batch import Study, run_study
    from spheroseg.synthetic.phantom import make_sequence

    seq = make_sequence(seed=2, n_frames=2, spacing=3.0)
    image = sitk.JoinSeries([sitk.GetImageFromArray(v.array) for v in seq.volumes])
    sitk.WriteImage(image, str(tmp_path / "s.mha"))
    study = Study(id="s", image=str(tmp_path / "s.mha"), apex=tuple(seq.frames[0].apex),
                  base=tuple(seq.frames[0].base), track=False)
    row = run_study(study, tmp_path / "out", options={"report": False})
    assert row["status"] == "failed" and "the manifest says track: false; set track to true" in row["error"]


def test_out_folders_get_the_mode_mkdir_gives(capfd, phantom, tmp_path):
    """Round 4: --out was made 0700 (mkdtemp's), batch study folders 0755."""
    image, points, _ = phantom
    umask = os.umask(0o022)
    try:
        proc = cli(capfd, "segment", image, *points, "--out", tmp_path / "o", *FAST)
    finally:
        os.umask(umask)
    assert proc.returncode in (0, 3), proc.stderr
    assert (tmp_path / "o").stat().st_mode & 0o777 == 0o755


def test_a_detached_nrrd_header_smaller_than_its_data_is_refused(tmp_path):
    """Round 4: accepted silently (ITK reads the first bytes: a scrambled image)."""
    from spheroseg.io import ImageFileError, load

    sitk.WriteImage(sitk.GetImageFromArray(np.ones((4, 5, 6), np.float32)), str(tmp_path / "x.nhdr"))
    assert load(tmp_path / "x.nhdr", no_data_value=None).shape == (4, 5, 6)
    text = (tmp_path / "x.nhdr").read_text()
    assert "sizes: 6 5 4" in text
    (tmp_path / "y.nhdr").write_text(text.replace("sizes: 6 5 4", "sizes: 6 5 3"))
    with pytest.raises(ImageFileError, match=r"y.nhdr: its data file x.raw holds 480 bytes, 120 more than"):
        load(tmp_path / "y.nhdr")


def test_a_bad_nrrd_says_why(tmp_path):
    """Round 4: NRRD errors ended with ITK's "Error reading ...:", no reason."""
    from spheroseg.io import ImageFileError, load

    header = b"NRRD0004\ntype: flot\ndimension: 3\nsizes: 6 5 4\nencoding: raw\n\n"
    (tmp_path / "bad.nrrd").write_bytes(header + bytes(480))
    with pytest.raises(ImageFileError, match=r"bad.nrrd: cannot read image \(.*: couldn't parse type \"flot\"\)"):
        load(tmp_path / "bad.nrrd")


def test_track_reads_a_pattern_only_with_glob(capfd, phantom, tmp_path):
    """Round 4: ``track 'cine[12].mha'`` tracked cine1 and cine2 (EF 1.4 %)
    while results.json named cine[12].mha."""
    image, points, _ = phantom
    for t in (1, 2):
        (tmp_path / f"cine{t}.mha").write_bytes(image.read_bytes())
    proc = cli(capfd, "track", tmp_path / "cine[12].mha", *points, "--out", tmp_path / "o", *FAST)
    assert proc.returncode == 2 and "cine[12].mha: no such file (a pattern? give --glob)" in one_error_line(proc.stderr)
    assert not (tmp_path / "o").exists()
