"""RON with and without the cast-shadow pass (``RONConfig.cast_shadows``, issue 25): MAEN on scenes with cast
shadows and on scenes without, 3 and 12 lights, directional and point, perspective camera.

Scenes (no DiLiGenT):

* ``bumps``: tests/ron_shadow_scenes.py's Gaussian bump (height 0.25 S, width 0.09 S, slopes up to 59 degrees)
  on a plane, the truth from the analytic height field (depth, normals, and each light's visibility by a 3D march
  against the height function in steps of 1/20 pixel); lights at slants up to 70 degrees.  Smooth: the rounds'
  integrated depth keeps the occluder's height.
* ``hemisphere`` / ``box``: tests/shadow_reference.py's analytic scenes (a hemisphere of radius 0.3 S, or a box
  0.31 S tall, on a plane filling the S x S image; a 12-degree pinhole with a 1-unit pixel on the plane), rendered
  by :class:`gpps.pipeline.render.Renderer` (no shadows there) and multiplied by the **exact** visibility of each
  light, ray-cast in numpy against the analytic solid (``Scene.visible``: independent of the depth map and of the
  march); Gaussian noise 0.002.  Known Blinn-Phong material (ks 0.4, shininess 40), uniform albedo.
* ``sphere``: :func:`gpps.host.scenes.make_scene` sphere (no cast shadows: it must not get worse).
* ``mts-*``: Mitsuba 3 path-traced captures (training/mitsuba_scenes.py: interreflections, noise, 16 bits;
  seeds 2001+, not the held-out 1000-1007), RON on the Lambertian model (the renders' material is not gpps's),
  the lights and camera of the capture; ``sphere_on_plane`` and ``spheres`` have cast shadows, ``bumps`` (a
  height field lit from 30-50 degrees) few.

MAEN (deg) over the mask and over the *shadowed* pixels (those with at least one observation in a cast
shadow: facing the light and hidden from it; analytic scenes: exact; Mitsuba: the ground-truth depth marched
by :class:`gpps.pipeline.shadows.CastShadows`, only for selecting the pixels to report).  Also the dropped
observations of the last pass, their IoU with those cast-shadow sets (facing observations only; for Mitsuba
against the march over the true depth, so not an independent check there) and the seconds of the passes
(``timings["shadows"]``).  Variants: ``off`` (``cast_shadows=False``) and ``on-<shadow_few>`` at RON's default
tolerance (``--tau`` adds others).  Results: perf/results/ron_shadows_cpu.json (and .txt, the printed table).

Usage:  python perf/ron_shadows.py [--size 64] [--lights 3 12] [--kinds directional point]
        [--scenes bumps hemisphere box sphere mts-sphere_on_plane ...] [--few keep flag] [--tau 1 0.5] [--out PATH]
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
sys.path.insert(0, str(ROOT / "training"))  # training/mitsuba_scenes.py

import numpy as np  # noqa: E402

from _common import device_label  # noqa: E402

MAT = ("blinn-phong", 0.4, 40.0)  # tests/ron_shadow_scenes.MATERIAL
ANALYTIC = ("hemisphere", "box")
BUMP = ((0.25, 0.0, 0.0, 0.09),)  # tests/ron_shadow_scenes.py: (A, cx, cy, s) in image sides
BUMP_SLANT = 70.0
MITSUBA = {"mts-sphere_on_plane": ("sphere_on_plane", "roughplastic", 0.2, False, 2001),
           "mts-spheres": ("spheres", "diffuse", 0.2, False, 2002),
           "mts-bumps": ("bumps", "roughplastic", 0.15, True, 2003)}
DEFAULT_SCENES = ("bumps", "hemisphere", "box", "sphere", "mts-sphere_on_plane", "mts-spheres", "mts-bumps")


def sphere_case(kind: str, n: int, size: int, noise: float = 0.002, seed: int = 0) -> dict:
    """gpps's sphere (no cast shadows) under the same light layouts."""
    from gpps.host.scenes import make_scene
    from gpps.lights import DirectionalLights, PointLights, ring_directions, spiral_directions
    from gpps.material import Material
    from gpps.pipeline.render import Renderer, add_noise

    sc = make_scene("sphere", size, "perspective")
    dirs = ring_directions(n, 45.0) if n <= 4 else spiral_directions(n, 15.0, 60.0)
    centre = np.array([0.0, 0.0, -float(sc.depth[sc.mask].mean())])
    rr = 3.0 * float(np.ptp(sc.camera.backproject(sc.depth)[sc.mask][:, 0]))
    lights = DirectionalLights(dirs) if kind == "directional" else PointLights(centre + rr * dirs, np.full((n, 3), rr * rr))
    mat = Material(MAT[0], ks=MAT[1], shininess=MAT[2])
    with Renderer((size, size), sc.camera, lights, mat) as r:
        img = r.run(sc.depth, sc.mask, np.array([0.7, 0.6, 0.5]), normals=sc.normals)
    img = np.clip(add_noise(img, noise, seed), 0.0, None).astype(np.float32)
    img[:, ~sc.mask] = 0.0
    return {"images": img, "mask": sc.mask, "camera": sc.camera, "lights": lights, "material": mat,
            "normals": sc.normals, "depth": sc.depth, "shadow": np.zeros((n,) + sc.mask.shape, bool),
            "reference_depth": float(sc.depth[sc.mask].mean())}


