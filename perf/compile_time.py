"""Time the first load (compile) of each gpps Warp kernel module on a device: `python perf/compile_time.py --device cuda:0`."""

import argparse
import importlib
import time

from _common import ROOT  # noqa: F401  (sets GPPS_CACHE_DIR)

from gpps._runtime import resolve_device, warp

MODULES = ["gpps.kernels.brdf", "gpps.kernels.render", "gpps.kernels.jacobians", "gpps.kernels.solve", "gpps.kernels.uncalibrated"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="auto")
    a = ap.parse_args()
    wp = warp()
    dev = resolve_device(a.device)
    for name in MODULES:
        mod = importlib.import_module(name)
        t = time.perf_counter()
        wp.load_module(mod, device=dev)
        print(f"{name:28s} {time.perf_counter() - t:8.2f} s", flush=True)


if __name__ == "__main__":
    main()
