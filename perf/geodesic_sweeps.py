"""DGMC's geodesic K-nearest-boundary sweeps (``DeviceDGMC._geodesics``) on the 256^2 x 3 reconstruct case.

The case is ``perf/profile_reconstruct.py``'s ``_synthetic``: perspective Cook-Torrance bumps, 3 directional lights
on a ring, 16-bit, material "cook-torrance" to estimate.  One ``gpps.reconstruct`` call records the exact
arguments RON passes to :meth:`gpps.pipeline.dgmc.DeviceDGMC.upload` (and the stage's config and device); a
:class:`DeviceDGMC` built once on them
runs ``upload`` + highlights + regions, then ``_geodesics`` is timed (median of ``--repeat`` after one warm-up,
device-synchronised): total, sweeps and time per sweep, wall and the process's CPU time (on a shared CPU the CPU
time is the steadier figure; with the CPU thread split it is the sum over the threads; the load averages before
and after are written too).  The converged lists' SHA-256 is written too, so two
versions of the kernels can be checked for identical lists.  Then ``--reconstruct`` warm ``gpps.reconstruct``
calls give the median wall time and the median DGMC stage time (``timings["dgmc"]``).

Usage:  python perf/geodesic_sweeps.py [--device cpu] [--size 256] [--repeat 5] [--reconstruct 3] [--name NAME]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))

import numpy as np  # noqa: E402
from _common import reconstruct_case, write_results  # noqa: E402


def _case(size: int, n: int, device):
    case = reconstruct_case(size, n, device)

    def call():
        rec, maen = case()
        return rec.timings, maen()
    return call


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--reconstruct", type=int, default=3, help="warm reconstruct calls (0: skip)")
    ap.add_argument("--name", default="geodesic_sweeps")
    a = ap.parse_args(argv)

    from gpps._runtime import warp
    from gpps.pipeline.dgmc import DeviceDGMC

    wp = warp()
    load0 = os.getloadavg()[0]
    call = _case(a.size, a.images, a.device)
    seen = {}
    orig = DeviceDGMC.upload

    def spy(self, images, mask, normals, **kw):
        # the solver's device frame is copied: its buffer is reused after DGMC
        imgs = wp.clone(images) if isinstance(images, wp.array) else np.array(images)
        seen.update(images=imgs, mask=np.array(mask), normals=np.array(normals), kw=kw, config=self.config,
                    device=self.device)
        return orig(self, images, mask, normals, **kw)

    DeviceDGMC.upload = spy
    try:
        call()  # cold: compiles; records DGMC's arguments
    finally:
        DeviceDGMC.upload = orig
    device = seen["device"]
    imgs = seen["images"]
    st = DeviceDGMC(tuple(imgs.shape[:3]), config=seen["config"], device=device)
    st.upload(imgs, seen["mask"], seen["normals"], **seen["kw"])
    st._highlights()
    st._regions()
    sync = lambda: wp.synchronize_device(device)  # noqa: E731
    st._geodesics()  # warm-up
    sync()
    ts, cpu = [], []
    for _ in range(a.repeat):
        c = time.process_time()
        t = time.perf_counter()
        st._geodesics()
        sync()
        ts.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    total = statistics.median(ts)
    lists = hashlib.sha256(st.keys[0].numpy().tobytes() + st.srcs[0].numpy().tobytes()).hexdigest()
    region = st.region.numpy().astype(bool)
    row = {"size": a.size, "images": a.images, "k_nearest": int(st.config.k_nearest),
           "region_pixels": int(region.sum()), "sweeps": int(st.sweeps),
           "geodesics_s": total, "geodesics_runs_s": ts, "per_sweep_s": total / max(st.sweeps, 1),
           "geodesics_cpu_s": statistics.median(cpu), "geodesics_cpu_runs_s": cpu,
           "threads": int(st.sweep_count.shape[0]) if not str(device).startswith("cuda") else 1,
           "lists_sha256": lists}
    print({k: v for k, v in row.items() if not k.endswith("runs_s")}, flush=True)
    if a.reconstruct:
        walls, cpus, dgmc, maen = [], [], [], None
        for _ in range(a.reconstruct):
            c = time.process_time()
            t = time.perf_counter()
            timings, maen = call()
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
            dgmc.append(float(timings["dgmc"]))
        row.update(reconstruct_s=statistics.median(walls), reconstruct_runs_s=walls,
                   reconstruct_cpu_s=statistics.median(cpus), reconstruct_cpu_runs_s=cpus,
                   dgmc_stage_s=statistics.median(dgmc), dgmc_stage_runs_s=dgmc, maen_deg=maen)
        print({k: row[k] for k in ("reconstruct_s", "reconstruct_cpu_s", "dgmc_stage_s", "maen_deg")}, flush=True)
    row["loadavg_1min_before_after"] = [load0, os.getloadavg()[0]]
    path = write_results(a.name, device, {"command": " ".join(sys.argv), "rows": [row]})
    print(path)


if __name__ == "__main__":
    main()
