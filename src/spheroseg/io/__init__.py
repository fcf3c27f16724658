"""Reading and writing the files of the field, one module a job:
:mod:`spheroseg.images` (images through SimpleITK, and ``.npy``),
:mod:`spheroseg.markups` (3D Slicer markups) and :mod:`spheroseg.atomic`
(files and folders written whole).  Their public names are importable from
here as well.
"""

from .atomic import write_atomically, write_folder_atomically
from .images import (BEAM_KEYS, BEAM_OPTIONAL_KEYS, BEAM_SUFFIXES, BUDGET_VARIABLE, IMAGE_SUFFIXES, MASK_SUFFIXES,
                     ImageFileError, beam_geometry_from_header, beam_header, check_image_size, frame_order, image_files,
                     image_format, is_sequence_file, load, load_frames, load_sequence, save_mask, save_volume,
                     shown_path)
from .markups import MARKUPS_UNITS, read_markups, write_markups

__all__ = ["load", "load_sequence", "load_frames", "save_mask", "save_volume", "read_markups", "write_markups",
           "image_format", "IMAGE_SUFFIXES", "MASK_SUFFIXES", "BEAM_SUFFIXES", "BEAM_KEYS", "BEAM_OPTIONAL_KEYS",
           "beam_header", "beam_geometry_from_header", "image_files", "write_atomically", "write_folder_atomically",
           "check_image_size", "ImageFileError", "BUDGET_VARIABLE", "MARKUPS_UNITS", "frame_order", "is_sequence_file",
           "shown_path"]
