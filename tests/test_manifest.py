"""Manifests of cohorts (spheroseg.apps.manifest): what a study entry may
say, and the one precise error a bad manifest gives before anything runs.

JSON and CSV manifests of a real cohort agreeing is tests/test_batch.py's
test_manifests_json_and_csv_agree."""

import json

import pytest

from spheroseg.apps.manifest import MANIFEST_KEYS, ManifestError, Study, as_study, read_manifest, select_shard

ENTRY = {"id": "a", "image": "a.mha", "apex": [0, 0, 0], "base": [0, 0, 9]}


def manifest(tmp_path, entries, name="m.json"):
    path = tmp_path / name
    path.write_text(entries if isinstance(entries, str) else json.dumps(entries))
    return path


def error(path):
    with pytest.raises(ManifestError) as caught:
        read_manifest(path)
    assert isinstance(caught.value, ValueError)
    return str(caught.value)


def test_an_entry_becomes_a_study_with_absolute_paths(tmp_path):
    (tmp_path / "sub").mkdir()
    path = manifest(tmp_path / "sub", [
        {"id": "v1", "image": "images/v1.mha", "apex": "1, 2, 3", "base": [4, 5, 6.5], "points": "p/v1.mrk.json",
         "landmarks": [[1, 1, 1], "2 2 2"], "spacing": "0.5 0.5 0.75", "track": "No"},
        {"id": "s.2_x-3", "image": "/data/s2.nrrd", "annulus": "1 0 0; 0 1 0; -1 0 0;", "apex": [0, 0, 50],
         "track": True},
        {"id": "located", "image": "c.mha"},
    ])
    v1, s2, located = read_manifest(path)
    assert v1 == Study(id="v1", image=str(tmp_path / "sub" / "images" / "v1.mha"), apex=(1.0, 2.0, 3.0),
                       base=(4.0, 5.0, 6.5), landmarks=((1.0, 1.0, 1.0), (2.0, 2.0, 2.0)),
                       points=str(tmp_path / "sub" / "p" / "v1.mrk.json"), spacing=(0.5, 0.5, 0.75), track=False)
    assert s2 == Study(id="s.2_x-3", image="/data/s2.nrrd", apex=(0.0, 0.0, 50.0),
                       annulus=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)), track=True)
    assert located == Study(id="located", image=str(tmp_path / "sub" / "c.mha"))


def test_a_csv_manifest_is_the_same_studies(tmp_path):
    rows = ("id,image,apex,base,annulus,landmarks,spacing,track\n"
            "v1,images/v1.mha,1 2 3,4 5 6.5,,1 1 1; 2 2 2,0.5 0.5 0.75,no\n"
            's.2_x-3,/data/s2.nrrd,0 0 50,,"1 0 0; 0 1 0; -1 0 0",,,true\n')
    as_csv = read_manifest(manifest(tmp_path, "\ufeff" + rows, "m.csv"))  # a byte-order mark, as Excel writes
    as_json = read_manifest(manifest(tmp_path, [
        {"id": "v1", "image": "images/v1.mha", "apex": [1, 2, 3], "base": [4, 5, 6.5],
         "landmarks": [[1, 1, 1], [2, 2, 2]], "spacing": [0.5, 0.5, 0.75], "track": False},
        {"id": "s.2_x-3", "image": "/data/s2.nrrd", "apex": [0, 0, 50], "annulus": [[1, 0, 0], [0, 1, 0], [-1, 0, 0]],
         "track": True}]))
    assert as_csv == as_json


def test_as_entry_reads_back_as_the_same_study(tmp_path):
    path = manifest(tmp_path, [{**ENTRY, "landmarks": [[1, 2, 3]], "annulus": [[1, 0, 9], [0, 1, 9], [-1, 0, 9]],
                                "spacing": [1, 1, 2], "track": False}])
    (study,) = read_manifest(path)
    entry = study.as_entry()
    assert set(entry) == set(MANIFEST_KEYS) - {"glob"}  # glob only when true (the checksums of earlier cohorts)
    assert read_manifest(manifest(tmp_path, [{**entry, "glob": True}], "pattern.json"))[0].as_entry()["glob"] is True
    assert json.loads(json.dumps(entry)) == entry  # JSON values
    assert entry["annulus"] == [[1.0, 0.0, 9.0], [0.0, 1.0, 9.0], [-1.0, 0.0, 9.0]]
    assert read_manifest(manifest(tmp_path, [entry], "again.json")) == [study]
    assert as_study(entry, tmp_path / "elsewhere") == study  # its paths are absolute already
    assert as_study(study, tmp_path) is study


