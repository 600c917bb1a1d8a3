"""Host time of :func:`gpps.reconstruct`'s preparation on issue 20's capture (256^2 x 3, perspective Cook-Torrance,
float images with clipped highlights; :func:`_common.reconstruct_inputs`), piece by piece: median of ``--repeat``
calls after one warm-up, milliseconds.  Nothing here touches a device: the same figures on any machine's host
(``--device`` only renders the capture).  Since session 44 ``prepare`` includes the noise estimate, which runs
with the working scale on the shared CPU pool beside the clipping and observation checks; ``pieces_sum`` is the
pieces one after another (the host's work before).

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
        "check_inputs": ms(ph.check_inputs, c["images"], c["mask"], c["lights"], c["camera"]),
        "clipped_observations": ms(clipped_observations, img, m),
        "check_observations": ms(ph.check_observations, img, m, lights),
        "working_scale": ms(ph.working_scale, img, m, lights),
        "estimate_noise": ms(estimate_noise, img, m),
    }
    out["pieces_sum"] = round(sum(v for k, v in out.items() if k != "prepare"), 3)
    print(json.dumps({"size": a.size, "images": a.images, "median_ms": out}))


if __name__ == "__main__":
    main()
