"""Cast-shadow march (gpps.pipeline.shadows.CastShadows): time of one ``step`` by image size and light count.

Scene (tests/shadow_reference.py): a hemisphere of radius 0.3 S on a plane filling the S x S image (all pixels
in the mask), seen by a 12-degree pinhole (f = 4.75 S pixels, the plane at 4.75 S units: a 1-unit pixel on
the plane) or the orthographic camera; N directional lights on a golden-angle spiral (slants 15-60 degrees from
the view axis: elevations 30-75) or N point lights at the same directions 3 S units from the hemisphere's centre.
The depth is uploaded once; each timed call is ``step()`` (the min-depth reduction and the march, N x S^2
rays), device-synchronised, median after warm-up (compile excluded; reported apart).  Also the fraction of
shadowed (light, pixel) pairs.

Usage:  python perf/shadows.py [--device cpu] [--sizes 256 1024] [--lights 3 96] [--camera perspective]
        [--light-kind directional] [--repeat 5] [--out perf/results/shadows_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
sys.path.insert(0, str(ROOT / "tests"))  # tests/shadow_reference.py: the analytic scenes

import numpy as np  # noqa: E402

from _common import device_label, timeit  # noqa: E402


def _case(size, n_lights, camera, light_kind):
    from shadow_reference import hemisphere_scene, perspective

    from gpps.camera import Orthographic
    from gpps.lights import DirectionalLights, PointLights, spiral_directions

    dp = 4.75 * size
    cam = perspective(dp, (size, size)) if camera == "perspective" else Orthographic(1.0)
    sc = hemisphere_scene(cam, shape=(size, size), plane_depth=dp, radius=0.3 * size)
    dirs = spiral_directions(n_lights, 15.0, 60.0)
    if light_kind == "directional":
        lights = DirectionalLights(dirs)
    else:
        lights = PointLights(np.array([0.0, 0.0, -dp]) + 3.0 * size * dirs)
    return sc, lights


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--lights", type=int, nargs="+", default=[3, 96])
    ap.add_argument("--camera", choices=["perspective", "orthographic"], default="perspective")
    ap.add_argument("--light-kind", choices=["directional", "point"], default="directional")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)

    from gpps._runtime import resolve_device, warp
    from gpps.pipeline.shadows import CastShadows

    wp = warp()
    device = resolve_device(a.device)
    rows = []
    for size in a.sizes:
        for n in a.lights:
            sc, lights = _case(size, n, a.camera, a.light_kind)
            st = CastShadows((n, size, size), sc.camera, lights, device=device)
            t0 = time.perf_counter()
            st.upload(sc.depth, sc.mask)
            st.step()
            wp.synchronize_device(device)
            first = time.perf_counter() - t0
            t = timeit(st.step, lambda: wp.synchronize_device(device), warmup=1, repeat=a.repeat)
            vis = st.fetch()
            st.close()
            row = {"size": size, "lights": n, "camera": a.camera, "light_kind": a.light_kind,
                   "first_call_s": first, "step_median_s": t["median_s"], "step_iqr_s": t["iqr_s"],
                   "runs": t["runs"], "rays_per_s": n * size * size / t["median_s"],
                   "shadowed_fraction": float(1.0 - vis.mean())}
            rows.append(row)
            print(f"{size}^2 x {n:3d} {a.light_kind} {a.camera}: step {1e3 * t['median_s']:.2f} ms "
                  f"(first call {first:.2f} s), {row['rays_per_s'] / 1e6:.1f} M rays/s, "
                  f"shadowed {100 * row['shadowed_fraction']:.1f} %", flush=True)
    payload = {"device": device, "device_name": device_label(device), "rows": rows}
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(payload, indent=2) + "\n")


if __name__ == "__main__":
    main()
