"""Analytic scenes with cast shadows for RON's cast-shadow pass (tests/test_ron_shadows.py, perf/ron_shadows.py).

``bumps``: a smooth height field ``z = -D + sum_i A_i exp(-|xy - c_i|^2 / (2 s_i^2))`` (Gaussian bumps on a plane)
seen by a 12-degree pinhole (``f = D`` pixels: a 1-unit pixel on the plane).  Everything comes from the analytic
surface, independent of any depth map or of :mod:`gpps.kernels.shadows`:

* depth: each camera ray ``t (x_n, y_n, -1)`` meets the surface where ``t = D - h(t x_n, t y_n)`` (fixed-point
  iteration: ``|grad h| |x_n| < 0.1``, contracting; iterated to 1e-10 units);
* normals: ``(-h_x, -h_y, 1)`` normalised;
* visibility: from each surface point a 3D march toward each light in steps of 0.05 units (a twentieth of a pixel)
  against ``h`` itself, until the ray rises above the highest bump (or reaches a point light): shadowed where
  ``z < -D + h(x, y)`` at some sample after the first 0.05 units.

Rendered by :class:`gpps.pipeline.render.Renderer` (no shadows there) and multiplied by the visibility.  A smooth
height field integrates well from its normals (no depth discontinuity, slopes under 45 degrees), so the march
over the rounds' integrated depth can find the shadows; the cast-shadow set is ``~visible & facing`` (facing:
``n . l > 0``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps.camera import Perspective
from gpps.flows.ron import RON, RONConfig
from gpps.lights import DirectionalLights, PointLights, ring_directions, spiral_directions
from gpps.material import Material
from gpps.pipeline.render import Renderer, add_noise

#: (A, cx, cy, s) of each bump, in units of the image side S (a 1-unit pixel on the plane)
BUMPS = ((0.19, -0.12, 0.08, 0.13), (0.12, 0.22, -0.16, 0.09))
MATERIAL = Material("blinn-phong", ks=0.4, shininess=40.0)
ALBEDO = (0.7, 0.6, 0.5)


@dataclass
class BumpScene:
    camera: Perspective
    depth: np.ndarray
    mask: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    plane_depth: float
    bumps: np.ndarray  # (B, 4) A, cx, cy, s in scene units

    def height(self, x, y):
        h = np.zeros(np.broadcast(x, y).shape)
        for a, cx, cy, s in self.bumps:
            h = h + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        return h

    def grad(self, x, y):
        gx = np.zeros(np.broadcast(x, y).shape)
        gy = np.zeros_like(gx)
        for a, cx, cy, s in self.bumps:
            e = a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
            gx = gx - e * (x - cx) / (s * s)
            gy = gy - e * (y - cy) / (s * s)
        return gx, gy

    def light_dirs(self, lights):
        """(N, H, W, 3) unit directions toward each light and the distances (N, H, W) (inf: directional)."""
        p = self.points
        if isinstance(lights, DirectionalLights):
            l = np.broadcast_to(lights.directions[:, None, None, :], (len(lights),) + p.shape)
            return l, np.full(l.shape[:3], np.inf)
        d = lights.positions[:, None, None, :] - p[None]
        r = np.linalg.norm(d, axis=-1)
        return d / r[..., None], r

    def visible(self, lights, step: float = 0.05) -> np.ndarray:
        """(N, H, W) bool: the 3D march against the analytic height field (module docstring)."""
        l, tmax = self.light_dirs(lights)
        p = np.broadcast_to(self.points[None], l.shape)
        top = -self.plane_depth + float(self.bumps[:, 0].sum())
        vis = np.ones(l.shape[:3], bool)
        act = np.ones(l.shape[:3], bool)
        t = step
        while act.any():
            q = p + t * l
            z_surf = -self.plane_depth + self.height(q[..., 0], q[..., 1])
            hit = act & (q[..., 2] < z_surf) & (t < tmax)
            vis &= ~hit
            act &= ~hit & (t < tmax) & ~((q[..., 2] > top) & (l[..., 2] >= 0))
            act &= q[..., 2] > -self.plane_depth - 1.0  # (below the plane: the plane itself stops it: hit above)
            t += step
        return vis

    def facing(self, lights) -> np.ndarray:
        l, _ = self.light_dirs(lights)
        return np.einsum("khwc,hwc->khw", l, self.normals) > 0


def bump_scene(size: int = 64, bumps=BUMPS) -> BumpScene:
    """The bumps (``(A, cx, cy, s)`` each, in image sides) at image side ``size`` (module docstring)."""
    d0 = 4.75 * size
    f = d0
    cam = Perspective([[f, 0, (size - 1) / 2 + 1.5], [0, f, (size - 1) / 2 - 1.0], [0, 0, 1]])
    bumps = np.array(bumps, float) * size
    sc = BumpScene(cam, None, np.ones((size, size), bool), None, None, d0, bumps)
    o, d = cam.rays((size, size))
    d = d / (-d[..., 2:3])  # t = depth
    t = np.full((size, size), d0)
    for _ in range(200):
        q = o + d * t[..., None]
        t_new = d0 - sc.height(q[..., 0], q[..., 1])
        if np.max(np.abs(t_new - t)) < 1e-10:
            t = t_new
            break
        t = t_new
    sc.depth = t
    sc.points = o + d * t[..., None]
    gx, gy = sc.grad(sc.points[..., 0], sc.points[..., 1])
    n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
    sc.normals = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return sc


def bump_lights(kind: str, n: int, size: int, plane_depth: float, slant: float = 60.0):
    """3 lights on a ring at slant 60 degrees (elevation 30: long shadows) or ``n`` on a spiral with slants
    20-65; point lights 3 S units from the plane's centre in those directions (radiance about 1 there)."""
    dirs = ring_directions(n, slant) if n <= 4 else spiral_directions(n, 20.0, slant)
    if kind == "directional":
        return DirectionalLights(dirs)
    r = 3.0 * size
    return PointLights(np.array([0.0, 0.0, -plane_depth]) + r * dirs, np.full((n, 3), r * r))


