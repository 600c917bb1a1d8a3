"""DGMC starts on the host (gpps.host.dgmc.dgmc_start) vs the device stage (gpps.pipeline.dgmc): time and agreement.

Scenes: Blinn-Phong bumps (Material.default_for), orthographic, directional lights on a golden-angle spiral
(``default_lights(layout="spiral")``), 16-bit, divided by the intensities; start normals = least squares
(solve_normals, solver="none"); default DGMCConfig.  For each size and light count:

* host: ``dgmc_start`` wall time (median of ``--repeat`` runs, no warm-up needed: numpy/scipy);
* device: ``DeviceDGMC`` built once, then ``upload`` + ``step`` + ``fetch`` (what ``dgmc_start_device`` does
  minus the allocation), median after one warm-up (compile excluded), device-synchronised; ``step`` alone and its
  phases (highlights, regions, geodesic sweeps, curvatures, start search), each synchronised;
* agreement: fraction of equal highlight observations, region IoU, fraction of highlight pixels with the same
  source, and the MAEN (deg) of both starts on the highlight pixels against ground truth.

Usage:  python perf/dgmc_device.py [--device cpu] [--sizes 64 128] [--lights 12 96] [--repeat 3]
        [--out perf/results/dgmc_device_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))

import numpy as np  # noqa: E402

from _common import device_label  # noqa: E402


def _case(size, n_lights, device):
    from gpps.flows.photometric import solve_normals
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    sc = make_scene("bumps", size, "orthographic")
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", n_lights, layout="spiral")
    img = render(sc, mat, L, bits=16, device=device)
    img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
    Lu = DirectionalLights(L.directions)
    ls = solve_normals(img, sc.mask, Lu, camera=sc.camera, material=mat, solver="none", device=device)
    nrm = ls.normals.astype(np.float64)
    ok = sc.mask & (np.abs(np.linalg.norm(nrm, axis=-1) - 1.0) < 1e-3)
    nrm[~ok] = (0.0, 0.0, 1.0)
    return img, Lu, sc, nrm


def _median(fn, repeat, sync):
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), ts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--lights", type=int, nargs="+", default=[12, 96])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--host-repeat", type=int, default=None, help="host runs (default --repeat; 128^2 x 96 takes minutes)")
    ap.add_argument("--append", action="store_true", help="add the rows to those already in --out")
    ap.add_argument("--out", default=str(ROOT / "perf" / "results" / "dgmc_device_cpu.json"))
    args = ap.parse_args()

    from gpps._runtime import warp
    from gpps.host.dgmc import dgmc_start
    from gpps.host.metrics import angular_error
    from gpps.pipeline.dgmc import DeviceDGMC

    wp = warp()
    sync = lambda: wp.synchronize_device(args.device)  # noqa: E731
    rows = []
    for size in args.sizes:
        for n in args.lights:
            img, L, sc, nrm = _case(size, n, args.device)
            h = None

            def host():
                nonlocal h
                h = dgmc_start(img, sc.mask, nrm, lights=L)

            t_host, ts_host = _median(host, args.host_repeat or args.repeat, lambda: None)
            st = DeviceDGMC(img.shape[:3], device=args.device)
            run = lambda: st.run(img, sc.mask, nrm, lights=L)  # noqa: E731
            run()  # warm-up: compile / load the kernels
            t_dev, ts_dev = _median(run, args.repeat, sync)
            st.upload(img, sc.mask, nrm, lights=L)
            t_step, _ = _median(st.step, args.repeat, sync)
            phases = {}
            for name in ("_highlights", "_regions", "_geodesics", "_curvatures", "_select"):
                phases[name.strip("_")], _ = _median(getattr(st, name), args.repeat, sync)
            d = st.fetch()
            hm = h.highlight | d.highlight
            row = {
                "size": size, "lights": n,
                "highlight_pixels_host": int(h.highlight.sum()), "regions_host": int(h.highlights.n_regions),
                "host_s": t_host, "host_runs_s": ts_host,
                "device_run_s": t_dev, "device_runs_s": ts_dev, "device_step_s": t_step,
                "device_phases_s": phases, "geodesic_sweeps": int(st.sweeps),
                "speedup_run": t_host / t_dev,
                "maps_agree": float((h.highlights.maps == d.highlights.maps).mean()),
                "region_iou": float((h.highlight & d.highlight).sum() / max(hm.sum(), 1)),
                "source_agree": float((h.source == d.source).all(-1)[hm].mean()) if hm.any() else 1.0,
                "normals_equal": bool(np.array_equal(h.normals, d.normals)),
                "maen_start_least_squares": float(angular_error(nrm.astype(np.float32), sc.normals, sc.mask)[hm].mean()),
                "maen_start_host": float(angular_error(h.normals, sc.normals, sc.mask)[hm].mean()),
                "maen_start_device": float(angular_error(d.normals, sc.normals, sc.mask)[hm].mean()),
            }
            st.close()
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    commands = ["python perf/dgmc_device.py " + " ".join(sys.argv[1:])]
    if args.append and out.exists():
        old = json.loads(out.read_text())
        rows = old["rows"] + rows
        commands = old["commands"] + commands
    payload = {"device": args.device, "device_name": device_label(args.device), "commands": commands,
               "scene": "bumps, Blinn-Phong, orthographic, spiral directional lights, 16-bit, default DGMCConfig",
               "rows": rows}
    out.write_text(json.dumps(payload, indent=2) + "\n")
    print(out)


if __name__ == "__main__":
    main()
