"""The host's time in ``PixelSolver.upload`` on issue 20's capture (256^2 x 3, perspective Cook-Torrance;
:func:`_common.reconstruct_inputs`), the whole call and its pieces: the images' checks and float32 copy, the grey
values and their percentile, and each copy into the device buffers (``wp.array.assign`` of a numpy array: a
pageable host-to-device copy on CUDA), each device-synchronised; ``upload_checked`` is the upload RON makes after
the flows' checks (``checked=True``: no grey values or percentile), ``upload_checked_own_noise`` the same with the
noise levels estimated by the upload (on CUDA on the device: RON's upload there since session 45).  Median of ``--repeat`` calls after one warm-up,
milliseconds; one JSON line.

Usage:  python perf/upload_timing.py [--device cuda:0] [--repeat 30]
"""
import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))

from _common import reconstruct_inputs  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=30)
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import warp as wp

    import gpps
    from gpps.flows.reconstruction import _prepare
    from gpps.host.observations import masked_grey
    from gpps.pipeline.solver import PixelSolver

    c = reconstruct_inputs(256, 3, a.device)
    p = _prepare(c["images"], c["mask"], c["lights"], c["camera"], "cook-torrance", "auto", None, None, None, None,
                 None)
    s = PixelSolver(p.shape, p.camera, p.lights, gpps.Material("cook-torrance"), p.config.solver, device=a.device)
    img, m, val = p.images, p.mask, p.valid
    idx = np.flatnonzero(m)
    v8 = val.astype(np.uint8) if val is not None else np.ones(p.shape, np.uint8)

    def ms(f):
        f()
        wp.synchronize_device(a.device)
        ts = []
        for _ in range(a.repeat):
            t = time.perf_counter()
            f()
            wp.synchronize_device(a.device)
            ts.append(time.perf_counter() - t)
        return round(statistics.median(ts) * 1e3, 3)

    g = masked_grey(img, m, idx=idx)
    out = {
        "upload": ms(lambda: s.upload(img, m, valid=val, noise=p.noise)),
        "upload_checked": ms(lambda: s.upload(img, m, valid=val, noise=p.noise, checked=True)),  # (RON's, after
        # the flows' checks: no grey values, no percentile)
        "upload_checked_own_noise": ms(lambda: s.upload(img, m, valid=val, checked=True)),  # (the noise levels
        # estimated by the upload: on CUDA on the device since session 45, RON's upload there; numpy on the CPU)
        "images_checked": ms(lambda: s._images(img)),
        "grey": ms(lambda: masked_grey(img, m, idx=idx)),
        "percentile": ms(lambda: np.percentile(g, 99.0)),
        "assign_images": ms(lambda: s.images.assign(s._images(img))),
        "assign_valid": ms(lambda: s.valid.assign(v8)),
        "assign_mask": ms(lambda: s.mask.assign(m.astype(np.uint8))),
        "assign_noise": ms(lambda: s.noise.assign(p.noise)),
        "depth_fill": ms(lambda: s.depth.fill_(1.0)),
    }
    s.close()
    print(json.dumps({"device": a.device, "size": 256, "images": 3, "median_ms": out}))


if __name__ == "__main__":
    main()
