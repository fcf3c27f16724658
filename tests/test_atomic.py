"""Files and folders written whole or not at all (spheroseg.io.atomic).

The all-or-nothing cycle of an output folder (a failed set, a first set, a
replacing set) is tests/test_io.py's test_write_folder_atomically_all_or_nothing."""

import os

import numpy as np
import pytest
import SimpleITK as sitk

from spheroseg.io.atomic import write_atomically, write_folder_atomically


def hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


class Boom(Exception):
    pass


def test_write_atomically_writes_the_file_and_leaves_nothing_else(tmp_path):
    seen = []

    def write(tmp):
        seen.append(tmp)
        tmp.write_bytes(b"abc")

    write_atomically(tmp_path / "out.bin", write)
    assert (tmp_path / "out.bin").read_bytes() == b"abc"
    # the writer was handed a path of the same name in a folder beside the target, now gone
    (tmp,) = seen
    assert tmp.name == "out.bin" and tmp.parent.parent == tmp_path and not tmp.parent.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


def test_a_writer_that_raises_leaves_no_file_and_no_temporary(tmp_path):
    def write(tmp):
        tmp.write_bytes(b"half a fi")
        raise Boom("disk full")

    with pytest.raises(Boom, match="disk full"):
        write_atomically(tmp_path / "out.bin", write)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("interrupt", [Boom, KeyboardInterrupt])
def test_an_existing_file_is_never_replaced_half_way(tmp_path, interrupt):
    (tmp_path / "out.bin").write_bytes(b"the old content")

    def write(tmp):
        tmp.write_bytes(b"the new con")
        raise interrupt()

    with pytest.raises(interrupt):
        write_atomically(tmp_path / "out.bin", write)
    assert (tmp_path / "out.bin").read_bytes() == b"the old content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]
    # a writer that finishes replaces it whole
    write_atomically(tmp_path / "out.bin", lambda tmp: tmp.write_bytes(b"new"))
    assert (tmp_path / "out.bin").read_bytes() == b"new"


def test_a_metaimage_header_and_its_data_file_move_together(tmp_path):
    """SimpleITK writes ``v.mhd`` and ``v.raw``: both arrive, and the header
    names the data file beside it (the image reads back bit for bit)."""
    array = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    image = sitk.GetImageFromArray(array)
    write_atomically(tmp_path / "v.mhd", lambda tmp: sitk.WriteImage(image, str(tmp)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mhd", "v.raw"]
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "v.mhd"))), array)


def test_write_folder_atomically_returns_what_the_writer_returned_and_makes_parents(tmp_path):
    out = tmp_path / "a" / "b" / "out"

    def write(folder):
        assert folder.parent == tmp_path and folder.name.startswith(".out.partial-")  # nearest existing folder
        (folder / "x.txt").write_text("x")
        return {"written": 1}

    assert write_folder_atomically(out, write) == {"written": 1}
    assert (out / "x.txt").read_text() == "x"
    assert hidden(tmp_path) == [] and hidden(out.parent) == []


@pytest.mark.parametrize("interrupt", [Boom, KeyboardInterrupt])
def test_write_folder_atomically_interrupted_leaves_out_as_it_was(tmp_path, interrupt):
    out = tmp_path / "out"
    out.mkdir()
    (out / "x.txt").write_text("old")
    (out / "keep.txt").write_text("mine")

    def write(folder):
        (folder / "x.txt").write_text("new")
        raise interrupt()

    with pytest.raises(interrupt):
        write_folder_atomically(out, write, replaces=["x.txt"])
    assert {p.name: p.read_text() for p in out.iterdir()} == {"x.txt": "old", "keep.txt": "mine"}
    assert hidden(tmp_path) == [] and hidden(out) == []


def test_write_folder_atomically_replaces_a_symlink_not_its_target(tmp_path):
    """An entry named in ``replaces`` that is a symbolic link (even a dangling
    one) is moved aside itself: the file it points to is untouched."""
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "elsewhere.txt").write_text("not ours")
    os.symlink(tmp_path / "elsewhere.txt", out / "x.txt")
    os.symlink(tmp_path / "nowhere.txt", out / "dangling.txt")
    write_folder_atomically(out, lambda folder: (folder / "x.txt").write_text("new"),
                            replaces=["x.txt", "dangling.txt"])
    assert not (out / "x.txt").is_symlink() and (out / "x.txt").read_text() == "new"
    assert not os.path.lexists(out / "dangling.txt")
    assert (tmp_path / "elsewhere.txt").read_text() == "not ours"
    assert hidden(out) == []


def test_entries_not_named_in_replaces_are_overwritten_only_by_new_ones(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("earlier run")
    (out / "same.txt").write_text("earlier")
    write_folder_atomically(out, lambda folder: (folder / "same.txt").write_text("later"))
    assert {p.name: p.read_text() for p in out.iterdir()} == {"old.txt": "earlier run", "same.txt": "later"}
