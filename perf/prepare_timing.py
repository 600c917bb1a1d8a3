"""Host time of :func:`gpps.reconstruct`'s preparation on issue 20's capture (256^2 x 3, perspective Cook-Torrance,
float images with clipped highlights; :func:`_common.reconstruct_inputs`), piece by piece: median of ``--repeat``
calls after one warm-up, milliseconds.  Nothing here touches a device: the same figures on any machine's host
(``--device`` only renders the capture).  Since session 44 ``prepare`` includes the noise estimate, which runs
with the working scale on the shared CPU pool beside the clipping and observation checks; ``pieces_sum`` is the
pieces one after another (the host's work before); ``prepare_no_noise`` is the preparation on CUDA since session
45 (the noise levels estimated on the device by the solver's upload).  ``checks_frames`` / ``checks_gathered``: the clipping
detection and the observation checks reading the frames each (before session 45) and from one gather of the mask's
observations (``_prepare`` since then), interleaved in one process.

Usage:  python perf/prepare_timing.py [--size 256] [--images 3] [--repeat 30]
"""
import argparse
import json
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
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--device", default="cpu", help="where the capture is rendered (the timed work is the host's)")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from gpps.flows import photometric as ph
    from gpps.flows import reconstruction as rc
    from gpps.host.clipping import clipped_observations
    from gpps.host.observations import gather_masked
    from gpps.pipeline.solver import estimate_noise

    c = reconstruct_inputs(a.size, a.images, a.device)
    img, m, lights, cam = ph.check_inputs(c["images"], c["mask"], c["lights"], c["camera"])

    def ms(f, *args):
        f(*args)
        ts = []
        for _ in range(a.repeat):
            t = time.perf_counter()
            f(*args)
            ts.append(time.perf_counter() - t)
        return round(float(np.median(ts)) * 1e3, 3)

    out = {
        "prepare": ms(rc._prepare, c["images"], c["mask"], c["lights"], c["camera"], "cook-torrance", "auto",
                      None, None, None, None, None),
        # (on CUDA: the noise levels estimated on the device by the solver's upload, none on the host)
        "prepare_no_noise": ms(lambda *x: rc._prepare(*x, host_noise=False), c["images"], c["mask"], c["lights"],
                               c["camera"], "cook-torrance", "auto", None, None, None, None, None),
        "check_inputs": ms(ph.check_inputs, c["images"], c["mask"], c["lights"], c["camera"]),
        "clipped_observations": ms(clipped_observations, img, m),
        "check_observations": ms(ph.check_observations, img, m, lights),
        "working_scale": ms(ph.working_scale, img, m, lights),
        "estimate_noise": ms(estimate_noise, img, m),
    }
    out["pieces_sum"] = round(sum(v for k, v in out.items() if not k.startswith("prepare")), 3)
    # the clipping detection and the observation checks as _prepare runs them (the mask's observations gathered
    # once, session 45) and each reading the frames (before): the same flags, interleaved medians
    sat = ph.input_saturation(c["images"], None)

    def checks(shared):
        g = None
        if shared:
            idx = np.flatnonzero(m)
            g = (idx, gather_masked(img if img.ndim == 4 else img[..., None], idx))
        val, clipped = ph.detect_clipping(c["images"], img, m, sink=[], gathered=g)
        return ph.check_observations(img, m, lights, valid=val, saturation=sat, sink=[], clipped=clipped,
                                     gathered=g), val

    r0, r1 = checks(False), checks(True)
    assert np.array_equal(r0[0], r1[0]) and (r0[1] is r1[1] is None or np.array_equal(r0[1], r1[1]))
    ts = {False: [], True: []}
    for _ in range(2 * a.repeat):
        for shared in (False, True):
            t = time.perf_counter()
            checks(shared)
            ts[shared].append(time.perf_counter() - t)
    out["checks_frames"] = round(float(np.median(ts[False])) * 1e3, 3)
    out["checks_gathered"] = round(float(np.median(ts[True])) * 1e3, 3)
    print(json.dumps({"size": a.size, "images": a.images, "median_ms": out}))


if __name__ == "__main__":
    main()
