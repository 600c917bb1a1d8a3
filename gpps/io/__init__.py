"""Readers and writers: image files, capture folders, output folders, meshes.

:mod:`gpps.io.files` holds the file primitives and the output-folder rules (checked before computing,
written to a temporary name and renamed, never overwriting what gpps did not write); they are
re-exported here.  :mod:`gpps.io.formats` reads image formats (16-bit PNG, TIFF, EXR, JPEG / sRGB),
:mod:`gpps.io.capture` a capture folder (images, lights, camera, mask), :mod:`gpps.io.nearlight` the
LED captures, :mod:`gpps.io.outputs` writes a reconstruction's files and :mod:`gpps.io.mesh` its mesh.

The public readers and writers are re-exported here (the names of ``__all__``): the command line
uses this package only.  Importing it costs numpy alone (OpenCV, tifffile and OpenEXR load on use).
"""

from gpps.io.files import *  # noqa: F401,F403
from gpps.io.files import __all__ as _files_all
from gpps.io.capture import SIDE_IMAGE_STEMS, Capture, find_side_file, list_images, read_capture
from gpps.io.outputs import OUTPUT_FILES, apply_depth_convention, depth_convention, write_outputs

__all__ = [
    *_files_all,
    "Capture",
    "read_capture",
    "list_images",
    "find_side_file",
    "SIDE_IMAGE_STEMS",
    "write_outputs",
    "depth_convention",
    "apply_depth_convention",
    "OUTPUT_FILES",
]
