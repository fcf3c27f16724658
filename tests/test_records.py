"""The records of a cohort (spheroseg.apps.records): checksums, summary rows
and the summary files.

A checksum following a real MetaImage's bytes and its markups is
tests/test_batch.py's test_checksum_follows_every_input_byte."""

import csv
import hashlib
import json

import pytest

from spheroseg.apps.manifest import Study
from spheroseg.apps.records import SUMMARY_FIELDS, study_checksum, summary_row, write_summary


def expected_checksum(study, options, files):
    """SHA-256 as study_checksum documents it, by hand: the entry and the
    options as sorted JSON, then each input file's name between NULs and its
    bytes (``\\0missing\\0`` for a missing one)."""
    digest = hashlib.sha256(json.dumps({"study": study.as_entry(), "options": options}, sort_keys=True).encode())
    for path in files:
        digest.update(b"\0" + path.name.encode() + b"\0")
        digest.update(path.read_bytes() if path.exists() else b"\0missing\0")
    return digest.hexdigest()


def test_the_checksum_of_a_volume_and_its_markups_is_sha256_of_their_bytes(tmp_path):
    (tmp_path / "v.mha").write_bytes(bytes(range(256)) * 5000)  # more than one 1 MiB block read
    (tmp_path / "p.mrk.json").write_text('{"markups": []}')
    study = Study(id="v", image=str(tmp_path / "v.mha"), apex=(1.0, 2.0, 3.0), points=str(tmp_path / "p.mrk.json"))
    options = {"patches": [4, 4], "myocardium": False}
    files = [tmp_path / "v.mha", tmp_path / "p.mrk.json"]
    assert study_checksum(study, options) == expected_checksum(study, options, files)
    # the thread count is left out; the key order of the options does not count
    assert study_checksum(study, {"myocardium": False, "threads": 8, "patches": [4, 4]}) == \
        expected_checksum(study, options, files)
    assert study_checksum(study, {**options, "patches": [8, 4]}) != expected_checksum(study, options, files)


def test_the_checksum_reads_a_metaimage_s_data_file_and_counts_a_missing_one(tmp_path):
    (tmp_path / "v.mhd").write_text("ObjectType = Image\nNDims = 3\nElementDataFile = v.raw\n")
    (tmp_path / "v.raw").write_bytes(b"\x01\x02\x03")
    study = Study(id="v", image=str(tmp_path / "v.mhd"))
    assert study_checksum(study, {}) == expected_checksum(study, {}, [tmp_path / "v.mhd", tmp_path / "v.raw"])
    (tmp_path / "v.raw").unlink()
    assert study_checksum(study, {}) == expected_checksum(study, {}, [tmp_path / "v.mhd", tmp_path / "v.raw"])


def test_the_checksum_of_a_folder_is_its_files_in_name_order(tmp_path):
    (tmp_path / "frames" / "sub").mkdir(parents=True)
    for name, data in (("b.mha", b"B"), ("a.mha", b"A"), ("sub/c.mha", b"C")):
        (tmp_path / "frames" / name).write_bytes(data)
    study = Study(id="s", image=str(tmp_path / "frames"))
    files = [tmp_path / "frames" / n for n in ("a.mha", "b.mha", "sub/c.mha")]
    before = study_checksum(study, {})
    assert before == expected_checksum(study, {}, files)
    # two frames swapped: the same bytes in all, another sequence (names are hashed with their bytes)
    (tmp_path / "frames" / "a.mha").write_bytes(b"B")
    (tmp_path / "frames" / "b.mha").write_bytes(b"A")
    assert study_checksum(study, {}) != before


SEGMENTED = {"id": "v1", "volume_ml": 123.4, "iterations": 57, "status": 0,
             "quality": {"poor": False, "warnings": [], "contrast": 2.5},
             "seconds": {"load": 0.25, "segment": 1.5, "report": 9.0}}
TRACKED = {"id": "s1", "volumes_ml": [150.0, 120.0, 90.0], "edv_ml": 150.0, "esv_ml": 90.0, "ef_percent": 40.0,
           "iterations": [30, 12, 9], "quality": {"poor": True, "warnings": ["frame 2: low contrast"]},
           "seconds": {"load": 1.0, "segment": [2.0, 0.5, 0.25]}}


def test_the_summary_row_of_a_segmentation():
    row = summary_row(SEGMENTED)
    assert tuple(row) == SUMMARY_FIELDS
    assert row == {"id": "v1", "status": "ok", "kind": "segment", "volume_ml": 123.4, "edv_ml": None, "esv_ml": None,
                   "ef": None, "iterations": 57, "descent_status": 0, "poor": False, "quality": SEGMENTED["quality"],
                   "seconds": 1.75, "error": None}  # load + segment: 0.25 + 1.5


def test_the_summary_row_of_a_tracked_sequence():
    row = summary_row(TRACKED)
    assert row["kind"] == "track" and row["volume_ml"] is None
    assert (row["edv_ml"], row["esv_ml"], row["ef"]) == (150.0, 90.0, 40.0)
    assert row["iterations"] == 51 and isinstance(row["iterations"], int)  # 30 + 12 + 9
    assert row["seconds"] == pytest.approx(3.75)  # 1 + 2 + 0.5 + 0.25
    assert row["poor"] is True and row["descent_status"] is None


def test_a_row_of_what_results_do_not_say():
    row = summary_row({"id": "x"})
    assert row["iterations"] is None and row["poor"] is None and row["quality"] is None and row["seconds"] == 0.0


def test_write_summary_json_and_csv_say_the_same(tmp_path):
    failed = {"id": "bad", "status": "failed", "error": "x.mha: no such file", "colour": "not a column"}
    rows = [summary_row(SEGMENTED), summary_row(TRACKED), failed]
    json_path, csv_path = write_summary(tmp_path, rows, name="summary-1-of-2")
    assert (json_path, csv_path) == (tmp_path / "summary-1-of-2.json", tmp_path / "summary-1-of-2.csv")
    written = json.loads(json_path.read_text())
    assert [list(r) for r in written] == [list(SUMMARY_FIELDS)] * 3
    assert written[:2] == rows[:2]
    assert written[2] == {k: failed.get(k) for k in SUMMARY_FIELDS}  # the unknown key dropped, the rest None
    with open(csv_path, newline="") as handle:
        reader = csv.DictReader(handle)
        assert tuple(reader.fieldnames) == SUMMARY_FIELDS
        table = list(reader)
    assert len(table) == 3
    assert json.loads(table[0]["quality"]) == SEGMENTED["quality"]  # a dict as JSON text
    assert float(table[0]["volume_ml"]) == 123.4 and table[0]["edv_ml"] == ""  # None as empty
    assert (table[1]["iterations"], table[1]["poor"], float(table[1]["ef"])) == ("51", "True", 40.0)
    assert table[2]["error"] == "x.mha: no such file" and table[2]["quality"] == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary-1-of-2.csv", "summary-1-of-2.json"]
