"""Development evaluation of issue 25 on captures rendered by Mitsuba 3, and DiLiGenT with 10 images.

Issue 25 asks to tune on our own physically based renders (concavities, parts that shadow each other,
interreflections, dielectric and metallic materials, 8- and 16-bit noise, 3 to 96 lights) and to keep DiLiGenT
for the final check.  Its Done-when: "Your renders: a table by material and light count, beside least squares and
beside today's pipeline; non-diffuse 3-light mean <= 2.5 deg and 12-light <= 1.5 deg", and DiLiGenT ball and bear
"with the 10-image subset (images 1, 10, 20, ..., 90) beside least squares on the same images".

**Development set** (:data:`DEV`): scenes of every shape and material :mod:`training/mitsuba_scenes.py` offers,
seeds 3000+ (the held-out set of perf/heldout_eval.py uses 1000-1007, never used here), each rendered under
{3, 12} x {directional, point} lights (perspective camera, path tracer with interreflections, cast shadows,
exposure, shot and read noise, 16-bit unless ``--bits 8``), cached under ``$GPPS_CACHE_DIR/mitsuba_captures``
(``--root``; a cached capture is reused when its spec matches).  Methods, MAEN (deg) inside the mask against the
pixel-centre ground truth (the machinery of perf/heldout_eval.py):

* ``ls``: Woodham's least squares (``FolderConfig(solver="none", integrate=False)``; with point lights the lighting
  at the ground truth's mean depth);
* ``pipeline``: ``gpps.reconstruct_folder`` with the default :class:`gpps.FolderConfig` (what ``gpps reconstruct``
  runs today).  The captures carry no ``material.json`` (the renderer's BSDFs are not gpps models), so the model is
  the folder flow's default, Blinn-Phong, with ks and shininess estimated by RON: as perf/heldout_eval.py's
  ``folder``;
* ``pipeline_plastic``: the same with ``FolderConfig(brdf="plastic")`` (the dielectric-coating model; RON estimates
  its ks and roughness): the folder flow takes the model name, nothing else changes;
* ``pipeline_compare``: the pipeline choosing between its Blinn-Phong and ``plastic`` by residual in the first
  material fit (``FolderConfig(models=("plastic",))``, ``gpps reconstruct --compare-models plastic``);
* ``pipeline_refine``: ``pipeline`` with the depth refinement after RON's rounds (``FolderConfig(refine=True)``,
  ``gpps reconstruct --refine``: :class:`gpps.pipeline.depth_refine.DepthRefiner`); ``pipeline_compare_refine``:
  ``pipeline_compare`` with it;
* ``pipeline_shadows`` (12 lights only): ``pipeline`` with RON's cast-shadow pass on
  (``FolderConfig(cast_shadows=True)``).  With 3 lights RON runs no pass under its default ``shadow_few="keep"``
  (gpps/flows/ron.py: a pixel losing one of 3 observations keeps them all), so it is not rerun there.

The results in perf/results/dev_eval_cpu.* were measured while the pass was on by default (1ae2818): their
``pipeline`` column is the pass on, and ``pipeline_noshadow`` (the pass off through a patched RONConfig) is today's
default ``pipeline``.

**DiLiGenT 10-image subset**: images 1, 10, 20, ..., 90 as the issue numbers them (1-based file names 001.png,
010.png, 020.png, ..., 090.png; 0-based indices 0, 9, 19, ..., 89: :data:`DILIGENT_SUBSET`) of
``../shared/data/diligent/{ball,bear}`` copied into a temporary folder with the matching rows of the light files,
``K.txt``, ``mask.png`` and ``normal_gt.npy``; ``ls`` and ``pipeline`` as above (10 images > MANY_IMAGES: the
pipeline's Cauchy loss, shadow threshold and 4 starts).  The 96-image numbers are measured elsewhere.

Output: per-capture rows, a table of mean MAEN by material x light count x method, the non-diffuse means for 3 and
12 lights (the issue's targets), the DiLiGenT rows; printed and written to perf/results/dev_eval_cpu.json and
.md (``dev_eval_<GPU name>`` on CUDA; only for the full set of scenes)::

    python perf/dev_eval.py [--device cpu] [--size 128] [--spp 64] [--bits 16] [--lights 3,12]
                            [--kinds directional,point] [--methods ls,pipeline,pipeline_plastic,pipeline_shadows]
                            [--scenes bumps_plastic,...] [--no-diligent] [--render-only]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/mitsuba_scenes.py
from _common import RESULTS, device_label, diligent_subset  # noqa: E402
from heldout_eval import _maen  # noqa: E402  (the one MAEN summary of the Mitsuba evaluations)
from heldout_eval import _specs as heldout_specs  # noqa: E402

#: (name, shape, material, alpha, texture, seed); seeds 3000+ (heldout_eval.HELDOUT: 1000-1007)
DEV = (
    ("bumps_plastic", "bumps", "plastic", 0.2, False, 3000),
    ("bowl_roughplastic", "bowl", "roughplastic", 0.1, True, 3001),
    ("ridges_roughconductor", "ridges", "roughconductor", 0.2, False, 3002),
    ("sphere_on_plane_diffuse", "sphere_on_plane", "diffuse", 0.2, True, 3003),
    ("spheres_roughplastic", "spheres", "roughplastic", 0.3, True, 3004),
    ("torus_plastic", "torus", "plastic", 0.2, True, 3005),
    ("steps_roughplastic", "steps", "roughplastic", 0.15, False, 3006),
    ("superquadric_roughconductor", "superquadric", "roughconductor", 0.35, False, 3007),
    ("ridges_diffuse", "ridges", "diffuse", 0.2, False, 3008),
    ("superquadric_plastic", "superquadric", "plastic", 0.2, False, 3009),
)
METHODS = ("ls", "pipeline", "pipeline_plastic", "pipeline_compare", "pipeline_shadows", "pipeline_refine",
           "pipeline_compare_refine")
#: the issue's "images 1, 10, 20, ..., 90" (1-based) as 0-based indices into filenames.txt
DILIGENT_SUBSET = (0, 9, 19, 29, 39, 49, 59, 69, 79, 89)
DILIGENT = Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent"
#: issue 25's targets: mean MAEN (deg) of the non-diffuse captures
TARGETS = {3: 2.5, 12: 1.5}


def _specs(args):
    return heldout_specs(args, DEV)


def _config(method: str):
    import gpps

    if method == "ls":
        return gpps.FolderConfig(solver="none", integrate=False)
    if method == "pipeline_plastic":
        return gpps.FolderConfig(brdf="plastic")
    if method == "pipeline_shadows":
        return gpps.FolderConfig(cast_shadows=True)
    if method == "pipeline_compare":
        return gpps.FolderConfig(models=("plastic",))
    if method == "pipeline_refine":
        return gpps.FolderConfig(refine=True)
    if method == "pipeline_compare_refine":
        return gpps.FolderConfig(models=("plastic",), refine=True)
    return gpps.FolderConfig()


def _shadow_summary(report: dict):
    """Observations RON's cast-shadow passes dropped, summed over the passes (None: no pass ran)."""
    passes = report.get("cast_shadows")
    if not passes:
        return None
    return {"passes": len(passes), "dropped": int(sum(p.get("dropped", 0) for p in passes))}


