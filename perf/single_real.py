"""``gpps.reconstruct_single`` on real images (issue 24): DiLiGenT ball and bear with one and three images
(MAEN against their ground truth), Beethoven's three images and a frontal Yale B face (no ground truth: views).

Image choice (fixed by a rule, not by score): on DiLiGenT the three images whose light directions have the
largest ``|det|`` (the best-conditioned triple for photometric stereo); the one-image rows run each image of
that triple alone and report each and their mean.  Images are divided by their light intensities (DiLiGenT's
calibration of the LED brightness); nothing else of the calibration is used.  Views: one PNG per set
(input, the network's normals, the refined normals, and the ground truth where there is one; normals
coloured as ``(n + 1) / 2``, RGB = xyz).

    python perf/single_real.py [--data ../shared/data] [--device cpu] [--out-dir perf/results/single_real]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_triple, write_results  # noqa: E402


def _read16(path):
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32) / 65535.0


def _view(images, m, panels):
    im = images[0] / max(np.percentile(images[0][m], 99), 1e-6)
    cols = [np.clip(im, 0, 1) if im.ndim == 3 else np.repeat(np.clip(im, 0, 1)[..., None], 3, -1)]
    cols += [(n * 0.5 + 0.5) * m[..., None] for n in panels]
    return (np.concatenate(cols, 1)[..., ::-1] * 255).astype(np.uint8)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out-dir", default=str(ROOT / "perf" / "results" / "single_real"))
    ap.add_argument("--weights", default=None, help="the single-image network's weights file (default: the shipped one)")
    ap.add_argument("--tag", default=None, help="results name suffix: perf/results/single_real_<tag>_<device>.json")
    a = ap.parse_args(argv)
    import gpps
    from gpps.nn.model import SingleNet

    net = SingleNet.load(a.weights)
    from gpps.host.metrics import normal_errors

    data, out = Path(a.data), Path(a.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for obj in ("ball", "bear"):
        d = data / "diligent" / obj
        L = np.loadtxt(d / "light_directions.txt")
        E = np.loadtxt(d / "light_intensities.txt")
        m = cv2.imread(str(d / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
        gt = np.load(d / "normal_gt.npy")
        tri = list(best_triple(L))
        imgs = np.stack([_read16(d / f"{k + 1:03d}.png") / E[k] for k in tri])
        runs = [(f"1:{tri[i] + 1:03d}", imgs[i:i + 1]) for i in range(3)] + [(f"3:{'/'.join(f'{k + 1:03d}' for k in tri)}", imgs)]
        for label, im in runs:
            t = time.perf_counter()
            res = gpps.reconstruct_single(im, m, device=a.device, net=net)
            dt = time.perf_counter() - t
            e_net = normal_errors(res.normals_net, gt, res.mask)["mean"]
            e_ref = normal_errors(res.normals, gt, res.mask)["mean"]
            rows.append({"object": obj, "images": label, "n_images": len(im), "maen_net": e_net, "maen": e_ref, "seconds": dt})
            print(f"{obj} {label}: network {e_net:.2f} deg, refined {e_ref:.2f} deg ({dt:.1f} s)", flush=True)
            cv2.imwrite(str(out / f"{obj}_{len(im)}img_{label.split(':')[1].replace('/', '-')}.png"),
                        _view(im, res.mask, [res.normals_net, res.normals, gt]))
    flat = {}
    for obj in ("ball", "bear"):
        d = data / "diligent" / obj
        m = cv2.imread(str(d / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
        gt = np.load(d / "normal_gt.npy")
        f = np.zeros_like(gt)
        f[..., 2] = 1
        flat[obj] = normal_errors(f, gt, m)["mean"]
    summary = {}
    for obj in ("ball", "bear"):
        one = [r for r in rows if r["object"] == obj and r["n_images"] == 1]
        three = [r for r in rows if r["object"] == obj and r["n_images"] == 3][0]
        summary[obj] = {"flat": flat[obj], "one_image_net_mean": float(np.mean([r["maen_net"] for r in one])),
                        "one_image_refined_mean": float(np.mean([r["maen"] for r in one])),
                        "three_images_net": three["maen_net"], "three_images_refined": three["maen"]}
        print(obj, {k: round(v, 2) for k, v in summary[obj].items()})
    # views without ground truth: Beethoven's three images, Yale B01's frontal light
    b = data / "beethoven"
    bi = sorted(p for p in b.iterdir() if p.suffix.lower() in (".png", ".bmp", ".jpg", ".tif") and "mask" not in p.name)
    bm = cv2.imread(str(b / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    bimg = np.stack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0 for p in bi[:3]])
    res = gpps.reconstruct_single(bimg, bm, device=a.device, net=net)
    cv2.imwrite(str(out / "beethoven_3img.png"), _view(bimg, res.mask, [res.normals_net, res.normals]))
    y = data / "yaleb" / "yaleB01"
    yf = sorted(y.glob("*P00A+000E+00.pgm"))[0]
    yim = cv2.imread(str(yf), cv2.IMREAD_UNCHANGED).astype(np.float32) / 255.0
    ym = np.ones(yim.shape, bool)
    res = gpps.reconstruct_single(yim, ym, device=a.device, net=net)
    cv2.imwrite(str(out / "yaleB01_1img.png"), _view(yim[None], res.mask, [res.normals_net, res.normals]))
    name = f"single_real_{a.tag}" if a.tag else "single_real"
    print("wrote", write_results(name, a.device, {"rows": rows, "summary": summary, "weights": a.weights or "shipped",
                                                   "rule": "DiLiGenT: the best-conditioned light triple"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