def bump_case(kind: str, n: int, size: int = 64, noise: float = 0.002, seed: int = 0, bumps=BUMPS,
              slant: float = 60.0) -> dict:
    """RON's inputs on the bumps with their exact cast shadows, and the truth."""
    sc = bump_scene(size, bumps)
    lights = bump_lights(kind, n, size, sc.plane_depth, slant)
    with Renderer((size, size), sc.camera, lights, MATERIAL) as r:
        img = r.run(sc.depth, sc.mask, np.array(ALBEDO), normals=sc.normals)
    vis = sc.visible(lights)
    img = np.clip(add_noise(img * vis[..., None], noise, seed), 0.0, None).astype(np.float32)
    return {"images": img, "mask": sc.mask, "camera": sc.camera, "lights": lights, "material": MATERIAL,
            "normals": sc.normals, "depth": sc.depth, "shadow": ~vis & sc.facing(lights), "visible": vis,
            "reference_depth": float(sc.depth.mean()), "scene": sc}


def solid_case(name: str, kind: str, n: int, size: int = 64, camera: str = "perspective", noise: float = 0.002,
               seed: int = 0) -> dict:
    """tests/shadow_reference.py's hemisphere (radius 0.3 S) or box (0.31 S tall) on a plane filling the S x S image,
    orthographic (1-unit pixel, plane at 4.75 S) or perspective (12 degrees, a 1-unit pixel on the plane); 3 lights
    at slant 45 or ``n`` on a spiral (slants 15-60), point lights 3 S from the plane's centre.  Rendered, times the
    exact visibility (ray-box / ray-sphere in 3D), with noise: RON's inputs and the truth."""
    from shadow_reference import box_scene, hemisphere_scene, perspective

    from gpps.camera import Orthographic

    dp = 4.75 * size
    cam = perspective(dp, (size, size)) if camera == "perspective" else Orthographic(1.0)
    s = size / 128.0
    if name == "hemisphere":
        sc = hemisphere_scene(cam, shape=(size, size), plane_depth=dp, radius=0.3 * size)
    else:
        sc = box_scene(cam, shape=(size, size), plane_depth=dp, box=(-24 * s, 16 * s, -16 * s, 20 * s, 40 * s))
    dirs = ring_directions(n, 45.0) if n <= 4 else spiral_directions(n, 15.0, 60.0)
    if kind == "directional":
        lights = DirectionalLights(dirs)
    else:
        r = 3.0 * size
        lights = PointLights(np.array([0.0, 0.0, -dp]) + r * dirs, np.full((n, 3), r * r))
    with Renderer((size, size), cam, lights, MATERIAL) as rd:
        img = rd.run(sc.depth, sc.mask, np.array(ALBEDO), normals=sc.normals)
    vis = sc.visible(lights)
    img = np.clip(add_noise(img * vis[..., None], noise, seed), 0.0, None).astype(np.float32)
    return {"images": img, "mask": sc.mask, "camera": cam, "lights": lights, "material": MATERIAL,
            "normals": sc.normals, "depth": sc.depth, "shadow": ~vis & sc.facing(lights), "visible": vis,
            "reference_depth": float(sc.depth[sc.mask].mean()), "scene": sc}


def write_case_folder(case, path):
    """A case of this module (directional lights) as a 16-bit capture folder at ``path`` (images, mask, lights,
    intrinsics and the ground truth, as users have it): ``gpps.reconstruct_folder``'s input.  Returns the folder."""
    from gpps.io import Dataset, write_dataset

    n = len(case["lights"])
    ds = Dataset(images=case["images"], mask=case["mask"], light_directions=case["lights"].directions,
                 light_intensities=np.ones((n, 3), np.float32), K=np.asarray(case["camera"].K),
                 normal_gt=case["normals"], depth_gt=case["depth"], filenames=[f"{i:03d}.png" for i in range(1, n + 1)])
    return write_dataset(path, ds, bits=16)


def run_ron(device, case, **cfg):
    """RON on a case of this module (its lights, material and mask, its reference depth), ``RONConfig(**cfg)``."""
    n = len(case["lights"])
    ron = RON((n,) + case["mask"].shape, case["camera"], case["lights"], case["material"], case["mask"],
              RONConfig(**cfg), device=device)
    try:
        return ron.run(case["images"], reference_depth=case["reference_depth"])
    finally:
        ron.close()