def _run(folder, method: str, device: str) -> dict:
    """One method on one capture folder: MAEN against the folder's normal_gt.npy, seconds, the material found."""
    import gpps
    from gpps.io import read_capture

    cfg = _config(method)
    t = time.perf_counter()
    res = gpps.reconstruct_folder(folder, cfg, device=device)
    dt = time.perf_counter() - t
    cap = read_capture(folder)
    out = {**_maen(res.normals, cap.dataset.normal_gt, cap.dataset.mask), "seconds": dt, "images": int(cap.dataset.images.shape[0])}
    rep = res.report
    if method != "ls":
        mat = rep.get("material", {})
        out["material_model"] = {k: mat[k] for k in ("brdf", "ks", "shininess", "roughness", "f0") if k in mat}
        if "refinement" in rep:
            ri = rep["refinement"]
            out["refinement"] = {"accepted": ri["accepted"], "rejected": ri["rejected"], "sigma": ri["sigma"],
                                 "energy_start": ri["start_energy"], "energy_end": ri["energy"][-1]}
        if "model_energies" in rep:
            out["model_energies"] = rep["model_energies"]
        out["rounds"] = rep.get("rounds")
        out["cast_shadows"] = _shadow_summary(rep)
    return out


def _means(rows, key) -> dict:
    out = {}
    for r in rows:
        out.setdefault(key(r), []).append(r["maen"])
    return {"/".join(map(str, k)): {"maen": float(np.mean(v)), "captures": len(v)} for k, v in sorted(out.items())}


def _fmt(v) -> str:
    return f"{v:.2f}" if v is not None else ""


def _md_table(head, body) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in body]
    return "\n".join(lines)