def mitsuba_case(name: str, kind: str, n: int, size: int, spp: int = 32) -> dict:
    """A Mitsuba capture (cached under $GPPS_CACHE_DIR/mitsuba_captures) read back as RON's inputs."""
    from mitsuba_scenes import CaptureSpec, make_capture

    from gpps.camera import Perspective
    from gpps.io import read_capture
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material
    from gpps.pipeline.shadows import CastShadows

    shape, material, alpha, texture, seed = MITSUBA[name]
    spec = CaptureSpec(shape=shape, material=material, alpha=alpha, texture=texture, light_kind=kind, n_lights=n,
                       size=size, spp=spp, seed=seed)
    ds = read_capture(make_capture(spec)).dataset
    cam = Perspective(ds.K)
    # images divided by the light intensities (read_capture's normalise): unit lights
    lights = PointLights(ds.light_positions) if ds.light_positions is not None else DirectionalLights(ds.light_directions)
    images = np.asarray(ds.images, np.float32)
    if not ds.normalised:
        images = images / np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
    m = ds.mask
    with CastShadows((n,) + m.shape, cam, lights) as st:
        vis = st.run(ds.depth_gt, m)
    nd = np.einsum("hwc,khwc->khw", ds.normal_gt, _light_dirs(lights, cam, ds.depth_gt, m))
    return {"images": images, "mask": m, "camera": cam, "lights": lights, "material": Material("lambertian"),
            "normals": ds.normal_gt, "depth": ds.depth_gt, "shadow": ~vis & (nd > 0) & m,
            "reference_depth": float(ds.depth_gt[m].mean())}


def _light_dirs(lights, cam, depth, mask):
    from gpps.lights import DirectionalLights

    if isinstance(lights, DirectionalLights):
        return np.broadcast_to(lights.directions[:, None, None, :], (len(lights),) + mask.shape + (3,))
    p = cam.backproject(np.where(mask, depth, 1.0))
    d = lights.positions[:, None, None, :] - p[None]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def run_ron(case: dict, cast_shadows: bool, *, device="cpu", few="keep", device_rounds=None, rounds=5, tau=None):
    """RON on a case (``tau`` None: RONConfig's default tolerance); returns the result."""
    from gpps.flows.ron import RON, RONConfig
    from gpps.lights import PointLights
    from gpps.pipeline.shadows import ShadowConfig

    extra = {} if tau is None else {"shadow_config": ShadowConfig(tolerance_px=tau)}
    cfg = RONConfig(cast_shadows=cast_shadows, shadow_few=few, device_rounds=device_rounds, rounds=rounds, **extra)
    n = len(case["lights"])
    shape = (n,) + case["mask"].shape
    ron = RON(shape, case["camera"], case["lights"], case["material"], case["mask"], cfg, device=device)
    try:
        ref = case["reference_depth"] if isinstance(case["lights"], PointLights) else None
        return ron.run(case["images"], reference_depth=ref)
    finally:
        ron.close()


