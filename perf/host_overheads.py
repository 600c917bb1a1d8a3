"""Host-side costs of ``gpps reconstruct`` on a capture folder, function by function (issue 20).

Times ``read_capture`` of the folder and the decoding alone (every PNG through ``cv2.imread``, one after
another), then on the folder's data: ``as_images``, ``check_observations``, ``folder._saturation`` and ``estimate_noise`` (the
whole mask, as ``PixelSolver.upload``).  Median of ``--repeat`` calls after one warm-up call; no device.

Usage:  python perf/host_overheads.py [FOLDER] [--repeat 7] [--out perf/results/host_overheads_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402

from perf._common import device_label  # noqa: E402

from gpps._check import as_images  # noqa: E402
from gpps.flows.folder import _saturation  # noqa: E402
from gpps.flows.photometric import check_observations  # noqa: E402
from gpps.io.capture import read_capture  # noqa: E402
from gpps.lights import DirectionalLights  # noqa: E402
from gpps.pipeline.solver import estimate_noise  # noqa: E402


def _median(fn, repeat: int) -> float:
    fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def _imread_all(folder) -> None:
    """Every image file of the folder through ``cv2.imread``, one after another (the decoding alone)."""
    for p in sorted(Path(folder).glob("*.png")):
        cv2.imread(str(p), cv2.IMREAD_UNCHANGED)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default="/work/shared/data/diligent/bear")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    cap = read_capture(a.folder)
    ds = cap.dataset
    lights = DirectionalLights(ds.light_directions)
    valid = _saturation(cap)
    img = ds.images
    rows = {
        "read_capture": _median(lambda: read_capture(a.folder), a.repeat),
        "cv2.imread sequential (all PNGs)": _median(lambda: _imread_all(a.folder), a.repeat),
        "as_images": _median(lambda: as_images("images", img), a.repeat),
        "check_observations": _median(lambda: check_observations(img, ds.mask, lights, valid=valid), a.repeat),
        "_saturation": _median(lambda: _saturation(cap), a.repeat),
        "estimate_noise": _median(lambda: estimate_noise(img, ds.mask), a.repeat),
    }
    res = {"folder": str(a.folder), "shape": list(img.shape), "mask_pixels": int(ds.mask.sum()),
           "device": device_label("cpu"), "repeat": a.repeat, "median_s": rows}
    print(json.dumps(res, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