def _capture_table(rows, methods) -> str:
    """Per scene and lights: MAEN of each method (markdown)."""
    by = {(r["scene"], r["kind"], r["n_lights"], r["method"]): r for r in rows}
    keys = sorted({(r["scene"], r["kind"], r["n_lights"]) for r in rows}, key=lambda k: ([d[0] for d in DEV].index(k[0]), k[1], k[2]))
    mats = {d[0]: d[2] + (f" a={d[3]:g}" if d[2] in ("roughplastic", "roughconductor") else "") + (" tex" if d[4] else "") for d in DEV}
    body = []
    for s, k, n in keys:
        body.append([s, mats[s], f"{k[:3]}{n}"] + [_fmt(by[(s, k, n, m)]["maen"]) if (s, k, n, m) in by else "" for m in methods])
    return _md_table(["scene", "material", "lights"] + list(methods), body)


def _summary_table(rows, methods) -> str:
    """Mean MAEN by material x light count (both kinds) per method, then all non-diffuse and all (markdown)."""
    groups = [(m, n) for m in sorted({r["material"] for r in rows}) for n in sorted({r["n_lights"] for r in rows})]
    groups += [("non-diffuse", n) for n in sorted({r["n_lights"] for r in rows})]
    groups += [("all", n) for n in sorted({r["n_lights"] for r in rows})]
    body = []
    for mat, n in groups:
        sel = [r for r in rows if r["n_lights"] == n and (mat == "all" or r["material"] == mat or (mat == "non-diffuse" and r["material"] != "diffuse"))]
        cells = []
        for m in methods:
            v = [r["maen"] for r in sel if r["method"] == m]
            cells.append(_fmt(float(np.mean(v))) if v else "")
        caps = len({r["capture"] for r in sel})
        target = f"<= {TARGETS[n]}" if mat == "non-diffuse" and n in TARGETS else ""
        body.append([mat, n, caps] + cells + [target])
    return _md_table(["material", "lights", "captures"] + list(methods) + ["issue target"], body)


def _diligent_subset(obj: str, dst: Path) -> Path:
    """``dst`` holding DILIGENT_SUBSET's images of DiLiGenT ``obj`` with the matching light rows."""
    return diligent_subset(DILIGENT / obj, dst, DILIGENT_SUBSET)