def measure(case: dict, res) -> dict:
    from gpps.host.metrics import normal_errors

    m = case["mask"]
    shadowed = case["shadow"].any(0) & m
    row = {"maen": normal_errors(res.normals, case["normals"], m)["mean"], "rounds": res.rounds,
           "shadowed_pixels": int(shadowed.sum()), "shadows_s": res.timings.get("shadows", 0.0),
           "total_s": res.timings["total"]}
    row["maen_shadowed"] = normal_errors(res.normals, case["normals"], shadowed)["mean"] if shadowed.any() else None
    if res.shadows:
        row["dropped"] = res.shadows[-1]["dropped"]
        row["few_pixels"] = res.shadows[-1]["few_pixels"]
        row["kept_pixels"] = res.shadows[-1]["kept_pixels"]
        # the cast-shadow sets (facing the light by the true normals), as tests/test_shadows.py compares them
        true = case["shadow"] & m[None]
        got = res.shadowed & case["facing"] & m[None]
        u = np.count_nonzero(true | got)
        row["iou"] = 1.0 if u == 0 else float(np.count_nonzero(true & got) / u)
    return row


def _facing(case):
    l = _light_dirs(case["lights"], case["camera"], case["depth"], case["mask"])
    return np.einsum("hwc,khwc->khw", case["normals"], l) > 0


def make_case(scene, kind, n, size):
    if scene == "bumps":
        from ron_shadow_scenes import bump_case

        return bump_case(kind, n, size, bumps=BUMP, slant=BUMP_SLANT)
    if scene in ANALYTIC:
        from ron_shadow_scenes import solid_case

        return solid_case(scene, kind, n, size)
    if scene == "sphere":
        return sphere_case(kind, n, size)
    return mitsuba_case(scene, kind, n, size)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--lights", type=int, nargs="+", default=[3, 12])
    ap.add_argument("--kinds", nargs="+", default=["directional", "point"])
    ap.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    ap.add_argument("--few", nargs="+", default=["keep", "flag"], help="shadow_few rules to run with the pass on")
    ap.add_argument("--tau", type=float, nargs="+", default=[None],
                    help="tolerances (pixel widths) with the pass on (default: RONConfig's)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)

    from gpps._runtime import resolve_device

    device = resolve_device(a.device)
    rows = []
    t_all = time.perf_counter()
    for scene in a.scenes:
        for kind in a.kinds:
            for n in a.lights:
                case = make_case(scene, kind, n, a.size)
                case["facing"] = _facing(case)
                variants = [("off", False, "keep", None)] + [
                    (f"on-{f}" + (f"-tau{t:g}" if len(a.tau) > 1 else ""), True, f, t) for t in a.tau for f in a.few]
                for label, on, few, tau in variants:
                    r = measure(case, run_ron(case, on, device=device, few=few, tau=tau))
                    row = {"scene": scene, "kind": kind, "lights": n, "shadows": label, **r}
                    rows.append(row)
                    ms = f"{r['maen_shadowed']:6.2f}" if r["maen_shadowed"] is not None else "     -"
                    print(f"{scene:>20} {kind:>11} {n:>2} {label:>14}: MAEN {r['maen']:6.2f}  shadowed {ms} "
                          f"({r['shadowed_pixels']} px)  dropped {r.get('dropped', 0):>6}  IoU {r.get('iou', float('nan')):.3f}"
                          f"  rounds {r['rounds']}  {r['total_s']:.1f} s", flush=True)
    payload = {"device": device_label(device), "size": a.size, "material": MAT, "args": {k: str(v) for k, v in vars(a).items()},
               "rows": rows,
               "seconds": time.perf_counter() - t_all}
    out = a.out or ROOT / "perf" / "results" / f"ron_shadows_{'cpu' if device == 'cpu' else device_label(device)}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(payload, indent=1))
    print("wrote", out)


if __name__ == "__main__":
    main()
