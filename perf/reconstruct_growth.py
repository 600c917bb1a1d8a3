"""How ``gpps.reconstruct`` time grows with pixels and images (issue 20: cost growth measured, not assumed).

Scene: Gaussian bumps, perspective camera, Cook-Torrance (ks 0.8, roughness 0.2, f0 0.5), directional
lights (a spiral of N), 16-bit, the material unknown (ks and roughness estimated: the default pipeline).
Two sweeps: pixels (128^2 .. 1024^2) at 3 images, and images (3 .. 96) at 256^2.  Each point: one cold
call (compilation included on a fresh cache), then the median of ``--repeat`` warm calls; per-stage
times from ``Reconstruction.timings``; MAEN against the rendered normals.

Writes ``perf/results/reconstruct_growth_<device>.json`` and a PNG plot beside it.

Usage:  python perf/reconstruct_growth.py [--device cpu] [--sizes 128 256 512] [--images 3 12 48 96] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))


import gpps  # noqa: E402
from gpps.io import save_json  # noqa: E402

TRUE = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)


def one(size: int, n: int, device: str, repeat: int) -> dict:
    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", n, layout="ring" if n <= 4 else "spiral")
    img = gpps.render(sc, TRUE, L, bits=16, device=device) / L.intensities[:, None, None, :]
    Lu = gpps.DirectionalLights(L.directions)

    def call():
        t = time.perf_counter()
        rec = gpps.reconstruct(img, sc.mask, Lu, camera=sc.camera, material="cook-torrance", device=device)
        return time.perf_counter() - t, rec

    cold, rec = call()
    warm = [call() for _ in range(repeat)]
    secs = [w[0] for w in warm]
    rec = warm[-1][1] if warm else rec
    return {"size": size, "images": n, "pixels": int(sc.mask.sum()), "cold_s": cold,
            "warm_s": statistics.median(secs) if secs else None, "warm_all_s": secs,
            "stages_s": {k: float(v) for k, v in rec.timings.items()},
            "maen_deg": gpps.normal_errors(rec.normals, sc.normals, sc.mask)["mean"],
            "estimated": rec.estimated}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="*", default=[128, 256, 512, 1024])
    ap.add_argument("--images", type=int, nargs="*", default=[3, 12, 48, 96])
    ap.add_argument("--images-size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    from _common import device_label

    label = device_label(a.device)
    rows = []
    for s in a.sizes:
        rows.append({"sweep": "pixels", **one(s, 3, a.device, a.repeat)})
        print(rows[-1], flush=True)
    for n in a.images:
        rows.append({"sweep": "images", **one(a.images_size, n, a.device, a.repeat)})
        print(rows[-1], flush=True)
    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"reconstruct_growth_{label}.json"
    save_json(out, {"device": a.device, "device_name": label, "scene": "bumps, perspective, cook-torrance, material unknown",
                    "rows": rows})
    print(f"\n{'sweep':7s} {'size':>5s} {'N':>3s} {'pixels':>8s} {'cold s':>8s} {'warm s':>8s} {'MAEN':>7s}  stages (warm)")
    for r in rows:
        st = " ".join(f"{k}={v:.3f}" for k, v in r["stages_s"].items() if k != "total")
        print(f"{r['sweep']:7s} {r['size']:5d} {r['images']:3d} {r['pixels']:8d} {r['cold_s']:8.3f} "
              f"{(r['warm_s'] or float('nan')):8.3f} {r['maen_deg']:7.3f}  {st}")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for sweep, axis, key, xl in (("pixels", ax[0], "pixels", "object pixels (3 images)"),
                                     ("images", ax[1], "images", f"images ({a.images_size}^2)")):
            rs = [r for r in rows if r["sweep"] == sweep and r["warm_s"]]
            if not rs:
                continue
            x = [r[key] for r in rs]
            axis.loglog(x, [r["warm_s"] for r in rs], "o-", label="total (warm)")
            for stage in ("dgmc", "normals", "material", "integration"):
                axis.loglog(x, [max(r["stages_s"].get(stage, 0.0), 1e-6) for r in rs], ".--", label=stage)
            axis.set_xlabel(xl)
            axis.set_ylabel("seconds")
            axis.grid(True, which="both", alpha=0.3)
        ax[0].legend(fontsize=7)
        fig.suptitle(f"gpps.reconstruct on {label}")
        fig.tight_layout()
        fig.savefig(out.with_suffix(".png"), dpi=110)
    except ImportError:
        print("matplotlib not installed: no plot")


if __name__ == "__main__":
    main()