def _diligent(device: str, methods=()) -> list[dict]:
    """The 10-image subsets of ball and bear: least squares, the pipeline, and the other ``methods`` asked for."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="gpps-dev-diligent-") as tmp:
        for obj in ("ball", "bear"):
            folder = _diligent_subset(obj, Path(tmp) / obj)
            files = (folder / "filenames.txt").read_text().split()
            for m in ("ls", "pipeline", *[x for x in methods if x not in ("ls", "pipeline", "pipeline_shadows")]):
                r = {"object": obj, "method": m, "files": files, **_run(folder, m, device)}
                rows.append(r)
                print(f"diligent {obj} 10 images {m}: MAEN {r['maen']:.2f} deg ({r['seconds']:.1f} s)", flush=True)
    return rows


def _parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--bits", type=int, default=16, choices=(8, 16))
    ap.add_argument("--lights", default="3,12", help="light counts, comma-separated")
    ap.add_argument("--kinds", default="directional,point")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--scenes", default=None, help=f"a subset of {[s[0] for s in DEV]} (no results written)")
    ap.add_argument("--root", default=None, help="capture cache (default $GPPS_CACHE_DIR/mitsuba_captures)")
    ap.add_argument("--no-diligent", action="store_true", help="skip the DiLiGenT 10-image subset")
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--tag", default=None, help="results as dev_eval_<tag>.json/.md (default: the device's)")
    args = ap.parse_args(argv)
    args.lights = [int(x) for x in args.lights.split(",") if x]
    args.kinds = [x for x in args.kinds.split(",") if x]
    args.methods = [x for x in args.methods.split(",") if x]
    unknown = sorted(set(args.methods) - set(METHODS))
    if unknown:
        ap.error(f"--methods: unknown {unknown}; expected some of {list(METHODS)}")
    args.scenes = [x for x in args.scenes.split(",") if x] if args.scenes else None
    if args.scenes and set(args.scenes) - {d[0] for d in DEV}:
        ap.error(f"--scenes: unknown {sorted(set(args.scenes) - {d[0] for d in DEV})}")
    return args


def _render(args) -> tuple[list, float]:
    from mitsuba_scenes import make_capture

    captures = []
    t_all = time.perf_counter()
    for name, spec in _specs(args):
        t = time.perf_counter()
        folder = make_capture(spec, args.root)
        info = json.loads((folder / "scene.json").read_text())
        captures.append((name, spec, folder, info))
        print(f"capture {folder.name}: {time.perf_counter() - t:.1f} s (rendered in {sum(info['timings']['render']):.1f} s, "
              f"{info['mean_render_s']:.2f} s/image)", flush=True)
    return captures, time.perf_counter() - t_all


def _evaluate(captures, args) -> list[dict]:
    rows = []
    for name, spec, folder, info in captures:
        base = {"scene": name, "material": spec.material, "kind": spec.light_kind, "n_lights": spec.n_lights, "capture": folder.name}
        for m in args.methods:
            if m == "pipeline_shadows" and spec.n_lights <= 3:
                continue  # no cast-shadow pass with 3 lights (shadow_few="keep"): the same as pipeline
            rows.append({**base, "method": m, **_run(folder, m, args.device)})
        print("  ".join(f"{r['scene']}/{r['kind'][:3]}{r['n_lights']}/{r['method']}: {r['maen']:.2f} ({r['seconds']:.1f} s)"
                        for r in rows if r["capture"] == folder.name), flush=True)
    return rows


def _timing_table(rows, captures, t_render) -> str:
    body = []
    for m in METHODS:
        for n in sorted({r["n_lights"] for r in rows}):
            v = [r["seconds"] for r in rows if r["method"] == m and r["n_lights"] == n]
            if v:
                body.append([m, n, len(v), f"{np.mean(v):.1f}", f"{np.sum(v):.0f}"])
    render = [sum(c[3]["timings"]["render"]) for c in captures]
    head = f"Captures: {len(captures)}, {sum(c[1].n_lights for c in captures)} images, rendered in {sum(render):.0f} s " \
           f"(when not cached; this run's capture step took {t_render:.0f} s)\n\n"
    return head + _md_table(["method", "lights", "runs", "mean s", "total s"], body)


def main(argv=None):
    args = _parse(argv)
    t_all = time.perf_counter()
    captures, t_render = _render(args)
    if args.render_only:
        return
    rows = _evaluate(captures, args)
    methods = [m for m in METHODS if m in args.methods]
    cap_table, sum_table = _capture_table(rows, methods), _summary_table(rows, methods)
    non_diffuse = [r for r in rows if r["material"] != "diffuse"]
    summary = {
        "by_method_material_lights": _means(rows, lambda r: (r["method"], r["material"], r["n_lights"])),
        "by_method_kind_lights": _means(rows, lambda r: (r["method"], r["kind"], r["n_lights"])),
        "by_method_lights": _means(rows, lambda r: (r["method"], r["n_lights"])),
        "non_diffuse_by_method_lights": _means(non_diffuse, lambda r: (r["method"], r["n_lights"])),
    }
    dil = [] if args.no_diligent else _diligent(args.device, args.methods)
    dil_table = _md_table(["object", "images (1-based)", "method", "MAEN deg", "seconds"],
                          [[r["object"], "1,10,20,...,90", r["method"], _fmt(r["maen"]), f"{r['seconds']:.1f}"] for r in dil])
    timing = _timing_table(rows, captures, t_render)
    total = time.perf_counter() - t_all
    text = (f"# perf/dev_eval.py ({device_label(args.device)}, size {args.size}, spp {args.spp}, {args.bits}-bit)\n\n"
            f"## Mean MAEN (deg) by material x light count (directional and point together)\n\n{sum_table}\n\n"
            f"## Per capture MAEN (deg)\n\n{cap_table}\n\n"
            f"## DiLiGenT, 10-image subset (0-based indices {list(DILIGENT_SUBSET)})\n\n{dil_table}\n\n"
            f"## Seconds\n\n{timing}\n\ntotal {total:.0f} s\n")
    print("\n" + text)
    if args.scenes is None:
        payload = {"args": {k: v for k, v in vars(args).items() if k != "root"}, "dev": [list(s) for s in DEV],
                   "rows": rows, "summary": summary, "targets_non_diffuse": TARGETS,
                   "diligent_subset_0based": list(DILIGENT_SUBSET), "diligent": dil,
                   "seconds_total": total, "seconds_captures": t_render,
                   "captures": {c[2].name: {"render_s": c[3]["timings"]["render"], "mitsuba": c[3]["mitsuba"],
                                            "variant": c[3]["variant"], "exposure": c[3]["exposure"]} for c in captures}}
        tag = args.tag or ("cpu" if args.device == "cpu" else device_label(args.device))
        RESULTS.mkdir(parents=True, exist_ok=True)
        path, md = RESULTS / f"dev_eval_{tag}.json", RESULTS / f"dev_eval_{tag}.md"
        payload = {"device": args.device, "device_name": device_label(args.device), "host": platform.node(), **payload}
        path.write_text(json.dumps(payload, indent=2) + "\n")
        md.write_text(text)
        print("wrote", path, md)


if __name__ == "__main__":
    main()
