"""Readers and writers: image files, capture folders, output folders, meshes.

:mod:`gpps.io.files` holds the file primitives and the output-folder rules (checked before computing,
written to a temporary name and renamed, never overwriting what gpps did not write); they are
re-exported here.  :mod:`gpps.io.formats` reads image formats (16-bit PNG, TIFF, EXR, JPEG / sRGB),
:mod:`gpps.io.capture` a capture folder (images, lights, camera, mask), :mod:`gpps.io.nearlight` the
LED captures, :mod:`gpps.io.outputs` writes a reconstruction's files and :mod:`gpps.io.mesh` its mesh.
"""

from gpps.io.files import *  # noqa: F401,F403
from gpps.io.files import __all__  # noqa: F401
