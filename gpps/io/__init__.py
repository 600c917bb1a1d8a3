"""Readers and writers: image files, capture folders, output folders, meshes.

:mod:`gpps.io.files` holds the file primitives and the output-folder rules (checked before computing,
written to a temporary name and renamed, never overwriting what gpps did not write); they are
re-exported here.  :mod:`gpps.io.formats` reads image formats (16-bit PNG, TIFF, EXR, JPEG / sRGB),
:mod:`gpps.io.capture` a capture folder (images, lights, camera, mask), :mod:`gpps.io.nearlight` the
LED captures, :mod:`gpps.io.outputs` writes a reconstruction's files and :mod:`gpps.io.mesh` its mesh.

The public readers and writers are re-exported here (the names of ``__all__``): the command line
uses this package only.  The capture reader loads lazily: it brings scipy (the automatic mask), about
0.25 s that ``gpps --help`` would otherwise pay.
"""

import importlib

from gpps.io.files import *  # noqa: F401,F403
from gpps.io.files import __all__ as _files_all
from gpps.io.outputs import OUTPUT_FILES, apply_depth_convention, depth_convention, write_outputs

_LAZY = {name: "gpps.io.capture" for name in ("Capture", "read_capture", "list_images", "find_side_file", "SIDE_IMAGE_STEMS")}


def __getattr__(name):
    """Lazy exports: ``gpps.io.read_capture`` loads :mod:`gpps.io.capture` (and scipy) on first use."""
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gpps.io' has no attribute {name!r}")


__all__ = [
    *_files_all,
    *_LAZY,
    "write_outputs",
    "depth_convention",
    "apply_depth_convention",
    "OUTPUT_FILES",
]
