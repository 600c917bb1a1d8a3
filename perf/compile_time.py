"""Time the first load (compile) of each gpps Warp kernel module on a device: `python perf/compile_time.py --device cuda:0`.

Besides the plain kernel modules, loads the solver modules specialised for
``SPECIALISED`` (see :func:`gpps.kernels.solve.get_solve_kernels`; each holds
the solve and the under-determined kernel of one solver / reflectance model /
robust loss) and, with ``--generic``, the generic build that switches on all of
them at run time.  Prints the load time and the size of the generated source
(.cpp for CPU, .cu for CUDA) in the kernel cache; for a cold-cache measurement
point ``GPPS_CACHE_DIR`` at an empty folder.  ``--only`` restricts the run to
the modules whose name contains one of the given strings; ``--spec`` loads the
given ``solver:brdf:robust`` specialisations instead of ``SPECIALISED``.
"""

import argparse
import glob
import importlib
import os
import time

from _common import ROOT  # noqa: F401  (sets GPPS_CACHE_DIR)

from gpps._runtime import resolve_device, warp

MODULES = ["gpps.kernels.brdf", "gpps.kernels.render", "gpps.kernels.jacobians", "gpps.kernels.uncalibrated"]

# (solver, brdf, robust) of the specialised solver kernels used in the GPU measurements
SPECIALISED = [
    ("lm", "blinn-phong", "none"),
    ("lm", "cook-torrance", "none"),
    ("lm", "lambertian", "none"),
    ("lm", "plastic", "none"),
    ("dogleg", "blinn-phong", "none"),
    ("bfgs", "blinn-phong", "none"),
]


def _source_size(wp, name: str, dev) -> int | None:
    ext = "cu" if str(dev).startswith("cuda") else "cpp"
    files = glob.glob(os.path.join(wp.config.kernel_cache_dir, f"wp_{glob.escape(name)}_*", f"*.{ext}"))
    return os.path.getsize(max(files, key=os.path.getmtime)) if files else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="auto")
    ap.add_argument("--generic", action="store_true", help="also load the generic (run-time switch) solver build")
    ap.add_argument("--only", nargs="*", default=None, help="load only modules whose name contains one of these")
    ap.add_argument("--spec", nargs="*", default=None, metavar="SOLVER:BRDF:ROBUST",
                    help="solver specialisations to load instead of SPECIALISED (e.g. lm:blinn-phong:cauchy, the "
                         "many-image build)")
    a = ap.parse_args()
    wp = warp()
    dev = resolve_device(a.device)
    from gpps.kernels import solve as sk

    todo = [(name, importlib.import_module(name)) for name in MODULES]
    specs = [tuple(x.split(":")) for x in a.spec] if a.spec else list(SPECIALISED)
    specs += [(None, None, None)] if a.generic else []
    for spec in specs:
        todo.append((sk.module_name(*spec), sk.get_solve_kernels(*spec)[0].module))
    if a.only:
        todo = [(n, m) for n, m in todo if any(s in n for s in a.only)]
    print(f"device {dev}, cache {wp.config.kernel_cache_dir}", flush=True)
    for name, mod in todo:
        t = time.perf_counter()
        wp.load_module(mod, device=dev)
        dt = time.perf_counter() - t
        size = _source_size(wp, name, dev)
        print(f"{name:48s} {dt:8.2f} s  {'-' if size is None else size:>9} B", flush=True)


if __name__ == "__main__":
    main()
