"""CPU compile time of one solve specialisation's Warp module with and without the material scorer's batched kernel
in it, and of the batched kernel in a module of its own (the choice of
:func:`gpps.kernels.solve.batched_in_solve_module`).  Each layout compiles in a fresh process with an empty kernel
cache.  ``python perf/solve_module_layout.py [--brdfs plastic conductor] [--cache 128]``: one JSON object on stdout,
seconds per layout and model."""
import argparse
import json
import subprocess
import sys

CHILD = r'''
import sys, tempfile, time
import warp as wp
wp.config.kernel_cache_dir = tempfile.mkdtemp()
wp.config.quiet = True
wp.init()
import gpps.kernels.solve_kernels as sk
import gpps.kernels.solve_batched as sb
from gpps.kernels.solve_methods import solver_funcs
layout, brdf, cache = sys.argv[1], sys.argv[2], int(sys.argv[3])
name = "layout_probe_" + layout.replace("+", "_and_")
module = wp.get_module(name)
funcs = solver_funcs("lm", brdf, "cauchy", module, "__" + name, cache=cache)
if layout in ("solve", "solve+batched"):
    sk.solve_kernel_for("lm", funcs.solve_pixel, module, "__" + name)
    sk.underdetermined_kernel_for(funcs.solve_pixel, funcs.held_dark_refit, module, "__" + name)
    sk.smooth_kernel_for(funcs.run_method, module, "__" + name)
if layout in ("batched", "solve+batched"):
    sb.batched_kernel_for("cauchy", funcs.solve_pixel, module, "__" + name)
t = time.perf_counter()
wp.load_module(module, device="cpu")
print(time.perf_counter() - t)
'''


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--brdfs", nargs="+", default=["plastic", "conductor", "blinn-phong"])
    ap.add_argument("--cache", type=int, default=128)
    a = ap.parse_args()
    out = {"method": "lm", "robust": "cauchy", "cache": a.cache, "seconds": {}}
    for brdf in a.brdfs:
        row = {}
        for layout in ("solve", "batched", "solve+batched"):
            r = subprocess.run([sys.executable, "-c", CHILD, layout, brdf, str(a.cache)], capture_output=True,
                               text=True, check=True)
            row[layout] = round(float(r.stdout.strip().splitlines()[-1]), 2)
        out["seconds"][brdf] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
