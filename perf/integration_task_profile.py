"""Device time per Taichi task of a warm 1024^2 stream-integration frame (issue 4).

Runs Taichi's kernel profiler (``TI_KERNEL_PROFILER=1``, CUDA events around every task)
over ``--frames`` warm one-cycle frames of :class:`gpps.pipeline.integration_device.StreamIntegrator`
for each launch form, and prints its per-task table (name, count, mean and total device time):
which phases of the frame cost what, against the counted bytes of
``perf/integration_device_speed.py``.  Profiling adds host work per task, so only the
device times mean anything here.

Usage:  TI_KERNEL_PROFILER=1 python perf/integration_task_profile.py [--size 1024] [--frames 20]
            [--launches persistent:2:256,persistent:2:512,tasks]
The H100 table (perf/results/integration_task_profile_H100.log, at 600c7d4, before the one-pass
right-hand side and the warp sums) shows 13 tasks for the default form, the persistent task of the
small levels ~75 us of them, and 9 tasks with ``persistent:2:512`` (its task ~107 us); the
earlier table (git history, before the fused finish) had the finish at 3 tasks + a serial one.
"""

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
os.environ.setdefault("TI_KERNEL_PROFILER", "1")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--launches", default="persistent,tasks")
    a = ap.parse_args(argv)

    import torch

    from gpps import _taichi
    from gpps.camera import Orthographic
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig
    from integration_speed import surface_normals

    ti = _taichi.init("cuda:0")
    n = a.size
    nA = torch.from_numpy(surface_normals(n, 0.0).astype(np.float32)).cuda()
    nB = torch.from_numpy(surface_normals(n, 0.002).astype(np.float32)).cuda()
    out = torch.zeros((n, n), dtype=torch.float32, device="cuda")
    for launch in a.launches.split(","):
        kind, bps, psize = (launch.split(":") + ["2", "256"])[:3]  # persistent:<blocks per SM>:<size>
        cfg = StreamIntegratorConfig(launch=kind, blocks_per_sm=int(bps), persistent_size=int(psize))
        si = StreamIntegrator(np.ones((n, n), bool), Orthographic(1.0 / n), cfg)
        si.step(nA, out, iterations=1)  # compile, check
        si.step(nA, out, iterations=12)
        ti.sync()
        ti.profiler.clear_kernel_profiler_info()
        for k in range(a.frames):
            si.step(nB if k % 2 == 0 else nA, out, iterations=1)
        ti.sync()
        print(f"== launch {launch} ({si.launch}), {n}x{n}, {a.frames} warm one-cycle frames; "
              f"levels {[f'{h}x{w}' for (_, h, w) in si.levels]}", flush=True)
        ti.profiler.print_kernel_profiler_info("count")
        print(f"total device time per frame: {ti.profiler.get_kernel_profiler_total_time() * 1e3 / a.frames:.3f} ms",
              flush=True)
        si.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
