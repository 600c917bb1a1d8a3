"""Mirror-sphere light calibration through the command line, on renders with known lights.

For each camera (orthographic, perspective: the default scene cameras at
200 px), light set (8 lights on a 30 deg ring; 12 random within 60 deg of the
view axis; 20 random within 70 deg) and bit depth (8, 16):

1. *found outline*: a mirror sphere alone in view (``gpps.host.calibrate.render_spheres``:
   a 3 deg source disc, a dim room reflected at 0.05, highlights saturating,
   4x4 anti-aliasing), written as PNGs (+ K.txt); ``gpps calibrate-lights DIR``
   finds the outline itself.
2. *masks*: a mirror and a matte sphere in view, their outlines given as
   ``chrome_mask.png`` / ``matte_mask.png`` (pixels whose centre sees the
   sphere), coloured light intensities to recover.
3. *reconstruct*: the textured bumps scene (Lambertian) rendered under the
   same lights and camera, reconstructed by ``gpps reconstruct`` with the true
   light files and with ``--lights`` the calibrated folder of step 2; MAEN of
   each against the ground truth and their difference.

4. *near lights* (``--near``): two mirror spheres of known radius, a perspective
   camera, 12 point lights 6-12 units from the spheres; ``gpps calibrate-lights
   --sphere-radius`` triangulates ``light_positions.txt``; error relative to the
   light's distance from the spheres.

Directions: angle to the true directions (deg).  Intensities: relative error
after the common scale.  Writes perf/results/calibrate_spheres.json.

Usage: python perf/calibrate_spheres.py [--quick] [--no-reconstruct]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np

SIZE = 200


def light_sets(seed=0):
    rng = np.random.default_rng(seed)

    def rand(n, maxdeg):
        th = np.radians(np.sqrt(rng.uniform(np.radians(5) ** 2, np.radians(maxdeg) ** 2, n)) * 180 / np.pi)
        ph = rng.uniform(0, 2 * np.pi, n)
        return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)

    t = np.radians(30)
    ph = np.arange(8) * np.pi / 4
    ring = np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.full(8, np.cos(t))], -1)
    return {"ring8_30deg": ring, "random12_60deg": rand(12, 60), "random20_70deg": rand(20, 70)}


def write_folder(path: Path, images, bits, K=None, extra=None):
    from gpps.io import save_png, save_txt

    path.mkdir(parents=True, exist_ok=True)
    q = np.clip(images, 0, 1)
    for k, im in enumerate(q):
        save_png(path / f"{k + 1:03d}.png", im, bits=bits)
    if K is not None:
        save_txt(path / "K.txt", K)
    for name, arr in (extra or {}).items():
        save_png(path / name, arr.astype(np.uint8) * 255)


def sphere_mask(shape, camera, center, radius):
    from gpps.host.calibrate import render_spheres
    from gpps.lights import DirectionalLights

    im = render_spheres(shape, camera, [{"center": center, "radius": radius, "kind": "matte", "albedo": (1, 1, 1)}],
                        DirectionalLights(np.array([[0.0, 0.0, 1.0]])), supersample=1, intensities=np.ones((1, 3)) * 1e6)
    return im[0, ..., 0] > 0


def gpps(*args):
    cmd = [sys.executable, "-m", "gpps", "--device", "cpu", *map(str, args)]
    t = time.perf_counter()
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{p.stderr[-3000:]}")
    return p, time.perf_counter() - t


def angles(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one light set, 16 bit only")
    ap.add_argument("--no-reconstruct", action="store_true")
    ap.add_argument("--keep", default=None)
    ap.add_argument("--near", action="store_true", help="only the near-light (two-sphere) positions")
    a = ap.parse_args(argv)
    if a.near:
        return near_lights(Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="gpps_near_")))

    from gpps.host.calibrate import render_spheres
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.host.scenes import default_camera, make_scene
    from gpps.flows.synthetic import render

    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="gpps_cal_"))
    sets = light_sets()
    if a.quick:
        sets = {"random12_60deg": sets["random12_60deg"]}
    rng = np.random.default_rng(1)
    rows = []
    for cam_kind in ("orthographic", "perspective"):
        cam = default_camera(cam_kind, SIZE)
        K = np.asarray(cam.K) if cam.is_perspective else None
        scene = make_scene("bumps", SIZE, cam, albedo="texture")
        for set_name, L in sets.items():
            E = rng.uniform(0.6, 1.4, (len(L), 1)) * rng.uniform(0.85, 1.15, (len(L), 3))
            lights = DirectionalLights(L, intensities=E)
            alone = render_spheres((SIZE, SIZE), cam, [{"center": (0.4, 0.3, -10.0), "radius": 1.6, "kind": "chrome"}], lights)
            chrome_c, matte_c = (-1.05, 0.5, -10.0), (1.3, -0.6, -10.0)
            pair = render_spheres((SIZE, SIZE), cam, [{"center": chrome_c, "radius": 1.25, "kind": "chrome"},
                                                     {"center": matte_c, "radius": 1.0, "kind": "matte", "albedo": (0.7, 0.7, 0.7)}], lights)
            masks = {"chrome_mask.png": sphere_mask((SIZE, SIZE), cam, chrome_c, 1.25), "matte_mask.png": sphere_mask((SIZE, SIZE), cam, matte_c, 1.0)}
            obj = render(scene, Material("lambertian"), lights, device="cpu")
            for bits in ((16,) if a.quick else (8, 16)):
                tag = f"{cam_kind}_{set_name}_{bits}bit"
                row = {"camera": cam_kind, "lights": set_name, "n": len(L), "bits": bits}
                d1 = work / tag / "alone"
                write_folder(d1, alone, bits, K)
                gpps("calibrate-lights", d1, "--out", work / tag / "cal_alone", "--quiet")
                est = np.loadtxt(work / tag / "cal_alone" / "light_directions.txt")
                e = angles(est, L)
                row["found_outline"] = {"mean_deg": float(e.mean()), "max_deg": float(e.max())}
                d2 = work / tag / "pair"
                write_folder(d2, pair, bits, K, masks)
                gpps("calibrate-lights", d2, "--out", work / tag / "cal_pair", "--quiet")
                est2 = np.loadtxt(work / tag / "cal_pair" / "light_directions.txt")
                ei = np.loadtxt(work / tag / "cal_pair" / "light_intensities.txt")
                e2 = angles(est2, L)
                s = (ei * E).sum() / (ei * ei).sum()
                ie = np.abs(ei * s - E) / E
                row["masks"] = {"mean_deg": float(e2.mean()), "max_deg": float(e2.max()),
                                "intensity_mean_rel_error": float(ie.mean()), "intensity_max_rel_error": float(ie.max())}
                msg = (f"{tag:38s} directions: found outline {e.mean():.3f} (max {e.max():.3f}) deg, masks {e2.mean():.3f} (max {e2.max():.3f}) deg; "
                       f"intensities {100 * ie.mean():.2f}% (max {100 * ie.max():.2f}%)")
                if not a.no_reconstruct:
                    from gpps.io import Dataset, write_dataset

                    d3 = work / tag / "object"
                    q = np.round(np.clip(obj, 0, 1) * (2**bits - 1)) / (2**bits - 1)
                    write_dataset(d3, Dataset(images=q, mask=scene.mask, light_directions=L, light_intensities=E,
                                              K=K, normal_gt=scene.normals, material={"brdf": "lambertian"}), bits=bits)
                    p1, t1 = gpps("reconstruct", d3, "--out", work / tag / "rec_true", "--json", "--quiet")
                    p2, t2 = gpps("reconstruct", d3, "--lights", work / tag / "cal_pair", "--out", work / tag / "rec_cal", "--json", "--quiet")
                    m1, m2 = json.loads(p1.stdout)["maen_deg"], json.loads(p2.stdout)["maen_deg"]
                    n1, n2 = np.load(work / tag / "rec_true" / "normals.npy"), np.load(work / tag / "rec_cal" / "normals.npy")
                    between = float(angles(n1[scene.mask], n2[scene.mask]).mean())
                    row["reconstruct"] = {"maen_true_lights": m1, "maen_calibrated": m2, "difference": m2 - m1,
                                          "mean_angle_between_normal_maps": between, "seconds": [t1, t2]}
                    msg += f"; MAEN true {m1:.3f}, calibrated {m2:.3f} (diff {m2 - m1:+.3f}, maps {between:.3f}) deg"
                print(msg, flush=True)
                rows.append(row)
    from gpps.io import save_json

    out = ROOT / "perf" / "results" / "calibrate_spheres.json"
    save_json(out, {"size": SIZE, "rows": rows,
                    "worst_direction_deg": max(max(r["found_outline"]["max_deg"], r["masks"]["max_deg"]) for r in rows),
                    "worst_mean_direction_deg": max(max(r["found_outline"]["mean_deg"], r["masks"]["mean_deg"]) for r in rows),
                    "worst_maen_difference": max((abs(r["reconstruct"]["difference"]) for r in rows if "reconstruct" in r), default=None)})
    print(f"wrote {out}")


def near_lights(work: Path):
    from gpps.host.calibrate import render_spheres
    from gpps.lights import PointLights
    from gpps.host.scenes import default_camera

    cam = default_camera("perspective", SIZE)
    rng = np.random.default_rng(7)
    centre = np.array([0.0, 0.0, -10.0])
    dirs = light_sets()["random12_60deg"]
    P = centre + dirs * rng.uniform(6, 12, (len(dirs), 1))
    spheres = [{"center": (-1.2, 0.9, -10.0), "radius": 1.0, "kind": "chrome"}, {"center": (1.2, -0.9, -10.0), "radius": 1.0, "kind": "chrome"}]
    imgs = render_spheres((SIZE, SIZE), cam, spheres, PointLights(P), source_deg=2.0)
    mask = sphere_mask((SIZE, SIZE), cam, spheres[0]["center"], 1.0) | sphere_mask((SIZE, SIZE), cam, spheres[1]["center"], 1.0)
    rows = []
    for bits in (8, 16):
        d = work / f"near_{bits}"
        write_folder(d, imgs, bits, np.asarray(cam.K), {"chrome_mask.png": mask})
        gpps("calibrate-lights", d, "--sphere-radius", "1.0", "--out", work / f"near_{bits}_cal", "--quiet")
        est = np.loadtxt(work / f"near_{bits}_cal" / "light_positions.txt")
        rel = np.linalg.norm(est - P, axis=1) / np.linalg.norm(P - centre, axis=1)
        rows.append({"bits": bits, "mean_relative_error": float(rel.mean()), "max_relative_error": float(rel.max())})
        print(f"near lights, two spheres of radius 1 (~{cam.fx / 10:.0f} px), {bits} bit: position error {100 * rel.mean():.2f}% "
              f"(max {100 * rel.max():.2f}%) of the light's distance", flush=True)
    from gpps.io import save_json

    save_json(ROOT / "perf" / "results" / "calibrate_near_lights.json", {"size": SIZE, "lights": len(P), "rows": rows})


if __name__ == "__main__":
    main()