@pytest.mark.parametrize("entries, message", [
    ([ENTRY, {**ENTRY, "id": "b"}, {**ENTRY, "id": "A"}], "study 3: id 'A' appears twice"),
    ([{**ENTRY, "image": ""}], "study 1 (a): no image"),
    ([{k: v for k, v in ENTRY.items() if k != "image"}], "study 1 (a): no image"),
    ([{k: v for k, v in ENTRY.items() if k != "id"}],
     "study 1: id must be a safe folder name (letters, digits, . _ -; not starting with . _ -), got ''"),
    ([{**ENTRY, "id": ".hidden"}], "study 1 (.hidden): id must be a safe folder name"),
    ([{**ENTRY, "id": "a/b"}], "study 1 (a/b): id must be a safe folder name"),
    ([{**ENTRY, "id": "x" * 129}], "id must be a safe folder name"),
    ([ENTRY, {**ENTRY, "id": "summary-1-of-2.CSV"}],
     "study 2 (summary-1-of-2.CSV): id 'summary-1-of-2.CSV' is the name of the cohort's summary; choose another"),
    ([{**ENTRY, "colour": "red", "age": 3}],
     f"study 1 (a): unknown key(s) age, colour (known: {', '.join(MANIFEST_KEYS)})"),
    ([{**ENTRY, "apex": [0, 0]}], "study 1 (a): apex must be 3 finite numbers (x y z), got [0, 0]"),
    ([{**ENTRY, "base": "0 0 nan"}], "study 1 (a): base must be 3 finite numbers (x y z), got '0 0 nan'"),
    ([{**ENTRY, "base": "0 0 top"}], "study 1 (a): base must be numbers, got '0 0 top'"),
    ([{**ENTRY, "apex": None}], "study 1 (a): give apex and base (x y z, mm) or apex and annulus, or points"),
    ([{**ENTRY, "base": None}], "study 1 (a): give apex and base (x y z, mm) or apex and annulus, not the apex alone"),
    ([{**ENTRY, "base": None, "annulus": [[1, 0, 9], [0, 1, 9]]}],
     "study 1 (a): annulus needs 3 or more points, got 2"),
    ([{**ENTRY, "annulus": [[1, 0, 9], [0, 1, 9], [0, 9]]}],
     "study 1 (a): each point of annulus must be 3 finite numbers (x y z), got [0, 9]"),
    ([{**ENTRY, "landmarks": {"x": 1}}], "study 1 (a): landmarks must be a list of points, got {'x': 1}"),
    ([{**ENTRY, "spacing": [1, 0, 1]}], "study 1 (a): spacing must be positive, got (1.0, 0.0, 1.0)"),
    ([{**ENTRY, "track": "maybe"}], "study 1 (a): track must be true or false, got 'maybe'"),
    ([ENTRY, "a.mha"], "study 2: a study must be an object with keys id, image, apex"),
    ({"studies": [ENTRY]}, "a JSON manifest must be a list of studies"),
    ([], "no studies"),
    ('[{"id": "a",\n ]', "not JSON (Expecting property name enclosed in double quotes, line 2)"),
])
def test_a_bad_json_manifest_is_one_precise_error(tmp_path, entries, message):
    path = manifest(tmp_path, entries)
    text = error(path)
    assert text.startswith(f"{path}: ") and message in text and "\n" not in text, text


@pytest.mark.parametrize("rows, message", [
    ("id,image,apex,base\na,a.mha,0 0 0,0 0 9\nb,b.mha,0 0 0\n",
     "row 3 (b): give apex and base (x y z, mm) or apex and annulus, not the apex alone"),
    ("id,image,apex,base\na,a.mha,0 0 0,0 0 9\nA,b.mha,0 0 0,0 0 9\n", "row 3: id 'A' appears twice"),
    ("id,image,colour\na,a.mha,red\n", "row 2 (a): unknown key(s) colour"),
    ("", "empty CSV manifest (expected a header: id,image,apex,base,annulus,landmarks,points,spacing,track,glob)"),
    ("id,image\n", "no studies"),
])
def test_a_bad_csv_manifest_names_its_row(tmp_path, rows, message):
    path = manifest(tmp_path, rows, "m.csv")
    text = error(path)
    assert text.startswith(f"{path}: ") and message in text, text


def test_a_manifest_that_is_not_one(tmp_path):
    assert error(manifest(tmp_path, "id,image\n", "m.txt")).endswith(": a manifest is .json or .csv, got .txt")
    assert error(manifest(tmp_path, "id,image\n", "manifest")).endswith("got no suffix")
    (tmp_path / "latin.csv").write_bytes("id,image\ncaf\xe9,a.mha\n".encode("latin-1"))
    assert error(tmp_path / "latin.csv").endswith(": a manifest must be UTF-8 text (JSON or CSV)")
    assert error(tmp_path / "missing.json") == f"{tmp_path / 'missing.json'}: cannot read manifest (No such file or directory)"


def test_select_shard_deals_the_studies_round_robin():
    studies = list("abcdefg")
    assert select_shard(studies, None) == studies and select_shard(studies, None) is not studies
    assert select_shard(studies, (1, 3)) == ["a", "d", "g"]
    assert select_shard(studies, (3, 3)) == ["c", "f"]
    assert select_shard(studies, (7, 7)) == ["g"] and select_shard(studies, (8, 9)) == []
    for i, n in ((0, 2), (3, 2), (-1, 2)):
        with pytest.raises(ValueError, match=rf"^shard must be I/N with 1 <= I <= N, got {i}/{n}$"):
            select_shard(studies, (i, n))
