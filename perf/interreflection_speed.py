"""Time of the interreflection gathers (gpps.pipeline.interreflection.Interreflections): the diffuse gather of the
observed radiance (``step``, what ``interreflections="subtract"`` runs) and the one bounce under the reflectance
model at both ends (``gather_model``, session 34), on a synthetic perspective surface of ``--size``^2 pixels under
``--lights`` directional lights.

Median of ``--repeat`` device-synchronised calls after one warm-up (each call uploads the surface and fetches the
result: the stage's whole cost as the flow pays it).  Counted work: ``R`` receivers (mask pixels) x ``S`` sources
form factors (each a march over the depth map, up to the pair's distance in ``step_px`` steps), then ``R x S x 3N``
multiply-adds (diffuse) or ``R x S x N`` pairs of reflectance evaluations (model).  Printed: the times, the pair
rates and the gathered light's share of the images (a check that something is gathered).

    python perf/interreflection_speed.py [--device cpu|cuda:0] [--size 128] [--lights 12] [--repeat 3]
        [--material conductor] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> None:
    import warp as wp

    import gpps
    from gpps.pipeline.interreflection import Interreflections
    from gpps.pipeline.render import Renderer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--material", default="conductor")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    sc = gpps.make_scene("bumps", a.size, "perspective")
    L = gpps.default_lights("directional", a.lights, layout="spiral")
    lights = gpps.DirectionalLights(L.directions)
    mat = gpps.Material(a.material) if a.material != "conductor" else gpps.Material("conductor", roughness=0.3)
    m, depth, nrm = sc.mask, sc.depth.astype(np.float32), sc.normals.astype(np.float32)
    albedo = np.full(m.shape + (3,), 0.6, np.float32)
    with Renderer(m.shape, sc.camera, lights, mat, device=a.device) as rd:
        images = rd.run(depth, m, albedo, nrm)
    n, h, w = images.shape[:3]

    def sync():
        wp.synchronize_device(a.device)

    out = {"device": a.device, "size": a.size, "lights": a.lights, "material": a.material}
    with Interreflections((n, h, w), sc.camera, device=a.device) as st:
        def diffuse():
            st.upload(depth, m, nrm, images)
            st.step()
            return st.fetch()

        def model():
            st.upload(depth, m, nrm, np.zeros((n, h, w), np.float32))
            return st.gather_model(albedo, mat, lights)

        for name, fn in (("diffuse", diffuse), ("model", model)):
            res = fn()  # (warm-up: compiles)
            sync()
            ts = []
            for _ in range(a.repeat):
                t = time.perf_counter()
                res = fn()
                sync()
                ts.append(time.perf_counter() - t)
            R, S = int(m.sum()), st.sources
            med = statistics.median(ts)
            pairs = R * S * (3 * n if name == "diffuse" else n)
            share = float((albedo[None] * res if name == "diffuse" else res)[:, m].sum() / images[:, m].sum())
            out[name] = {"median_s": med, "times_s": ts, "receivers": R, "sources": S, "form_factors": R * S,
                         "pairs": pairs, "pairs_per_s": pairs / med, "share": share}
            print(f"{name}: {med * 1e3:.1f} ms median ({a.device}), R={R} S={S} N={n}, "
                  f"{pairs / med / 1e9:.2f} G {'multiply-adds' if name == 'diffuse' else 'model pairs'}/s, "
                  f"gathered share {share:.4f}", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
