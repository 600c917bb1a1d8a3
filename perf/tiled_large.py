"""A large synthetic capture solved in tiles over a LocalCluster (``gpps.batch.reconstruct_tiled``) against the
untiled solve (``gpps.reconstruct_folder`` with the same config): MAEN of each against the ground truth, their
difference, the largest angle between the two normal maps, flags, and wall times.  Usage::

    python perf/tiled_large.py [--size 4096] [--tile 1024] [--workers 2] [--brdf lambertian] [--integrate]

The capture: the bumps scene (``--scene sphere --slant 45``: a rim of pixels lit by fewer than 3 lights, which
the neighbour pass solves across the tile borders), orthographic, 4 directional lights, 16-bit PNGs with ground truth, solved with the material known (``method="ppn"``, ``known_material``).
Without ``--integrate`` neither run integrates (the depth of the same normals is the same; tests/test_batch.py
checks it on a small capture), which keeps 4096^2 within reach of a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from perf._common import rss_mb, write_results  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--tile", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--brdf", default="lambertian")
    ap.add_argument("--scene", default="bumps", help="bumps (no under-determined pixels at 40 deg) or sphere (a rim of them)")
    ap.add_argument("--slant", type=float, default=40.0)
    ap.add_argument("--integrate", action="store_true")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--name", default=None)
    a = ap.parse_args(argv)

    import distributed

    import gpps
    from gpps import batch
    from gpps.host.metrics import angular_error
    from gpps.io import write_dataset

    with tempfile.TemporaryDirectory(prefix="gpps-tiled-perf-") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        sc = gpps.make_scene(a.scene, a.size, "orthographic", albedo="texture", seed=1)
        lights = gpps.default_lights("directional", 4, slant_deg=a.slant)
        ds = gpps.render_dataset(sc, gpps.Material.default_for(a.brdf), lights, bits=16, seed=1, device=a.device)
        folder = write_dataset(tmp / "capture", ds)
        del ds, sc
        t_render = time.perf_counter() - t
        print(f"rendered {a.size}^2 in {t_render:.1f} s", flush=True)
        cfg = gpps.FolderConfig(method="ppn", known_material=True, integrate=a.integrate)

        t = time.perf_counter()
        ref = gpps.reconstruct_folder(folder, cfg, device=a.device)
        t_untiled = time.perf_counter() - t
        print(f"untiled: {t_untiled:.1f} s, MAEN {ref.report['maen_deg']:.5f}", flush=True)

        cluster = batch.make_cluster(a.workers, device=a.device, dashboard_address=None)
        client = distributed.Client(cluster)
        try:
            t = time.perf_counter()
            rep = batch.reconstruct_tiled(folder, tmp / "tiled", client, tile=a.tile, config=cfg, device=a.device)
            t_tiled = time.perf_counter() - t
        finally:
            client.close()
            cluster.close()
        got = np.load(tmp / "tiled" / "normals.npy")
        m = ref.mask
        diff = angular_error(got, ref.normals, m)[m]
        print(f"tiled: {t_tiled:.1f} s, MAEN {rep['maen_deg']:.5f}", flush=True)
        payload = {
            "scene": a.scene, "slant_deg": a.slant, "size": a.size, "tile": a.tile, "workers": a.workers, "brdf": a.brdf, "images": 4, "integrate": a.integrate,
            "mask_pixels": int(m.sum()), "tiles": rep["tiled"]["tiles"], "halo": rep["tiled"]["halo"],
            "maen_untiled_deg": ref.report["maen_deg"], "maen_tiled_deg": rep["maen_deg"],
            "maen_difference_deg": abs(rep["maen_deg"] - ref.report["maen_deg"]),
            "angle_between_maps_deg": {"max": float(diff.max()), "mean": float(diff.mean())},
            "flagged_pixels": {"untiled": ref.report["flagged_pixels"], "tiled": rep["flagged_pixels"]},
            "seconds": {"render": t_render, "untiled": t_untiled, "tiled": t_tiled,
                        "untiled_solve": ref.report["timings"].get("solve"), "tiled_solve": rep["timings"].get("solve")},
            "rss_mb_client_end": rss_mb(), "cpu_count": os.cpu_count(), "load_average_end": os.getloadavg(),
        }
    path = write_results(a.name or f"tiled_large_{a.size}", a.device, payload)
    print(json.dumps(payload, indent=1), f"\nwrote {path}")


if __name__ == "__main__":
    main()
