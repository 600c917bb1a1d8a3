"""References for the cast-shadow march (tests/test_shadows.py, perf/shadows.py).

* Analytic scenes in closed form: a box on a plane (a step) and a hemisphere on a plane, seen by either camera;
  depth, normals and each light's visibility come from ray casting in 3D (camera ray: first hit of the plane and
  the solid; light ray: slab test against the box, ray-sphere roots for the hemisphere) - independent of the
  depth map and of the march.
* :func:`march_reference`: the march of :mod:`gpps.kernels.shadows` in numpy float64, vectorised over all
  (light, pixel) rays (the same rule, sampling and tolerance, written from the module's docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps.camera import Perspective
from gpps.lights import DirectionalLights


def light_rays(lights, points):
    """Unit directions (N, M, 3) from ``points`` (M, 3) toward each light and the distances (N, M) (inf for
    directional lights)."""
    if isinstance(lights, DirectionalLights):
        l = np.broadcast_to(lights.directions[:, None, :], (len(lights), len(points), 3))
        return l, np.full(l.shape[:2], np.inf)
    d = lights.positions[:, None, :] - points[None]
    r = np.linalg.norm(d, axis=-1)
    return d / r[..., None], r


def camera_rays(camera, shape):
    """Origins and directions (H, W, 3) of the camera rays, scaled so that ``t`` is the depth (d = -z)."""
    o, d = camera.rays(shape)
    return o, d / (-d[..., 2:3])


@dataclass
class Scene:
    """An analytic scene: depth (H, W), mask (H, W), points (H, W, 3), normals (H, W, 3) and the solid."""

    camera: object
    depth: np.ndarray
    mask: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    kind: str
    plane_depth: float
    box: tuple | None = None  # (x0, x1, y0, y1, height)
    sphere: tuple | None = None  # (cx, cy, cz, radius)

    def visible(self, lights) -> np.ndarray:
        """(N, H, W) bool: the ray from each surface point toward each light meets no part of the solid (the
        plane is a half-space: a ray that goes below it is shadowed)."""
        h, w = self.depth.shape
        p = self.points.reshape(-1, 3)
        l, tmax = light_rays(lights, p)
        eps = 1e-6 * self.plane_depth
        z0 = -self.plane_depth
        # below the plane (the half-space behind it): a ray that sinks under z0 before reaching the light
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = np.where(l[..., 2] < 0, (z0 - p[None, :, 2]) / l[..., 2], np.inf)
        hit = (t_plane > -eps) & (t_plane < tmax) & (l[..., 2] < 0)
        if self.box is not None:
            x0, x1, y0, y1, hb = self.box
            lo = np.array([x0, y0, z0 - 1.0])
            hi = np.array([x1, y1, z0 + hb])
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / l
                ta = (lo - p[None]) * inv
                tb = (hi - p[None]) * inv
            ta = np.where(np.isnan(ta), -np.inf, ta)  # a zero direction inside its slab: no bound
            tb = np.where(np.isnan(tb), np.inf, tb)
            tn = np.max(np.minimum(ta, tb), axis=-1)
            tf = np.min(np.maximum(ta, tb), axis=-1)
            hit |= (tn <= tf) & (tf > eps) & (tn < tmax)
        if self.sphere is not None:
            c = np.asarray(self.sphere[:3])
            r = self.sphere[3]
            oc = p[None] - c
            b = np.sum(oc * l, axis=-1)
            cc = np.sum(oc * oc, axis=-1) - r * r
            disc = b * b - cc
            sq = np.sqrt(np.maximum(disc, 0))
            t1, t2 = -b - sq, -b + sq
            # the first root past the start (a point on the sphere has a root at 0: the other one counts)
            tt = np.where(t1 > eps * 10, t1, t2)
            z_hit = p[None, :, 2] + tt * l[..., 2]
            hit |= (disc > 0) & (tt > eps * 10) & (tt < tmax) & (z_hit > z0)
        return ~hit.reshape(len(lights), h, w)

    def facing(self, lights) -> np.ndarray:
        """(N, H, W) bool: n . l > 0 (not in an attached shadow)."""
        p = self.points.reshape(-1, 3)
        l, _ = light_rays(lights, p)
        return (np.sum(l * self.normals.reshape(1, -1, 3), axis=-1) > 0).reshape(len(lights), *self.depth.shape)


def box_scene(camera, shape=(128, 128), plane_depth=150.0, box=(-24.0, 16.0, -16.0, 20.0, 40.0)) -> Scene:
    """A box (x0..x1, y0..y1, height toward the camera) standing on the plane z = -plane_depth."""
    o, d = camera_rays(camera, shape)
    x0, x1, y0, y1, hb = box
    z0 = -plane_depth
    lo = np.array([x0, y0, z0 - 1.0])
    hi = np.array([x1, y1, z0 + hb])
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - o) / d
        tb = (hi - o) / d
    ta = np.where(np.isnan(ta), -np.inf, ta)
    tb = np.where(np.isnan(tb), np.inf, tb)
    tn = np.max(np.minimum(ta, tb), axis=-1)
    tf = np.min(np.maximum(ta, tb), axis=-1)
    on_box = (tn <= tf) & (tn > 0) & (tn < plane_depth)
    depth = np.where(on_box, tn, plane_depth)
    pts = o + d * depth[..., None]
    nrm = np.zeros_like(pts)
    nrm[..., 2] = 1.0
    # the walls (seen by the perspective camera when the box is off the axis): the slab that bounds tn
    axis = np.argmax(np.minimum(ta, tb), axis=-1)
    wall = on_box & (axis < 2)
    for a in (0, 1):
        sel = wall & (axis == a)
        nrm[sel] = 0.0
        nrm[sel, a] = -np.sign(d[sel, a])
    return Scene(camera, depth, np.ones(shape, bool), pts, nrm, "box", plane_depth, box=box)


def hemisphere_scene(camera, shape=(128, 128), plane_depth=150.0, radius=40.0, center_xy=(0.0, 0.0)) -> Scene:
    """A hemisphere of ``radius`` centred on the plane z = -plane_depth."""
    o, d = camera_rays(camera, shape)
    c = np.array([center_xy[0], center_xy[1], -plane_depth])
    oc = o - c
    dd = np.sum(d * d, axis=-1)
    b = np.sum(oc * d, axis=-1)
    cc = np.sum(oc * oc, axis=-1) - radius ** 2
    disc = b * b - dd * cc
    t1 = (-b - np.sqrt(np.maximum(disc, 0))) / dd
    on = (disc > 0) & (t1 < plane_depth)
    depth = np.where(on, t1, plane_depth)
    pts = o + d * depth[..., None]
    nrm = np.where(on[..., None], (pts - c) / radius, np.array([0.0, 0.0, 1.0]))
    return Scene(camera, depth, np.ones(shape, bool), pts, nrm, "hemisphere", plane_depth,
                 sphere=(c[0], c[1], c[2], radius))


def directional(elevations_deg, azimuths_deg) -> DirectionalLights:
    """Directional lights at elevations above the image plane and azimuths from +x toward +y (degrees)."""
    e = np.deg2rad(np.asarray(elevations_deg, float))
    a = np.deg2rad(np.asarray(azimuths_deg, float))
    return DirectionalLights(np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1))


def perspective(plane_depth, shape=(128, 128)) -> Perspective:
    """A pinhole with ``f = plane_depth`` pixels (a 1-unit pixel on the plane) and its principal point 3 pixels
    right and 2 up of the image centre."""
    h, w = shape
    f = float(plane_depth)
    return Perspective([[f, 0, (w - 1) / 2 + 3.0], [0, f, (h - 1) / 2 - 2.0], [0, 0, 1]])


def footprint(camera, depth):
    """Side of one pixel on a surface at ``depth`` (the kernel's ``footprint``)."""
    return _footprint(camera, np.asarray(depth, np.float64))


def iou(a, b) -> float:
    """|a & b| / |a | b| of two boolean sets (1.0 when both are empty)."""
    u = np.count_nonzero(a | b)
    return 1.0 if u == 0 else np.count_nonzero(a & b) / u


# ------------------------------------------------------------------------------------------------ the march


def _footprint(camera, d):
    if isinstance(camera, Perspective):
        return d / max(camera.fx, camera.fy)
    return np.full_like(d, camera.pixel_size)


def _project(camera, p, shape):
    if isinstance(camera, Perspective):
        cx, cy = camera.principal_point()
        dd = -p[:, 2]
        return cx + camera.fx * p[:, 0] / dd, cy - camera.fy * p[:, 1] / dd
    cx, cy = camera.principal_point(shape)
    s = camera.pixel_size
    return cx + p[:, 0] / s, cy - p[:, 1] / s


def _speed(camera, p, l):
    if isinstance(camera, Perspective):
        d = -p[:, 2]
        du = camera.fx * (l[:, 0] * d + p[:, 0] * l[:, 2]) / d ** 2
        dv = -camera.fy * (l[:, 1] * d + p[:, 1] * l[:, 2]) / d ** 2
        return np.hypot(du, dv)
    return np.hypot(l[:, 0], l[:, 1]) / camera.pixel_size


def _depth_at(depth, mask, u, v):
    h, w = depth.shape
    j, i = np.floor(u + 0.5).astype(np.int64), np.floor(v + 0.5).astype(np.int64)
    inside = (i >= 0) & (j >= 0) & (i < h) & (j < w)
    ic, jc = np.clip(i, 0, h - 1), np.clip(j, 0, w - 1)
    return np.where(inside & mask[ic, jc], depth[ic, jc], -1.0)


def march_reference(depth, mask, camera, lights, *, tau=1.0, step_px=1.0, max_steps=None) -> np.ndarray:
    """(N, H, W) bool visibility by the rule of :mod:`gpps.kernels.shadows`, in float64 numpy."""
    depth = np.asarray(depth, np.float64)
    mask = np.asarray(mask, bool)
    h, w = depth.shape
    n = len(lights)
    if max_steps is None:
        max_steps = int(np.ceil(2 * (h + w) / step_px))
    vis = np.ones((n, h, w), bool)
    if not mask.any():
        return vis
    pts = camera.backproject(np.where(mask, depth, 1.0))[mask]  # (M, 3)
    l, tend = light_rays(lights, pts)
    m = len(pts)
    p0 = np.broadcast_to(pts[None], (n, m, 3)).reshape(-1, 3)
    l = l.reshape(-1, 3)
    tend = tend.reshape(-1)
    dmin = depth[mask].min()
    fp = _footprint(camera, -p0[:, 2])
    tol = tau * fp
    floor_speed = 1.0 / (8.0 * fp)
    t = np.zeros(len(p0))
    res = np.ones(len(p0), bool)
    act = np.arange(len(p0))
    for _ in range(max_steps):
        if act.size == 0:
            break
        p = p0[act] + t[act, None] * l[act]
        t[act] += step_px / np.maximum(_speed(camera, p, l[act]), floor_speed[act])
        p = p0[act] + t[act, None] * l[act]
        dr = -p[:, 2]
        done = (t[act] >= tend[act]) | (dr <= 0) | ((l[act, 2] > 0) & (dr - tol[act] < dmin))
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = _project(camera, p, (h, w))
        done |= ~((u >= -0.5) & (v >= -0.5) & (u <= w - 0.5) & (v <= h - 0.5))
        ds = _depth_at(depth, mask, np.where(done, 0.0, u), np.where(done, 0.0, v))
        shadow = ~done & (ds > 0) & (ds < dr - tol[act])
        res[act[shadow]] = False
        act = act[~(done | shadow)]
    vis[:, mask] = res.reshape(n, m)
    return vis


def planes_under_cast_shadows(device, seed=1, h=12, w=12, brdf="blinn-phong"):
    """Planes of ``brdf`` (Blinn-Phong ks 0.2, n 20; others ks 0.5, roughness 0.3; normals within 40 deg of the
    view, albedo 0.3-0.7) under 5 directional lights at 30-65 deg elevation; in every pixel one light (two in 30 %)
    casts a shadow where it faces the surface by n.l > 0.2, the observation replaced by 0-4 % of the albedo (light
    bounced from elsewhere), then noise 0.002 (the scene of the cast-shadow refit's test and
    perf/cast_misfit_planes.py).  ``(dirs, mat, normals, shadowed (N, H, W) bool, images)``."""
    from gpps.camera import Orthographic
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.render import Renderer

    rng = np.random.default_rng(seed)
    nl = 5
    el = np.radians(rng.uniform(30, 65, nl))
    az = np.radians(np.arange(nl) * 360 / nl + rng.uniform(-20, 20, nl))
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    t = np.radians(rng.uniform(0, 40, (h, w)))
    p = rng.uniform(0, 2 * np.pi, (h, w))
    nrm = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).astype(np.float32)
    kd = rng.uniform(0.3, 0.7, (h, w, 1)).repeat(3, -1).astype(np.float32)
    mat = Material(brdf, ks=0.2, shininess=20.0) if brdf == "blinn-phong" else Material(brdf, ks=0.5, roughness=0.3)
    img = Renderer((h, w), Orthographic(), DirectionalLights(dirs), mat, device=device).run(
        np.ones((h, w), np.float32), np.ones((h, w), bool), kd, normals=nrm)
    k1 = rng.integers(0, nl, (h, w))
    two = rng.random((h, w)) < 0.3
    k2 = (k1 + rng.integers(1, nl, (h, w))) % nl
    shad = np.stack([(k1 == k) | (two & (k2 == k)) for k in range(nl)]) & (np.einsum("hwc,kc->khw", nrm, dirs) > 0.2)
    dark = rng.uniform(0.0, 0.04, (nl, h, w))[..., None] * kd[None]
    img = np.where(shad[..., None], dark, img)
    img = np.maximum(img + rng.normal(0, 0.002, img.shape), 0).astype(np.float32)
    return dirs, mat, nrm, shad, img
