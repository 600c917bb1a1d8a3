"""Cook-Torrance against plastic on captures rendered by Mitsuba 3 (issue 25, Build line 2): an independent renderer.

A few Mitsuba ``roughplastic`` (GGX, index 1.49) and ``plastic`` (smooth coating, index 1.5: its highlight is a
delta, so only the diffuse term's Fresnel loss shows) scenes of :mod:`training/mitsuba_scenes.py`, seeds
:data:`SCENES` (not the held-out 1000-1007), directional lights (3 and 12), perspective camera, 16-bit, noise and
interreflections as the module renders them.  Each capture is reconstructed by ``gpps.reconstruct_folder`` (RON,
the material estimated: ks and roughness for both models, f0 at the model's default: Cook-Torrance's Schlick 0.5,
plastic's 0.04, i.e. ior 1.5) once per model, without integration.  Per capture and model:

* ``maen``: mean angular error of the normals in the mask (deg) against the pixel-centre ground truth;
* ``energy``: RON's final trimmed material energy on its sample pixels (what the material fit minimises);
* ``rms_residual``: RMS over the mask of the per-pixel residual of one plain (non-robust) LM solve with the
  fitted material: the quantity a choice of the model by its residual would compare;
* the estimated ks and roughness, and the seconds of the reconstruction.

``--distribution beckmann`` renders the roughplastic scenes with Mitsuba's Beckmann distribution instead of GGX
(the lobe shape of gpps's Cook-Torrance and plastic; captures cached in their own folder)::

    python perf/plastic_vs_ct.py [--size 96] [--spp 32] [--lights 3,12] [--distribution ggx|beckmann]

Writes ``perf/results/plastic_vs_ct_cpu.json`` (``plastic_vs_ct_beckmann_cpu.json`` for that distribution; other
devices: their name) unless ``--scenes`` picks a subset.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/mitsuba_scenes.py
from _common import RESULTS, device_label  # noqa: E402

#: (name, shape, material, alpha, texture, seed): seeds outside the held-out 1000-1007
SCENES = (
    ("sphere_on_plane", "sphere_on_plane", "roughplastic", 0.1, False, 2501),
    ("bumps", "bumps", "roughplastic", 0.2, True, 2502),
    ("superquadric", "superquadric", "roughplastic", 0.15, False, 2503),
    ("spheres", "spheres", "plastic", 0.2, False, 2504),
)
MODELS = ("cook-torrance", "plastic")


def _captures(args):
    import mitsuba_scenes as ms

    root = Path(args.root) if args.root else ms.default_root()
    if args.distribution != "ggx":
        root = root / f"distribution_{args.distribution}"
        ggx_bsdf = ms._bsdf

        def bsdf(spec, rng):  # the same scene with the other microfacet distribution
            d = ggx_bsdf(spec, rng)
            if d.get("distribution") == "ggx":
                d = {**d, "distribution": args.distribution}
            return d

        ms._bsdf = bsdf
    for name, shape, material, alpha, texture, seed in SCENES:
        if args.scenes and name not in args.scenes:
            continue
        for n in args.lights:
            spec = ms.CaptureSpec(shape=shape, material=material, alpha=alpha, texture=texture, light_kind="directional",
                                  n_lights=n, size=args.size, spp=args.spp, seed=seed)
            t = time.perf_counter()
            folder = ms.make_capture(spec, root)
            yield name, spec, folder, time.perf_counter() - t


def _fit(folder, model: str, device: str) -> dict:
    import gpps
    from gpps.flows.photometric import solve_normals
    from gpps.host.metrics import normal_errors
    from gpps.io import read_capture
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    t = time.perf_counter()
    res = gpps.reconstruct_folder(folder, gpps.FolderConfig(brdf=model, integrate=False), device=device)
    dt = time.perf_counter() - t
    ds = read_capture(folder).dataset
    mat = Material.from_dict(res.report["material"])
    plain = solve_normals(ds.images, ds.mask, DirectionalLights(ds.light_directions), camera=res.camera, material=mat,
                          solver="lm", robust="none", irls_rounds=0, device=device)
    r = plain.residual[ds.mask]
    return {"model": model, "maen": normal_errors(res.normals, ds.normal_gt, ds.mask)["mean"],
            "energy": float(res.report["energy_per_round"][-1]), "rms_residual": float(np.sqrt(np.mean(r * r))),
            "maen_plain": normal_errors(plain.normals, ds.normal_gt, ds.mask)["mean"],
            "ks": mat.ks, "roughness": mat.roughness, "f0": mat.f0, "rounds": res.report["rounds"], "seconds": dt}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--lights", default="3,12")
    ap.add_argument("--distribution", default="ggx", choices=("ggx", "beckmann"))
    ap.add_argument("--scenes", default=None, help=f"a subset of {[s[0] for s in SCENES]} (no JSON written)")
    ap.add_argument("--root", default=None, help="capture cache (default $GPPS_CACHE_DIR/mitsuba_captures)")
    args = ap.parse_args()
    args.lights = [int(x) for x in args.lights.split(",") if x]
    args.scenes = [x for x in args.scenes.split(",") if x] if args.scenes else None
    t_all = time.perf_counter()
    rows = []
    for name, spec, folder, t_cap in _captures(args):
        info = json.loads((folder / "scene.json").read_text())
        base = {"scene": name, "material": spec.material, "alpha": spec.alpha if spec.material == "roughplastic" else None,
                "n_lights": spec.n_lights, "capture": folder.name, "capture_s": t_cap, "mitsuba": info["mitsuba"]}
        for model in MODELS:
            rows.append({**base, **_fit(folder, model, args.device)})
            r = rows[-1]
            print(f"{name:<16} {spec.material:<13} N={spec.n_lights:<3} {model:<14} MAEN {r['maen']:6.2f}  energy {r['energy']:.3e}  "
                  f"rms {r['rms_residual']:.4f}  ks {r['ks']:.3f}  m {r['roughness']:.3f}  {r['seconds']:.1f} s", flush=True)
    by = {(r["scene"], r["n_lights"], r["model"]): r for r in rows}
    lines = [f"{'scene':<16} {'material':<13} {'N':>3} | {'MAEN ct':>8} {'MAEN pl':>8} | {'rms ct':>8} {'rms pl':>8} | "
             f"{'energy ct':>10} {'energy pl':>10} | lower residual"]
    for name, _, material, *_ in SCENES:
        for n in args.lights:
            if (name, n, "plastic") not in by:
                continue
            ct, pl = by[(name, n, "cook-torrance")], by[(name, n, "plastic")]
            lines.append(f"{name:<16} {material:<13} {n:>3} | {ct['maen']:8.2f} {pl['maen']:8.2f} | {ct['rms_residual']:8.4f} "
                         f"{pl['rms_residual']:8.4f} | {ct['energy']:10.3e} {pl['energy']:10.3e} | "
                         f"{'plastic' if pl['rms_residual'] < ct['rms_residual'] else 'cook-torrance'}")
    table = "\n".join(lines)
    means = {m: {"maen": float(np.mean([r["maen"] for r in rows if r["model"] == m])),
                 "rms_residual": float(np.mean([r["rms_residual"] for r in rows if r["model"] == m]))} for m in MODELS}
    total = time.perf_counter() - t_all
    print("\n" + table + "\n\nmeans: " + json.dumps(means) + f"\ntotal {total:.0f} s")
    name = "plastic_vs_ct" + ("" if args.distribution == "ggx" else f"_{args.distribution}")
    if args.scenes is not None:
        return  # a subset: nothing written
    payload = {"device": args.device, "device_name": device_label(args.device),
               "args": {k: v for k, v in vars(args).items() if k != "root"}, "scenes": [list(s) for s in SCENES],
               "rows": rows, "means": means, "table": table, "seconds_total": total}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}_{'cpu' if args.device == 'cpu' else device_label(args.device)}.json"
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
