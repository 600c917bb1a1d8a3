"""The embedded demo: render a perspective Blinn-Phong scene with strong highlights and reconstruct it."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gpps.io import atomic_dir, save_json, save_npy, save_png, write_dataset
from gpps.material import Material
from gpps.scenes import make_scene
from gpps.synthetic import default_lights, render_dataset


def _angular_error_deg(a, b, mask):
    c = np.clip(np.sum(a[mask] * b[mask], -1), -1.0, 1.0)
    return np.degrees(np.arccos(c))


def _woodham(images, mask, directions):
    """Lambertian least squares on grey images (the baseline), numpy."""
    grey = images.mean(-1)[:, mask]  # (N, P)
    b, *_ = np.linalg.lstsq(directions, grey, rcond=None)  # (3, P)
    rho = np.linalg.norm(b, axis=0)
    n = np.zeros(mask.shape + (3,), np.float32)
    n[mask] = (b / np.maximum(rho, 1e-12)).T
    return n


def run_demo(out: Path, *, size: int = 256, device=None, progress=None) -> dict:
    """Render the demo scene into ``out/capture`` and write the reconstruction beside it.

    Returns the report (also written to ``out/report.json``).
    """
    step = progress or (lambda *a, **k: None)
    t0 = time.perf_counter()
    scene = make_scene("bumps", size, "perspective", albedo="texture")
    material = Material("blinn-phong", ks=0.6, shininess=40.0)
    lights = default_lights("directional", 3)
    ds = render_dataset(scene, material, lights, bits=16, device=device)
    t_render = time.perf_counter() - t0
    step(1, 3, "rendered")
    with atomic_dir(out) as tmp:
        write_dataset(tmp / "capture", ds)
        step(2, 3, "written")
        t1 = time.perf_counter()
        images = ds.images / lights.intensities[:, None, None, :]
        normals = _woodham(images, scene.mask, lights.directions)
        t_rec = time.perf_counter() - t1
        err = _angular_error_deg(normals, scene.normals, scene.mask)
        save_npy(tmp / "normals.npy", normals)
        save_png(tmp / "normals.png", (normals + 1) / 2 * scene.mask[..., None], bits=8)
        report = {
            "scene": {"name": "bumps", "size": size, "camera": "perspective", "lights": "3 directional", "material": material.to_dict()},
            "method": "Lambertian least squares (Woodham)",
            "timings_s": {"render": t_render, "reconstruct": t_rec},
            "summary": {
                "method": "Lambertian least squares",
                "MAEN (deg)": round(float(err.mean()), 3),
                "median angular error (deg)": round(float(np.median(err)), 3),
                "render time (s)": round(t_render, 3),
                "reconstruction time (s)": round(t_rec, 3),
            },
        }
        save_json(tmp / "report.json", report)
    step(3, 3, "done")
    return report
