"""Where a warm 1024^2 stream-integration frame spends its time on the host side (issue 4).

Times, median of device-synchronised repeats after warm-up: an empty Taichi
kernel on fields; the same with two ``ti.types.ndarray()`` arguments bound to
torch CUDA tensors and to Taichi ndarrays; the one-launch frame kernel called
directly; and ``StreamIntegrator.integrate`` (which adds argument checks).

Usage:  python perf/integration_launch_overhead.py [--device cuda:0] [--size 1024]
Writes perf/results/integration_launch_overhead_<device>.json.
"""


import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
sys.path.insert(0, str(ROOT / "perf"))

from _fused_variants import profiling_kernels  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=50)
    a = ap.parse_args(argv)

    from gpps import _taichi
    from gpps.camera import Orthographic
    from gpps.pipeline.integration_device import StreamIntegrator

    ti = _taichi.init(a.device)
    cuda = a.device.startswith("cuda")
    n = a.size
    import torch

    tdev = "cuda" if cuda else "cpu"
    nrm = torch.zeros((n, n, 3), dtype=torch.float32, device=tdev)
    nrm[..., 2] = 1
    out = torch.zeros((n, n), dtype=torch.float32, device=tdev)
    nd_n = ti.ndarray(ti.f32, (n, n, 3))
    nd_o = ti.ndarray(ti.f32, (n, n))
    si = StreamIntegrator(np.ones((n, n), bool), Orthographic(1.0 / n), device=a.device)
    K = {**si._K, **profiling_kernels(si._K)}  # with vcycle_only, noop
    fld = si._F["sc"]

    @ti.kernel
    def noop_nd(x: ti.types.ndarray(), y: ti.types.ndarray()):
        for i in range(1):
            fld[6] += 0

    def med(fn, inner=10):
        fn()
        ti.sync()
        ts = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            ti.sync()
            ts.append((time.perf_counter() - t0) / inner)
        return 1e6 * statistics.median(ts)

    from gpps._taichi import DirectLaunch

    frame = K["frame"](1)
    dnoop, dframe = DirectLaunch(noop_nd), DirectLaunch(frame)
    args = (*si._cam, si.config.min_nz, 0.0)
    res = {
        "noop_fields_us": med(K["noop"]),
        "noop_two_torch_ndarrays_us": med(lambda: noop_nd(nrm, out)),
        "noop_two_taichi_ndarrays_us": med(lambda: noop_nd(nd_n, nd_o)),
        "frame1_kernel_torch_args_us": med(lambda: frame(nrm, out, *si._cam, si.config.min_nz, 0.0)),
        "frame1_kernel_taichi_ndarray_args_us": med(lambda: frame(nd_n, nd_o, *si._cam, si.config.min_nz, 0.0)),
        "noop_two_torch_ndarrays_direct_us": med(lambda: dnoop(nrm, out)),
        "noop_two_taichi_ndarrays_direct_us": med(lambda: dnoop(nd_n, nd_o)),
        "frame1_kernel_torch_args_direct_us": med(lambda: dframe(nrm, out, *args)),
        "frame1_kernel_taichi_ndarray_args_direct_us": med(lambda: dframe(nd_n, nd_o, *args)),
        "frame1_isolated_torch_plain_us": med(lambda: frame(nrm, out, *args), 1),
        "frame1_isolated_torch_direct_us": med(lambda: dframe(nrm, out, *args), 1),
        "frame1_isolated_taichi_ndarray_plain_us": med(lambda: frame(nd_n, nd_o, *args), 1),
        "frame1_isolated_taichi_ndarray_direct_us": med(lambda: dframe(nd_n, nd_o, *args), 1),
        "integrate_1_iteration_us": med(lambda: si.step(nrm, out, iterations=1)),
        "vcycle_only_us": med(K["vcycle_only"]),
    }
    for k, v in res.items():
        print(f"{k:40s} {v:8.1f}")
    from gpps.io import save_json

    dev_name = torch.cuda.get_device_name(0) if cuda else "cpu"
    path = ROOT / "perf" / "results" / f"integration_launch_overhead_{a.device.replace(':', '')}.json"
    save_json(path, {"device": a.device, "device_name": dev_name, "size": n, "repeat": a.repeat, **res})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
