"""Where issue 25's 12-light error comes from: interreflections, the pixel footprint, and the rest.

For each development capture of perf/dev_eval.py (seeds 3000-3009) under the given lights this measures, against
the pixel-centre ground truth the captures carry:

* ``ls_d4`` / ``pipe_d4``: least squares and the default pipeline on the capture as rendered (Mitsuba's path
  tracer, ``max_depth`` 4: up to two interreflections);
* ``ls_d2`` / ``pipe_d2``: the same scene, lights, noise and seed rendered with ``max_depth`` 2 (direct light only:
  cast shadows kept, interreflections gone).  ``pipe_d4 - pipe_d2`` is what interreflections cost the pipeline;
* ``footprint``: the mean angle between the pixel-centre normal and the mean normal over the pixel's footprint
  (``SUB`` x ``SUB`` rays inside the pixel, the box filter the renders use).  A per-pixel method that recovers
  the footprint's mean normal exactly still scores this against the centre ground truth: a floor that no
  photometric method beats (it is largest on one-pixel facets, creases and silhouettes);
* ``pipe_d2_smooth``: the d2 pipeline's MAEN over the pixels whose footprint spread is below 1 deg (no crease
  or silhouette inside the pixel).

Everything here is our own renders (issue 25's development set); nothing is tuned on it in this script.
Output: JSON lines (one per capture) and a markdown table on stdout::

    python perf/dev_floor.py OUT.jsonl [--lights 12] [--kinds directional,point] [--scenes a,b] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))
from dev_eval import DEV  # noqa: E402

#: sub-pixel rays per side for the footprint's mean normal
SUB = 4


def _scene_shapes(spec):
    """The Mitsuba shapes of ``spec``, built exactly as ``render_capture`` builds them (same rng draws)."""
    import tempfile

    import mitsuba_scenes as ms

    mi = ms.mitsuba()
    rng = np.random.default_rng([spec.seed, ms.SHAPES.index(spec.shape), ms.MATERIALS.index(spec.material), 11])
    with tempfile.TemporaryDirectory(prefix="gpps-floor-") as tmp:
        bsdf = mi.load_dict(ms._bsdf(spec, rng))
        shapes = {k: mi.load_dict(v) for k, v in ms._shapes(spec, rng, bsdf, Path(tmp)).items()}
    return shapes


def footprint_normals(spec, sub: int = SUB) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) mean normal over each pixel's footprint (``sub`` x ``sub`` rays, misses and surfaces facing away
    left out) and (H, W) the fraction of the rays that hit a visible surface."""
    import mitsuba_scenes as ms

    mi = ms.mitsuba()
    shapes = _scene_shapes(spec)
    scene = mi.load_dict({"type": "scene", **shapes})
    size = spec.size
    K = np.array(ms.default_camera("perspective", size).K)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    acc = np.zeros((size, size, 3))
    hits = np.zeros((size, size))
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    for i in range(size):
        for j in range(size):
            for dv in offs:
                for du in offs:
                    # gpps frame: x right, y up, z toward the camera; rows go down
                    d = np.array([(j + du - cx) / fx, -(i + dv - cy) / fy, -1.0])
                    d /= np.linalg.norm(d)
                    si = scene.ray_intersect(mi.Ray3f([0.0, 0.0, 0.0], d.tolist()))
                    if not si.is_valid():
                        continue
                    n = np.array(si.sh_frame.n, np.float64)
                    n /= np.linalg.norm(n)
                    if -float(n @ d) <= ms.MIN_FACING:
                        continue
                    acc[i, j] += n
                    hits[i, j] += 1
    norm = np.linalg.norm(acc, axis=-1, keepdims=True)
    return acc / np.maximum(norm, 1e-12), hits / sub**2


def _angles(a, b) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def _run(folder, method: str, device: str) -> np.ndarray:
    import gpps

    cfg = gpps.FolderConfig() if method == "pipe" else gpps.FolderConfig(solver="none", integrate=False)
    return gpps.reconstruct_folder(folder, cfg, device=device).normals


def main(argv=None) -> None:
    import mitsuba_scenes as ms
    from gpps.io import read_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--lights", default="12")
    ap.add_argument("--kinds", default="directional,point")
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = []
    for name, shape, material, alpha, texture, seed in DEV:
        if args.scenes and name not in args.scenes.split(","):
            continue
        fp = None
        for kind in args.kinds.split(","):
            for n in (int(x) for x in args.lights.split(",")):
                spec = ms.CaptureSpec(shape=shape, material=material, alpha=alpha, texture=texture, light_kind=kind,
                                      n_lights=n, size=128, spp=args.spp, bits=16, seed=seed)
                t = time.perf_counter()
                d4 = ms.make_capture(spec)
                d2 = ms.make_capture(replace(spec, max_depth=2))
                t_render = time.perf_counter() - t
                ds = read_capture(d4).dataset
                gt, mask = ds.normal_gt, ds.mask
                if fp is None:
                    t = time.perf_counter()
                    fp, cover = footprint_normals(spec)
                    t_fp = time.perf_counter() - t
                spread = _angles(fp, gt)
                smooth = mask & (spread < 1.0) & (cover > 0.999)
                row = {"capture": spec.name, "scene": name, "material": material, "kind": kind, "lights": n,
                       "footprint": float(spread[mask].mean()), "smooth_share": float(smooth.sum() / mask.sum()),
                       "render_s": t_render, "footprint_s": t_fp}
                for tag, folder in (("d4", d4), ("d2", d2)):
                    for m in ("ls", "pipe"):
                        err = _angles(_run(folder, m, args.device), gt)
                        row[f"{m}_{tag}"] = float(err[mask].mean())
                        row[f"{m}_{tag}_smooth"] = float(err[smooth].mean())
                rows.append(row)
                with open(args.out, "a") as f:
                    f.write(json.dumps(row) + "\n")
                print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    keys = ("footprint", "ls_d4", "pipe_d4", "ls_d2", "pipe_d2", "pipe_d4_smooth", "pipe_d2_smooth")
    print("| capture | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for r in rows:
        print(f"| {r['scene']} {r['kind']}{r['lights']} | " + " | ".join(f"{r[k]:.2f}" for k in keys) + " |")
    nd = [r for r in rows if r["material"] != "diffuse"]
    if nd:
        print("| non-diffuse mean | " + " | ".join(f"{np.mean([r[k] for r in nd]):.2f}" for k in keys) + " |")


if __name__ == "__main__":
    main()
