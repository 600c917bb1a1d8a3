"""Held-out evaluation on captures rendered by Mitsuba 3 (issues 24 and 25): not gpps's own image model.

Eight fixed scenes (:data:`HELDOUT`: shape, material, texture, seed; seeds 1000+ are never used for training data),
each rendered by :mod:`training/mitsuba_scenes.py` under {3, 12} x {directional, point} lights (perspective
camera, path tracer with interreflections, cast shadows, exposure, shot and read noise, 16-bit unless ``--bits 8``),
cached under ``$GPPS_CACHE_DIR/mitsuba_captures`` (``--root``).  Methods, MAEN (deg) inside the mask against the
pixel-centre ground truth:

* ``folder``: ``gpps.reconstruct_folder`` with the default :class:`gpps.FolderConfig` (RON, what ``gpps reconstruct``
  runs);
* ``ls``: Woodham's least squares (``FolderConfig(solver="none", integrate=False)``: Lambertian least squares per
  pixel; with point lights the lighting at the ground truth's mean depth);
* ``flat``: a plane facing the camera, n = (0, 0, 1) everywhere;
* ``single1`` / ``single3``: ``gpps.reconstruct_single`` (the flow behind ``gpps single``: no lights, no camera, the
  mask given) on the first image / the three images of the 3-light directional capture, images as the files hold
  them; ``*_net`` rows are the network's normals before the cuckoo refinement.

Means by material and light count are printed and written to ``perf/results/heldout_eval_<device>.json`` (only for
the full set of scenes)::

    python perf/heldout_eval.py [--size 128] [--spp 64] [--lights 3,12] [--kinds directional,point]
                                [--methods folder,ls,flat,single] [--scenes bumps,bowl] [--render-only] [--tag T]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/mitsuba_scenes.py
from _common import write_results  # noqa: E402

#: (name, shape, material, alpha, texture, seed)
HELDOUT = (
    ("bumps", "bumps", "roughplastic", 0.15, True, 1000),
    ("bowl", "bowl", "diffuse", 0.2, True, 1001),
    ("ridges", "ridges", "roughplastic", 0.05, False, 1002),
    ("sphere_on_plane", "sphere_on_plane", "roughplastic", 0.1, False, 1003),
    ("spheres", "spheres", "plastic", 0.2, False, 1004),
    ("torus", "torus", "roughplastic", 0.3, True, 1005),
    ("steps", "steps", "diffuse", 0.2, True, 1006),
    ("superquadric", "superquadric", "roughconductor", 0.3, False, 1007),
)
METHODS = ("folder", "ls", "flat", "single")


def _specs(args, scenes=HELDOUT):
    """``(name, CaptureSpec)`` of every scene of ``scenes`` (rows as :data:`HELDOUT`) under ``args``' lights,
    size, samples and bits (``args.scenes``: a subset of the names).  perf/dev_eval.py passes its own scenes."""
    from mitsuba_scenes import CaptureSpec

    for name, shape, material, alpha, texture, seed in scenes:
        if args.scenes and name not in args.scenes:
            continue
        for kind in args.kinds:
            for n in args.lights:
                yield name, CaptureSpec(shape=shape, material=material, alpha=alpha, texture=texture, light_kind=kind, n_lights=n,
                                        size=args.size, spp=args.spp, bits=args.bits, seed=seed)


def _maen(normals, gt, mask) -> dict:
    from gpps.host.metrics import normal_errors

    e = normal_errors(normals, gt, mask)
    return {"maen": e["mean"], "median": e["median"], "under_10deg": e["under_10deg"]}


def _run_folder(folder, method: str, device: str) -> dict:
    import gpps
    from gpps.io import read_capture

    cfg = gpps.FolderConfig() if method == "folder" else gpps.FolderConfig(solver="none", integrate=False)
    t = time.perf_counter()
    res = gpps.reconstruct_folder(folder, cfg, device=device)
    dt = time.perf_counter() - t
    cap = read_capture(folder)
    return {**_maen(res.normals, cap.dataset.normal_gt, cap.dataset.mask), "seconds": dt}


def _run_single(folder, n_images: int, device: str, generations: int, net=None) -> list[dict]:
    import gpps
    from gpps.io import read_capture
    from gpps.pipeline.cuckoo import CuckooConfig

    ds = read_capture(folder, normalise=False).dataset
    cfg = gpps.SingleConfig(cuckoo=CuckooConfig(nests=12, generations=generations), integrate=False)
    t = time.perf_counter()
    res = gpps.reconstruct_single(ds.images[:n_images], ds.mask, config=cfg, device=device, net=net)
    dt = time.perf_counter() - t
    net = res.normals_net_first if n_images == 1 else res.normals_net
    return [{"method": f"single{n_images}_net", **_maen(net, ds.normal_gt, ds.mask), "seconds": res.timings["network"]},
            {"method": f"single{n_images}", **_maen(res.normals, ds.normal_gt, ds.mask), "seconds": dt}]


def _means(rows, key) -> dict:
    out = {}
    for r in rows:
        out.setdefault(key(r), []).append(r["maen"])
    return {"/".join(map(str, k)): {"maen": float(np.mean(v)), "scenes": len(v)} for k, v in sorted(out.items())}


def _table(rows, scenes) -> str:
    cols = sorted({(r["kind"], r["n_lights"], r["method"]) for r in rows}, key=lambda c: (c[2], c[0], c[1]))
    by = {(r["scene"], r["kind"], r["n_lights"], r["method"]): r["maen"] for r in rows}
    head = ["scene", "material"] + [f"{m}:{k[:3]}{n}" for k, n, m in cols]
    lines = [" | ".join(f"{h:>14}" if i > 1 else f"{h:<16}" for i, h in enumerate(head))]
    mats = {s[0]: s[2] for s in HELDOUT}
    for s in scenes:
        vals = [by.get((s, k, n, m)) for k, n, m in cols]
        lines.append(" | ".join([f"{s:<16}", f"{mats[s]:<16}"] + [f"{v:14.2f}" if v is not None else f"{'':>14}" for v in vals]))
    means = []
    for k, n, m in cols:
        v = [by[(s, k, n, m)] for s in scenes if (s, k, n, m) in by]
        means.append(float(np.mean(v)) if v else None)
    lines.append(" | ".join([f"{'mean':<16}", f"{'':<16}"] + [f"{v:14.2f}" if v is not None else f"{'':>14}" for v in means]))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--bits", type=int, default=16, choices=(8, 16))
    ap.add_argument("--lights", default="3,12", help="light counts, comma-separated")
    ap.add_argument("--kinds", default="directional,point")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--scenes", default=None, help=f"a subset of {[s[0] for s in HELDOUT]} (no JSON written)")
    ap.add_argument("--generations", type=int, default=80, help="cuckoo generations of gpps single")
    ap.add_argument("--weights", default=None, help="the single-image network's weights file (default: the shipped one)")
    ap.add_argument("--root", default=None, help="capture cache (default $GPPS_CACHE_DIR/mitsuba_captures)")
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--tag", default=None, help="results name suffix: perf/results/heldout_eval_<tag>_<device>.json "
                    "(a partial run, e.g. --methods flat,single, must not replace the full table)")
    args = ap.parse_args()
    from gpps.nn.model import SingleNet

    net = SingleNet.load(args.weights)
    args.lights = [int(x) for x in args.lights.split(",") if x]
    args.kinds = [x for x in args.kinds.split(",") if x]
    methods = [x for x in args.methods.split(",") if x]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        ap.error(f"--methods: unknown {unknown}; expected some of {list(METHODS)}")
    args.scenes = [x for x in args.scenes.split(",") if x] if args.scenes else None

    import json

    from gpps.io import read_capture
    from mitsuba_scenes import make_capture

    t_all = time.perf_counter()
    captures = []
    for name, spec in _specs(args):
        t = time.perf_counter()
        folder = make_capture(spec, args.root)
        info = json.loads((folder / "scene.json").read_text())
        captures.append((name, spec, folder, info))
        print(f"capture {folder.name}: {time.perf_counter() - t:.1f} s (rendered in {sum(info['timings']['render']):.1f} s, "
              f"{info['mean_render_s']:.2f} s/image)", flush=True)
    t_render = time.perf_counter() - t_all
    if args.render_only:
        return
    rows = []
    for name, spec, folder, info in captures:
        base = {"scene": name, "material": spec.material, "kind": spec.light_kind, "n_lights": spec.n_lights, "capture": folder.name}
        if "flat" in methods:
            ds = read_capture(folder).dataset
            flat = np.zeros_like(ds.normal_gt)
            flat[..., 2] = 1.0
            rows.append({**base, "method": "flat", **_maen(flat, ds.normal_gt, ds.mask), "seconds": 0.0})
        for m in ("ls", "folder"):
            if m in methods:
                rows.append({**base, "method": m, **_run_folder(folder, m, args.device)})
        if "single" in methods and spec.light_kind == "directional" and spec.n_lights == 3:
            for k in (1, 3):
                rows += [{**base, **r} for r in _run_single(folder, k, args.device, args.generations, net)]
        print("  ".join(f"{r['scene']}/{r['kind'][:3]}{r['n_lights']}/{r['method']}: {r['maen']:.2f}" for r in rows
                        if r["capture"] == folder.name), flush=True)
    scenes = [s[0] for s in HELDOUT if not args.scenes or s[0] in args.scenes]
    table = _table(rows, scenes)
    print("\nMAEN (deg); columns method:kind+lights (single*: the 3-light directional capture)\n" + table)
    non_diffuse = [r for r in rows if r["material"] != "diffuse"]
    summary = {
        "by_method_kind_lights": _means(rows, lambda r: (r["method"], r["kind"], r["n_lights"])),
        "by_method_lights": _means(rows, lambda r: (r["method"], r["n_lights"])),
        "by_method_material_lights": _means(rows, lambda r: (r["method"], r["material"], r["n_lights"])),
        "non_diffuse_by_method_lights": _means(non_diffuse, lambda r: (r["method"], r["n_lights"])),
    }
    print("\nmeans by method / lights:")
    for k, v in summary["by_method_lights"].items():
        print(f"  {k:<22} {v['maen']:6.2f}  ({v['scenes']} captures)")
    print("non-diffuse means by method / lights:")
    for k, v in summary["non_diffuse_by_method_lights"].items():
        print(f"  {k:<22} {v['maen']:6.2f}  ({v['scenes']} captures)")
    total = time.perf_counter() - t_all
    print(f"\ntotal {total:.0f} s (captures {t_render:.0f} s)")
    if args.scenes is None:
        payload = {"args": {k: v for k, v in vars(args).items() if k != "root"}, "heldout": [list(s) for s in HELDOUT],
                   "rows": rows, "summary": summary, "table": table, "seconds_total": total, "seconds_captures": t_render,
                   "captures": {c[2].name: {"render_s": c[3]["timings"]["render"], "mitsuba": c[3]["mitsuba"],
                                            "variant": c[3]["variant"], "exposure": c[3]["exposure"]} for c in captures}}
        name = "heldout_eval" + (f"_{args.tag}" if args.tag else "")
        print("wrote", write_results(name, args.device, payload))


if __name__ == "__main__":
    main()
