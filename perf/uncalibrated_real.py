"""Uncalibrated PS on real data: Yale B faces and DiLiGenT ball / bear with the lights withheld.

Yale B (``--subjects``, Extended Yale B cropped, 64 lights + an ambient image a subject):

* Lights from the file names (``yaleB01_P00A+035E-20.pgm``: azimuth A, elevation E) in the gpps
  frame (x right, y up, z toward the camera, toward the light)::

      x = -cos(E) sin(A),   y = sin(E),   z = cos(E) cos(A)

  i.e. a positive azimuth is a light on the subject's right, the *image's left*.  The usual
  conversion ``x = +cos(E) sin(A)`` is mirrored in our frame.  :func:`check_convention` shows
  it from the images: (1) with A > 0 (E = 0) the image's left half is the brighter, with E > 0
  the upper half; (2) Lambertian least squares with the nominal lights gives normals pointing
  left on the image's left half (a convex face) and a more integrable field (smaller curl)
  than with either axis mirrored; both are in the JSON (``convention``).
* Images: 8-bit / 255, minus the subject's ambient image, clipped at 0.  The ambient image
  is not used otherwise.
* Mask (none is given): pixels brighter than 0.1 (after the ambient subtraction) in at least
  a third of the images; it drops the pupils, nostrils and dark eyebrows.
* Failed captures are left out, by the rule solve_uncalibrated enforces
  (``gpps.host.gbr.dark_images``: 99th percentile below 0.1 x the median image's):
  yaleB02's ``A+095E+00`` (0.01; the flash did not fire) and ``A-130E+20`` (0.05; the same
  light gives 0.30-0.35 for the other subjects).  Kept, they came out 97 and 123 deg off.
* Score: mean angle between the estimated and the nominal light directions.  The only
  alignment is the convex/concave flip ``(x, y, z) -> (-x, -y, z)`` when the method reports
  the flip as ambiguous (the GBR itself is resolved by the method); the oracle columns (best
  GBR / best 3x3 fitted to the true lights) are diagnostics of what each stage loses, never
  the score.

DiLiGenT (``--objects``): images read with ``gpps.io.read_dataset(normalise=False)``: the
light directions *and intensities* are withheld from the uncalibrated method (the calibrated
baseline divides by the intensities, as perf/diligent_calibrated.py does).  The perspective
camera of ``K.txt`` is passed (the flip is decided by the perspective curl when it can be).
MAEN against ``normal_gt.npy`` after only the flip, beside Woodham least squares with the true
lights (``gpps.flows.photometric.solve_normals(..., solver="none")``) on the same images.

Baseline = factorisation + integrability + GBR (no refinement); it is
``UncalibratedResult.baseline`` of the refined run, which is exactly what
``refine="none"`` returns (the stages before the refinement are the same code).

Writes perf/results/uncalibrated_real_<device>.json and the normal maps (RGB = (n + 1) / 2)
perf/results/views/uncalibrated_<name>.png: panels calibrated least squares | baseline |
refined (DiLiGenT: ground truth first).

Usage:  python perf/uncalibrated_real.py [--subjects yaleB01 ...] [--objects ball bear] [--quick] [--device cpu]
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np

DATA = ROOT.parent / "shared" / "data"
FLIP = np.diag([-1.0, -1.0, 1.0])
SUBJECTS = ["yaleB01", "yaleB02", "yaleB03", "yaleB04"]
OBJECTS = ["ball", "bear"]
MASK_LEVEL, MASK_FRACTION = 0.1, 1.0 / 3.0


# --------------------------------------------------------------------------- Yale B


def yale_lights(azimuth_deg, elevation_deg, sign_x: float = -1.0, sign_y: float = 1.0) -> np.ndarray:
    """Unit directions toward the lights in the gpps frame (the verified convention: sign_x = -1)."""
    a = np.radians(np.asarray(azimuth_deg, np.float64))
    e = np.radians(np.asarray(elevation_deg, np.float64))
    return np.stack([sign_x * np.cos(e) * np.sin(a), sign_y * np.sin(e), np.cos(e) * np.cos(a)], -1)


def read_yale(folder: Path) -> dict:
    """64 images (ambient subtracted, clipped at 0, in [0, 1]), azimuth/elevation, the ambient image."""
    from gpps.io import read_image

    folder = Path(folder)
    sub = folder.name
    files = sorted(glob.glob(str(folder / f"{sub}_P00A*.pgm")))
    if not files:
        raise FileNotFoundError(f"{folder}: no {sub}_P00A*.pgm images")
    ambient = read_image(folder / f"{sub}_P00_Ambient.pgm")[..., 0]
    ims, ae = [], []
    for f in files:
        m = re.search(r"A([+-]\d+)E([+-]\d+)", Path(f).name)
        ae.append((int(m[1]), int(m[2])))
        ims.append(read_image(f)[..., 0])
    ims = np.clip(np.stack(ims) - ambient[None], 0.0, None).astype(np.float32)
    ae = np.array(ae, np.float64)
    return {"images": ims, "azimuth": ae[:, 0], "elevation": ae[:, 1], "ambient": ambient, "files": [Path(f).name for f in files]}


def yale_mask(images: np.ndarray) -> np.ndarray:
    return (images > MASK_LEVEL).sum(0) >= MASK_FRACTION * len(images)


def lambertian_ls(images, mask, lights, shadow: float = 0.15, saturation: float = 0.98) -> tuple[np.ndarray, np.ndarray]:
    """Calibrated Lambertian least squares with shadows (< shadow x the image's 99th percentile) and
    saturated observations dropped; returns (H, W, 3) unit normals and (P,) RMS residuals."""
    M = images[:, mask].astype(np.float64)
    W = (M > shadow * np.percentile(M, 99, axis=1, keepdims=True)) & (M < saturation)
    W = W.astype(np.float64)
    A = np.einsum("np,ni,nj->pij", W, lights, lights) + 1e-9 * np.eye(3)
    B = np.linalg.solve(A, ((W * M).T @ lights)[..., None])[..., 0]
    res = np.sqrt((W * (M - lights @ B.T) ** 2).sum(0) / np.maximum(W.sum(0), 1))
    n = np.zeros(mask.shape + (3,))
    n[mask] = B / np.maximum(np.linalg.norm(B, axis=1, keepdims=True), 1e-12)
    return n, res


def relative_curl(normals, mask) -> float:
    """Mean |dp/dy - dq/dx| / mean |(p, q)| of the orthographic gradient field (p, q) = -(nx, ny) / nz."""
    nz = np.where(np.abs(normals[..., 2]) < 0.05, 0.05, normals[..., 2])
    p, q = -normals[..., 0] / nz, -normals[..., 1] / nz
    ok = mask[1:, :-1] & mask[:-1, :-1] & mask[1:, 1:]
    py = p[:-1, :-1] - p[1:, :-1]  # y up = row up
    qx = q[1:, 1:] - q[1:, :-1]
    return float(np.abs(py - qx)[ok].mean() / (np.abs(p[1:, :-1][ok]).mean() + np.abs(q[1:, :-1][ok]).mean()))


def check_convention(d: dict, mask) -> dict:
    """Evidence for the sign of the azimuth and the elevation, from the images themselves."""
    ims, A, E = d["images"], d["azimuth"], d["elevation"]
    h, w = mask.shape
    left, top = np.zeros((h, w), bool), np.zeros((h, w), bool)
    left[:, : w // 2] = True
    top[: h // 2] = True
    az = (E == 0) & (A != 0)
    el = (A == 0) & (E != 0) & (np.abs(E) < 90)
    bright = {
        "azimuth>0, E=0: mean(left half) - mean(right half)": float(np.mean([ims[k][left & mask].mean() - ims[k][~left & mask].mean() for k in np.where(az & (A > 0))[0]])),
        "azimuth<0, E=0: mean(left half) - mean(right half)": float(np.mean([ims[k][left & mask].mean() - ims[k][~left & mask].mean() for k in np.where(az & (A < 0))[0]])),
        "elevation>0, A=0: mean(upper half) - mean(lower half)": float(np.mean([ims[k][top & mask].mean() - ims[k][~top & mask].mean() for k in np.where(el & (E > 0))[0]])),
        "elevation<0, A=0: mean(upper half) - mean(lower half)": float(np.mean([ims[k][top & mask].mean() - ims[k][~top & mask].mean() for k in np.where(el & (E < 0))[0]])),
    }
    fits = {}
    for name, sx, sy in (("x=-cosE sinA, y=+sinE (used)", -1.0, 1.0), ("x=+cosE sinA (azimuth mirrored)", 1.0, 1.0), ("y=-sinE (elevation mirrored)", -1.0, -1.0)):
        n, res = lambertian_ls(ims, mask, yale_lights(A, E, sx, sy))
        fits[name] = {
            "mean nx, image left half": float(n[left & mask][:, 0].mean()),
            "mean nx, image right half": float(n[~left & mask][:, 0].mean()),
            "mean ny, image upper half": float(n[top & mask][:, 1].mean()),
            "mean ny, image lower half": float(n[~top & mask][:, 1].mean()),
            "fraction nz > 0": float((n[mask][:, 2] > 0).mean()),
            "relative curl": relative_curl(n, mask),
            "rms residual": float(np.median(res)),
        }
    return {"brightness": bright, "calibrated_least_squares": fits}


# --------------------------------------------------------------------------- scoring


def light_scores(est, true, flip_status: str) -> dict:
    """Light-direction errors after only the flip (when the method left it ambiguous)."""
    from gpps.host.gbr import light_direction_errors

    cands = {"as returned": est}
    if flip_status != "resolved":
        cands["flipped"] = est @ FLIP
    errs = {k: light_direction_errors(v, true) for k, v in cands.items()}
    k = min(errs, key=lambda k: errs[k].mean())
    e = errs[k]
    return {"mean": float(e.mean()), "median": float(np.median(e)), "max": float(e.max()), "flip_applied": k == "flipped", "per_light": e}


def oracle_errors(est, true) -> dict:
    """Diagnostics (never the score): errors after the best GBR (+flip, sign) and the best 3x3 fitted to the true lights."""
    from scipy.optimize import least_squares

    from gpps.host.gbr import gbr, light_direction_errors

    def unit(a):
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    best = np.inf
    for fl in (np.eye(3), FLIP):
        for g0 in (0.5, 1.0, 2.0):
            e = est @ fl
            r = least_squares(lambda x, e=e: (unit(e @ np.linalg.inv(gbr(x[0], x[1], x[2]))) - true).ravel(), [0.0, 0.0, g0])
            best = min(best, light_direction_errors(est @ fl @ np.linalg.inv(gbr(*r.x)), true).mean())
    X = np.linalg.lstsq(est, true, rcond=None)[0]
    r = least_squares(lambda x: (unit(est @ x.reshape(3, 3)) - true).ravel(), X.ravel())
    return {"best_gbr": float(best), "best_linear": float(light_direction_errors(est @ r.x.reshape(3, 3), true).mean())}


def flip_normals(n, applied: bool):
    return n @ FLIP if applied else n


def normal_view(path, panels, mask):
    from gpps.io import save_png

    tiles = []
    for n in panels:
        rgb = np.where(mask[..., None], (np.asarray(n, np.float64) + 1.0) / 2.0, 0.0)
        tiles.append(rgb)
        tiles.append(np.ones((mask.shape[0], 4, 3)))
    save_png(path, np.concatenate(tiles[:-1], 1), bits=8)


# --------------------------------------------------------------------------- runs


def run_yale(subject, data, cfg, device, views, log):
    from gpps.flows.uncalibrated import solve_uncalibrated
    from gpps.host.gbr import dark_images

    d = read_yale(Path(data) / subject)
    mask = yale_mask(d["images"])
    # failed captures (signal at the noise level) are refused by solve_uncalibrated: leave them out
    drop = dark_images(d["images"], mask, cfg.dark_fraction) if cfg.dark_fraction > 0 else []
    keep = np.setdiff1d(np.arange(len(d["images"])), drop)
    dropped = [d["files"][k] for k in drop]
    d = {**d, "images": d["images"][keep], "azimuth": d["azimuth"][keep], "elevation": d["elevation"][keep], "files": [d["files"][k] for k in keep]}
    mask = yale_mask(d["images"])
    true = yale_lights(d["azimuth"], d["elevation"])
    out = {"name": subject, "kind": "yaleb", "images": len(d["images"]), "dropped_dark_images": dropped, "shape": list(mask.shape), "pixels": int(mask.sum())}
    out["convention"] = check_convention(d, mask)
    calib, _ = lambertian_ls(d["images"], mask, true)
    t = time.perf_counter()
    res = solve_uncalibrated(d["images"], mask, config=cfg, device=device)
    out["seconds"] = time.perf_counter() - t
    out["timings"] = res.timings
    out["flip"] = res.flip
    out["baseline_light"] = light_scores(res.baseline["light_directions"], true, res.flip)
    out["refined_light"] = light_scores(res.light_directions, true, res.flip)
    out["oracle_baseline"] = oracle_errors(res.baseline["light_directions"], true)
    out["oracle_refined"] = oracle_errors(res.light_directions, true)
    nb = flip_normals(res.baseline["normals"], out["baseline_light"]["flip_applied"])
    nr = flip_normals(res.normals, out["refined_light"]["flip_applied"])
    from gpps.host.metrics import normal_errors

    # not ground truth: the agreement with calibrated Lambertian least squares (true lights)
    out["baseline_vs_calibrated_ls_deg"] = normal_errors(nb, calib, mask)["mean"]
    out["refined_vs_calibrated_ls_deg"] = normal_errors(nr, calib, mask)["mean"]
    out["gbr"] = res.gbr
    out["material"] = res.material
    out["lights"] = {"files": d["files"], "true": true, "refined": res.light_directions, "baseline": res.baseline["light_directions"]}
    if views:
        p = ROOT / "perf" / "results" / "views" / f"uncalibrated_{subject}.png"
        normal_view(p, [calib, nb, nr], mask)
        out["view"] = str(p.relative_to(ROOT))
    log(f"{subject}: baseline {out['baseline_light']['mean']:.2f} deg, refined {out['refined_light']['mean']:.2f} deg ({out['seconds']:.0f} s)" + (f"; left out (nearly dark): {', '.join(dropped)}" if dropped else ""))
    return out


def run_diligent(name, data, cfg, device, views, log):
    from gpps.camera import camera_from_K
    from gpps.io import read_dataset
    from gpps.lights import DirectionalLights
    from gpps.host.metrics import normal_errors
    from gpps.flows.photometric import solve_normals
    from gpps.flows.uncalibrated import solve_uncalibrated

    raw = read_dataset(Path(data) / name, normalise=False)
    ds = read_dataset(Path(data) / name)
    camera = camera_from_K(ds.K)
    true = ds.light_directions
    out = {"name": name, "kind": "diligent", "images": len(ds.images), "shape": list(ds.mask.shape), "pixels": int(ds.mask.sum())}
    t = time.perf_counter()
    ls = solve_normals(ds.images, ds.mask, DirectionalLights(true), camera=camera, solver="none", device=device)
    out["calibrated_ls"] = normal_errors(ls.normals, ds.normal_gt, ds.mask)
    out["calibrated_ls"]["seconds"] = time.perf_counter() - t
    t = time.perf_counter()
    res = solve_uncalibrated(raw.images, raw.mask, camera=camera, config=cfg, device=device)
    out["seconds"] = time.perf_counter() - t
    out["timings"] = res.timings
    out["flip"] = res.flip
    out["baseline_light"] = light_scores(res.baseline["light_directions"], true, res.flip)
    out["refined_light"] = light_scores(res.light_directions, true, res.flip)
    out["oracle_baseline"] = oracle_errors(res.baseline["light_directions"], true)
    out["oracle_refined"] = oracle_errors(res.light_directions, true)
    # MAEN after only the flip; the baseline's flip is its own (it is not perspective-resolved)
    out["baseline_maen"], nb = _best_maen(res.baseline["normals"], ds.normal_gt, ds.mask, "ambiguous")
    out["refined_maen"], nr = _best_maen(res.normals, ds.normal_gt, ds.mask, res.flip)
    out["gbr"] = res.gbr
    out["material"] = res.material
    if views:
        p = ROOT / "perf" / "results" / "views" / f"uncalibrated_{name}.png"
        normal_view(p, [ds.normal_gt, ls.normals, nb, nr], ds.mask)
        out["view"] = str(p.relative_to(ROOT))
    log(
        f"{name}: calibrated LS MAEN {out['calibrated_ls']['mean']:.2f}; uncalibrated MAEN baseline {out['baseline_maen']['mean']:.2f}, "
        f"refined {out['refined_maen']['mean']:.2f}; lights {out['baseline_light']['mean']:.2f} -> {out['refined_light']['mean']:.2f} deg ({out['seconds']:.0f} s)"
    )
    return out


def _best_maen(n, gt, mask, flip_status):
    from gpps.host.metrics import normal_errors

    cands = {"as returned": n}
    if flip_status != "resolved":
        cands["flipped"] = n @ FLIP
    errs = {k: normal_errors(v, gt, mask) for k, v in cands.items()}
    k = min(errs, key=lambda k: errs[k]["mean"])
    return {**errs[k], "flip_applied": k == "flipped"}, cands[k]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--subjects", nargs="*", default=None, help=f"Yale B subjects (default {' '.join(SUBJECTS)}; --quick: yaleB01)")
    ap.add_argument("--objects", nargs="*", default=None, help=f"DiLiGenT objects (default {' '.join(OBJECTS)}; --quick: ball)")
    ap.add_argument("--quick", action="store_true", help="one subject and one object, fewer refinement steps")
    ap.add_argument("--yale", default=str(DATA / "yaleb"))
    ap.add_argument("--diligent", default=str(DATA / "diligent"))
    ap.add_argument("--no-views", action="store_true")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    from gpps.flows.uncalibrated import UncalibratedConfig

    subjects = a.subjects if a.subjects is not None else (SUBJECTS[:1] if a.quick else SUBJECTS)
    objects = a.objects if a.objects is not None else (OBJECTS[:1] if a.quick else OBJECTS)
    opts = {"refine_iterations": 100, "final_iterations": 50, "refine_pixels": 3000} if a.quick else {}
    cfg = UncalibratedConfig(**opts)

    def log(s):
        print(s, flush=True)

    rows = []
    for s in subjects:
        rows.append(run_yale(s, a.yale, cfg, a.device, not a.no_views, log))
    for o in objects:
        rows.append(run_diligent(o, a.diligent, cfg, a.device, not a.no_views, log))

    print("\nlight-direction error (deg, after only the flip), MAEN (deg) where ground truth exists")
    print(f"{'case':9s} {'baseline':>8s} {'refined':>8s} {'better':>6s} | {'MAEN base':>9s} {'MAEN ref':>8s} {'MAEN LS':>8s} | {'flip':9s} {'seconds':>7s}")
    for r in rows:
        b, f = r["baseline_light"]["mean"], r["refined_light"]["mean"]
        m = (f"{r['baseline_maen']['mean']:9.2f} {r['refined_maen']['mean']:8.2f} {r['calibrated_ls']['mean']:8.2f}") if r["kind"] == "diligent" else f"{'-':>9s} {'-':>8s} {'-':>8s}"
        fl = r["flip"] + ("*" if r["refined_light"]["flip_applied"] else "")
        print(f"{r['name']:9s} {b:8.2f} {f:8.2f} {'yes' if f < b else 'NO':>6s} | {m} | {fl:9s} {r['seconds']:7.0f}")
    print("flip: 'ambiguous*' = the flipped alternative was the one scored; MAEN LS = calibrated Woodham least squares, true lights")

    from dataclasses import asdict

    from gpps.io import save_json

    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"uncalibrated_real_{a.device.split(':')[0]}.json"
    save_json(out, {"device": a.device, "quick": a.quick, "config": asdict(cfg), "yale_lights": "x = -cos(E) sin(A), y = sin(E), z = cos(E) cos(A)", "cases": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
