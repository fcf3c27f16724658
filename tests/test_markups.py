"""3D Slicer markups files (spheroseg.io.markups).

Labels, units, undefined and duplicated points of hand-written files are
tests/test_io.py's test_markups_*; here: Slicer's own layout, each node's
coordinate system, what write_markups writes, and the errors."""

import json

import numpy as np
import pytest

from spheroseg.io.images import ImageFileError
from spheroseg.io.markups import read_markups, write_markups

SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/"
          "markups-schema-v1.0.3.json#")


def slicer_point(k, label, position, status="defined"):
    """A control point as 3D Slicer 5 saves it."""
    return {"id": str(k), "label": label, "description": "", "associatedNodeID": "vtkMRMLScalarVolumeNode1",
            "position": position, "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True, "locked": False, "visibility": True, "positionStatus": status}


def slicer_node(kind, system, points):
    """A markups node as 3D Slicer 5 saves it (display properties trimmed)."""
    return {"type": kind, "coordinateSystem": system, "coordinateUnits": "mm", "locked": False,
            "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d", "lastUsedControlPointNumber": len(points),
            "controlPoints": [slicer_point(k + 1, *p) for k, p in enumerate(points)], "measurements": [],
            "display": {"visibility": True, "opacity": 1.0, "color": [0.4, 1.0, 1.0], "glyphType": "Sphere3D",
                        "glyphScale": 3.0, "textScale": 3.0, "pointLabelsVisibility": True}}


def write_doc(path, *nodes):
    path.write_text(json.dumps({"@schema": SCHEMA, "markups": list(nodes)}, indent=4))
    return path


# the points a user placed, in RAS (Slicer's view coordinates) and, by hand, LPS: (-R, -A, S)
RAS = {"apex": [12.5, -30.25, 80.0], "base": [-4.0, 6.5, 10.75], "F-3": [1.0, 2.0, 3.0],
       "landmark-1": [20.0, 0.0, -5.5]}
LPS = {"apex": [-12.5, 30.25, 80.0], "base": [4.0, -6.5, 10.75], "landmark-1": [-20.0, -0.0, -5.5]}


@pytest.mark.parametrize("system", ["RAS", "LPS"])
def test_a_file_as_slicer_saves_it(tmp_path, system):
    """A Fiducial node as Slicer saves it, in either coordinate system: the
    same points in LPS mm, the unlabelled ``F-3`` left out."""
    given = RAS if system == "RAS" else {**LPS, "F-3": [1.0, 2.0, 3.0]}
    marks = read_markups(write_doc(tmp_path / "p.mrk.json", slicer_node("Fiducial", system, list(given.items()))))
    np.testing.assert_array_equal(marks["apex"], LPS["apex"])
    np.testing.assert_array_equal(marks["base"], LPS["base"])
    np.testing.assert_array_equal(marks["landmarks"], [LPS["landmark-1"]])
    assert marks["annulus"].shape == (0, 3)


def test_each_node_has_its_own_coordinate_system(tmp_path):
    """Apex and base in a RAS Fiducial node, the annulus in an LPS closed
    curve (any markups type has control points), landmarks in a node with no
    coordinateSystem (LPS, the schema's default)."""
    annulus_lps = [[10.0, 0.0, 50.0], [0.0, 10.0, 52.0], [-10.0, 0.0, 51.0]]
    path = write_doc(tmp_path / "p.mrk.json",
                     slicer_node("Fiducial", "RAS", [("Apex", RAS["apex"]), ("BASE", RAS["base"])]),
                     slicer_node("ClosedCurve", "LPS", [(f"annulus-{k + 1}", p) for k, p in enumerate(annulus_lps)]),
                     {"type": "Fiducial", "controlPoints": [{"label": "Landmark 2", "position": [1.0, -2.0, 3.0]}]})
    marks = read_markups(path)
    np.testing.assert_array_equal(marks["apex"], LPS["apex"])
    np.testing.assert_array_equal(marks["base"], LPS["base"])
    np.testing.assert_array_equal(marks["annulus"], annulus_lps)
    np.testing.assert_array_equal(marks["landmarks"], [[1.0, -2.0, 3.0]])


def test_write_markups_writes_slicer_s_layout_in_lps_mm(tmp_path, rng):
    apex, base = rng.normal(size=3) * 40, rng.normal(size=3) * 40
    annulus, landmarks = rng.normal(size=(4, 3)) * 30, rng.normal(size=(2, 3)) * 30
    write_markups(tmp_path / "p.mrk.json", apex=apex, base=base, annulus=annulus, landmarks=landmarks)
    doc = json.loads((tmp_path / "p.mrk.json").read_text())
    assert doc["@schema"] == SCHEMA
    (node,) = doc["markups"]
    assert (node["type"], node["coordinateSystem"], node["coordinateUnits"]) == ("Fiducial", "LPS", "mm")
    points = node["controlPoints"]
    assert [p["label"] for p in points] == ["apex", "base"] + ["annulus"] * 4 + ["landmark-1", "landmark-2"]
    assert [p["id"] for p in points] == [str(k) for k in range(1, 9)]
    assert {p["positionStatus"] for p in points} == {"defined"}
    np.testing.assert_array_equal([p["position"] for p in points], np.vstack([apex, base, annulus, landmarks]))
    # and read back, bit for bit
    marks = read_markups(tmp_path / "p.mrk.json")
    np.testing.assert_array_equal(marks["apex"], apex)
    np.testing.assert_array_equal(marks["base"], base)
    np.testing.assert_array_equal(marks["annulus"], annulus)
    np.testing.assert_array_equal(marks["landmarks"], landmarks)


def test_write_markups_of_nothing_reads_back_as_nothing(tmp_path):
    write_markups(tmp_path / "p.mrk.json")
    marks = read_markups(tmp_path / "p.mrk.json")
    assert marks["apex"] is None and marks["base"] is None
    assert marks["annulus"].shape == (0, 3) and marks["landmarks"].shape == (0, 3)


@pytest.mark.parametrize("points, message", [
    ({"apex": [1.0, 2.0]}, r"^apex must be 3 finite numbers \(x, y, z in mm\), got \[1\.0, 2\.0\]$"),
    ({"base": [0.0, np.inf, 1.0]}, r"^base must be 3 finite numbers \(x, y, z in mm\), got \[0\.0, inf, 1\.0\]$"),
    ({"landmarks": [[1, 2, 3], [4, 5, 6, 7]]}, r"^landmark-2 must be 3 finite numbers"),
])
def test_write_markups_refuses_bad_points_and_keeps_the_old_file(tmp_path, points, message):
    write_markups(tmp_path / "p.mrk.json", apex=[1, 2, 3])
    before = (tmp_path / "p.mrk.json").read_bytes()
    with pytest.raises(ValueError, match=message):
        write_markups(tmp_path / "p.mrk.json", **points)
    assert (tmp_path / "p.mrk.json").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["p.mrk.json"]


@pytest.mark.parametrize("content, detail", [
    ("not json", "JSONDecodeError"),
    ('{"points": []}', "KeyError: 'markups'"),
    ('{"markups": [{"controlPoints": [{"label": "apex", "position": [1, 2]}]}]}', "ValueError: cannot reshape"),
    ('{"markups": [{"controlPoints": [{"label": "base"}]}]}', "KeyError: 'position'"),
    ('[1, 2]', "TypeError"),
])
def test_not_a_markups_file_is_one_line_naming_the_file(tmp_path, content, detail):
    (tmp_path / "p.mrk.json").write_text(content)
    with pytest.raises(ValueError) as error:
        read_markups(tmp_path / "p.mrk.json")
    text = str(error.value)
    assert text.startswith(f"{tmp_path / 'p.mrk.json'}: not a 3D Slicer markups file with control points (")
    assert detail in text and "\n" not in text


def test_apex_in_two_nodes_is_refused(tmp_path):
    path = write_doc(tmp_path / "p.mrk.json", slicer_node("Fiducial", "LPS", [("apex", [0.0, 0.0, 0.0])]),
                     slicer_node("Fiducial", "RAS", [("Apex", [1.0, 1.0, 1.0])]))
    with pytest.raises(ImageFileError, match=r"p\.mrk\.json: two control points labelled 'apex'; keep one$"):
        read_markups(path)


def test_a_folder_is_no_markups_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=f"^{tmp_path}: no such file$"):
        read_markups(tmp_path)
