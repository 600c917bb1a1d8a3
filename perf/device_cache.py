"""Compile gpps's Warp kernel modules for the GPU machine's CUDA here, into a Warp kernel cache to carry there.

The lent GPU machine starts bare every session, and its first launch of each gpps kernel module compiles it with
NVRTC: seconds to a minute a module, paid out of the session's 30 device minutes (a cold DiLiGenT ball took 196 s
in session 27; session 28's test calls spent most of 400 s compiling).  Warp keys its cache by the module's content
hash and the target architecture, and NVRTC needs no GPU, so a module compiled on this machine for sm_90
(``warp.compile_aot_module(module, arch=90, use_ptx=False)``) is the file the H200 would write: byte for byte the
same ``wp_gpps.kernels.dgmc_2bded18.sm90.cubin`` and ``.meta`` (session 28, against a cache the H200 wrote).

This script compiles into ``OUT/<warp version>/<module id>/`` (Warp's own layout):

* every module of :mod:`gpps.kernels` (all of its files imported);
* the least-squares solve, and the per-pixel solver's specialisations for ``--methods`` x ``--brdfs`` x
  ``--robust``: the one-thread solve and
  the neighbour pass, the starts-parallel solve and neighbour pass (CUDA's default cold solve), the lights-parallel
  solve (:mod:`gpps.kernels.solve`), and the material scorer's batched and starts-parallel kernels
  (:mod:`gpps.kernels.solve_batched`), each with CUDA's term cache (:func:`gpps.kernels.solve.term_cache_size`).

A module already in ``OUT`` is skipped (its name carries its content's hash: a changed module gets a new
directory; ``--prune`` removes the gpps module directories outside this run's selection: old versions, and the
models and losses not asked for).  On the GPU machine, before the
first launch::

    mkdir -p "$WARP_CACHE_PATH" && cp -r <carried OUT>/* "$WARP_CACHE_PATH"/

Modules that tests define (e.g. ``tests/test_solvers.py``'s) and Taichi's kernels (Taichi compiles for the GPU it
runs on) still compile there.

Usage:  python perf/device_cache.py --out .kit/cache/warp [--arch 90] [--brdfs all] [--robust none,cauchy]
        [--methods lm] [--part 0/2] [--prune] [--list]
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))


def gpps_modules(methods, brdfs, robusts) -> list:
    """The Warp modules of gpps's kernels, with the solver's specialisations for the given choices built."""
    from warp._src import context

    import gpps.kernels
    from gpps.kernels import solve, solve_batched

    for info in pkgutil.iter_modules(gpps.kernels.__path__):
        importlib.import_module(f"gpps.kernels.{info.name}")
    for brdf in brdfs:  # (least squares: one specialisation whatever the model)
        solve.get_solve_kernels("none", brdf, "none")
    for method in methods:
        for brdf in brdfs:
            for robust in robusts:
                solve.get_solve_kernels(method, brdf, robust)
                solve.get_solve_kernel_lanes(method, brdf, robust)
                solve.get_split_kernels(method, brdf, robust)
                solve.get_split_under_kernels(method, brdf, robust)
                solve_batched.get_batched_kernel(method, brdf, robust)
                solve_batched.get_batched_kernel(method, brdf, robust, lanes=True)
                solve_batched.get_batched_starts_kernels(method, brdf, robust)
    return sorted((m for name, m in context.user_modules.items() if name.startswith("gpps.") and m.kernels),
                  key=lambda m: m.name)


def main(argv=None) -> int:
    from gpps.material import BRDF_NAMES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the cache directory to fill (Warp's layout below it)")
    ap.add_argument("--arch", type=int, default=90, help="CUDA architecture (90: H100 / H200)")
    ap.add_argument("--methods", default="lm", help="nonlinear solvers, comma-separated (lm, dogleg, bfgs)")
    ap.add_argument("--brdfs", default="all", help="reflectance models, comma-separated, or all")
    ap.add_argument("--robust", default="none,cauchy", help="robust losses, comma-separated (none, huber, cauchy)")
    ap.add_argument("--part", default="0/1", help="I/N: compile every N-th module from the I-th (parallel runs)")
    ap.add_argument("--prune", action="store_true",
                    help="remove the gpps module directories outside this run's selection (this tree's modules for "
                         "the given --methods, --brdfs and --robust)")
    ap.add_argument("--list", action="store_true", help="list the modules and whether they are in OUT; compile nothing")
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    wp.init()
    brdfs = list(BRDF_NAMES) if a.brdfs == "all" else [b.strip() for b in a.brdfs.split(",") if b.strip()]
    bad = [b for b in brdfs if b not in BRDF_NAMES]
    if bad:
        raise SystemExit(f"--brdfs: expected names from {list(BRDF_NAMES)}, got {bad}")
    modules = gpps_modules([m for m in a.methods.split(",") if m], brdfs, [r for r in a.robust.split(",") if r])
    i, n = (int(x) for x in a.part.split("/"))
    base = Path(a.out) / wp.config.version
    ids = {m.name: m.get_module_identifier(block_dim=m.options["block_dim"]) for m in modules}
    if a.prune and base.is_dir():
        keep = set(ids.values())
        for d in base.iterdir():
            if d.is_dir() and d.name.startswith("wp_gpps.") and d.name not in keep:
                shutil.rmtree(d)
                print(f"pruned {d.name}")
    done = skipped = 0
    t_all = time.perf_counter()
    for k, m in enumerate(modules):
        d = base / ids[m.name]
        have = any(p.suffix == ".cubin" and f".sm{a.arch}." in p.name for p in d.glob("*")) if d.is_dir() else False
        if a.list:
            print(f"{'have' if have else 'need'}  {ids[m.name]}")
            continue
        if k % n != i or have:
            skipped += have
            continue
        t = time.perf_counter()
        wp.compile_aot_module(m, arch=a.arch, use_ptx=False, module_dir=str(d))
        done += 1
        print(f"{time.perf_counter() - t:6.1f} s  {ids[m.name]}", flush=True)
    if not a.list:
        size = sum(p.stat().st_size for p in base.rglob("*") if p.is_file()) if base.is_dir() else 0
        print(f"{done} compiled, {skipped} already there, {len(modules)} modules; {size / 2**20:.1f} MiB in {base}; "
              f"{time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
