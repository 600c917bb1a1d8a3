"""Photometric-stereo captures rendered by Mitsuba 3, an independent physically based renderer.

gpps's own renderer draws its own image model (no cast shadows, no interreflections, its five BRDFs),
so captures made with it hide what breaks gpps on real objects (issues 24 and 25).  This module renders
captures with Mitsuba 3's path tracer instead (CPU variant ``scalar_rgb``; the ``llvm_ad_rgb`` variant
aborts in LLVM's instruction selection on this machine's LLVM) and writes them as gpps capture folders
(:func:`gpps.io.read_capture` / :func:`gpps.reconstruct_folder` read them):

* shapes with concavities and self-shadowing (:data:`SHAPES`): height fields (``bumps``, ``bowl``,
  ``ridges``), compositions on a support plane (``sphere_on_plane``, ``spheres``, ``torus``), a stepped
  relief of boxes (``steps``) and a superquadric (``superquadric``); triangle meshes carry their analytic
  vertex normals, spheres, disks and boxes are Mitsuba's own primitives;
* materials (:data:`MATERIALS`): ``diffuse``, ``roughplastic`` (GGX, ``alpha``), ``plastic`` (smooth
  dielectric coating), ``roughconductor`` (copper, GGX ``alpha``); the diffuse reflectance is a
  constant colour or a smooth random RGB texture (spatially varying albedo);
* lights: N directional lights (Mitsuba ``directional``) or N point lights (``point``) at a finite
  distance, one render per light; path tracer with ``max_depth >= 3`` (interreflections), cast shadows;
* a perspective camera in gpps's frame (:mod:`gpps.camera`: camera at the origin, x right, y up, looking
  down -z) with ``K = gpps.host.scenes.default_camera("perspective", size).K``: Mitsuba's film pixel
  ``j`` spans ``[j, j + 1)``, so its centre ``j + 0.5`` is gpps's integer pixel ``j``; the field of view
  ``2 atan(W / (2 fx))`` on the x axis (square pixels) puts the principal point at ``(W - 1) / 2``;
* radiometry matched to gpps's image model (:mod:`gpps.kernels.brdf`: ``E kd max(n.l, 0)`` for a
  Lambertian surface lit by radiance ``E``): Mitsuba's diffuse BSDF is ``kd / pi``, so a gpps light of
  intensity ``I`` is a Mitsuba ``directional`` emitter of irradiance ``pi I`` or a ``point`` emitter of
  intensity ``pi I`` (radiance ``pi I / r^2``, 2.31); tests/test_mitsuba_scenes.py renders a Lambertian
  sphere both ways and compares;
* ground truth at pixel centres by casting gpps's own camera rays into the Mitsuba scene: normals (the
  shading normal, what the BSDF sees), depth ``d = -z``, mask (pixels whose ray hits a surface facing
  the camera: ``n . v > MIN_FACING``);
* a camera: one exposure per capture (the ``exposure_percentile`` of the masked pixels maps to
  ``exposure_level`` of full scale, brighter highlights clip), Gaussian shot noise (``full_well``
  electrons at full scale) and read noise, 8- or 16-bit quantisation; ``light_intensities.txt`` holds
  ``exposure x I`` so that the reader's division leaves ``kd cos`` for a Lambertian surface.

Everything is a function of the :class:`CaptureSpec` (shape parameters, texture, lights, Mitsuba's seeds
and the noise are drawn from ``spec.seed``).  Training-time code: nothing in the runtime package imports
it; Mitsuba is the optional dependency ``gpps[render]``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from gpps._check import check_choices, check_number
from gpps.host.scenes import D0, default_camera
from gpps.io import Dataset, write_dataset
from gpps.lights import DirectionalLights, PointLights

__all__ = ["CaptureSpec", "RenderedCapture", "SHAPES", "MATERIALS", "light_rig", "render_scene", "render_capture", "write_capture",
           "make_capture", "with_lights", "default_root", "mitsuba", "VERSION"]

ShapeName = Literal["bumps", "bowl", "ridges", "sphere_on_plane", "spheres", "torus", "steps", "superquadric"]
MaterialName = Literal["diffuse", "roughplastic", "plastic", "roughconductor"]
LightKind = Literal["directional", "point"]
SHAPES: tuple[str, ...] = get_args(ShapeName)
MATERIALS: tuple[str, ...] = get_args(MaterialName)

#: bumped when the renders change: a cached capture of another version is rendered again
VERSION = 1
#: a pixel is in the mask when its ray meets a surface with ``n . v`` above this (v toward the camera)
MIN_FACING = 0.02
#: distance of point lights from the object's centre (0, 0, -D0), scene units
POINT_DISTANCE = 9.0
VARIANT = "scalar_rgb"


def mitsuba(variant: str = VARIANT):
    """The ``mitsuba`` module with ``variant`` set (ImportError naming the extra when it is absent)."""
    try:
        import mitsuba as mi  # optional: the render extra
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ImportError("gpps.training.mitsuba_scenes needs Mitsuba 3: pip install 'gpps[render]' (mitsuba>=3.5)") from e
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


@dataclass(frozen=True)
class CaptureSpec:
    """One capture to render.

    Attributes:
        shape: one of :data:`SHAPES`.
        material: one of :data:`MATERIALS`.
        light_kind: ``"directional"`` or ``"point"``.
        n_lights: number of lights (one image each, >= 1).
        alpha: GGX roughness of ``roughplastic`` / ``roughconductor`` (> 0).
        texture: spatially varying diffuse reflectance (a smooth random RGB texture) instead of one colour.
        size: image side (pixels; square images).
        spp: samples per pixel.
        max_depth: path length of Mitsuba's path tracer (>= 3: at least one interreflection).
        bits: 8 or 16.
        full_well: electrons at full scale (shot noise); 0: none.
        read_noise: standard deviation of the read noise (full scale = 1).
        exposure_percentile: percentile of the masked pixel values that maps to ``exposure_level``.
        exposure_level: its value after the exposure (full scale = 1).
        seed: shape, texture, lights, Mitsuba's sampler and the noise.
    """

    shape: ShapeName = "bumps"
    material: MaterialName = "roughplastic"
    light_kind: LightKind = "directional"
    n_lights: int = 3
    alpha: float = 0.2
    texture: bool = False
    size: int = 128
    spp: int = 64
    max_depth: int = 4
    bits: int = 16
    full_well: float = 20000.0
    read_noise: float = 5e-4
    exposure_percentile: float = 99.5
    exposure_level: float = 0.85
    seed: int = 0

    def __post_init__(self):
        check_choices(self)
        object.__setattr__(self, "n_lights", check_number("n_lights", self.n_lights, lo=1, integer=True))
        object.__setattr__(self, "alpha", check_number("alpha", self.alpha, lo=0.0, lo_open=True))
        object.__setattr__(self, "size", check_number("size", self.size, lo=8, integer=True))
        object.__setattr__(self, "spp", check_number("spp", self.spp, lo=1, integer=True))
        object.__setattr__(self, "max_depth", check_number("max_depth", self.max_depth, lo=2, integer=True))
        if self.bits not in (8, 16):
            raise ValueError(f"bits: expected 8 or 16, got {self.bits!r}")
        object.__setattr__(self, "full_well", check_number("full_well", self.full_well, lo=0.0))
        object.__setattr__(self, "read_noise", check_number("read_noise", self.read_noise, lo=0.0))
        object.__setattr__(self, "exposure_percentile", check_number("exposure_percentile", self.exposure_percentile, lo=0.0, lo_open=True, hi=100.0))
        object.__setattr__(self, "exposure_level", check_number("exposure_level", self.exposure_level, lo=0.0, lo_open=True))
        object.__setattr__(self, "seed", check_number("seed", self.seed, lo=0, integer=True))
        if not isinstance(self.texture, bool):
            raise TypeError(f"texture: expected a bool, got {self.texture!r}")

    @property
    def name(self) -> str:
        """A folder name that says what the capture is (every field that changes the images)."""
        mat = self.material + (f"{self.alpha:g}" if self.material in ("roughplastic", "roughconductor") else "")
        mat += "-tex" if self.texture else ""
        noise = f"fw{self.full_well:g}-rn{self.read_noise:g}-ex{self.exposure_percentile:g}_{self.exposure_level:g}"
        return (f"{self.shape}-{mat}-{self.light_kind}{self.n_lights}-s{self.size}-spp{self.spp}-d{self.max_depth}"
                f"-b{self.bits}-{noise}-seed{self.seed}-v{VERSION}")


@dataclass
class RenderedCapture:
    """A rendered capture before it is written.

    Attributes:
        spec: what was rendered.
        images: (N, H, W, 3) float32 in [0, 1], quantised to ``spec.bits`` (what the PNG files hold).
        linear: (N, H, W, 3) float32 noise-free renders in gpps's units (``kd cos I`` for a Lambertian
            surface), before the exposure.
        lights: the lights in gpps's frame and units (before the exposure).
        exposure: the gain applied (``light_intensities.txt`` = ``exposure x lights.intensities``).
        K: (3, 3) intrinsics (pixels).
        mask: (H, W) bool.
        normals: (H, W, 3) float32 unit ground-truth normals (gpps frame), 0 outside the mask.
        depth: (H, W) float32 depth ``-z``, 0 outside the mask.
        timings: seconds: ``scene`` (meshes, load), ``render`` (each image), ``ground_truth``.
    """

    spec: CaptureSpec
    images: np.ndarray
    linear: np.ndarray
    lights: DirectionalLights | PointLights
    exposure: float
    K: np.ndarray
    mask: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    timings: dict


# --------------------------------------------------------------------------- lights


def light_rig(kind: LightKind, n: int, seed: int = 0) -> DirectionalLights | PointLights:
    """``n`` lights around the view axis, drawn from ``seed``.

    Up to 4 lights: evenly spread azimuths (jittered by up to 15 deg) at slants 30-50 deg; more: a
    golden-angle spiral with slants 15-60 deg (jittered by 3 deg).  Directional lights have intensity 1;
    point lights sit :data:`POINT_DISTANCE` from the object's centre ``(0, 0, -D0)`` in those directions
    with intensity ``POINT_DISTANCE^2`` (radiance 1 at the centre).
    """
    rng = np.random.default_rng([int(seed), int(n), 7])
    k = np.arange(n)
    if n <= 4:
        slant = rng.uniform(30.0, 50.0, n)
        az = 90.0 + 360.0 * k / n + rng.uniform(-15.0, 15.0, n)
    else:
        slant = np.clip(15.0 + 45.0 * k / (n - 1) + rng.uniform(-3.0, 3.0, n), 5.0, 70.0)
        az = 90.0 + np.rad2deg(k * np.pi * (3.0 - np.sqrt(5.0))) + rng.uniform(-10.0, 10.0, n)
    s, a = np.deg2rad(slant), np.deg2rad(az)
    dirs = np.stack([np.sin(s) * np.cos(a), np.sin(s) * np.sin(a), np.cos(s)], axis=1)
    if kind == "directional":
        return DirectionalLights(dirs, np.ones((n, 3)))
    if kind == "point":
        pos = np.array([0.0, 0.0, -D0]) + POINT_DISTANCE * dirs
        return PointLights(pos, np.full((n, 3), POINT_DISTANCE**2))
    raise ValueError(f"light_kind: expected 'directional' or 'point', got {kind!r}")


def _emitter(lights, k: int) -> dict:
    """Mitsuba emitter of gpps light ``k`` (intensity x pi: Mitsuba's diffuse BSDF is kd / pi)."""
    value = (np.pi * np.asarray(lights.intensities[k], np.float64)).tolist()
    if isinstance(lights, DirectionalLights):
        return {"type": "directional", "direction": (-lights.directions[k]).tolist(), "irradiance": {"type": "rgb", "value": value}}
    return {"type": "point", "position": lights.positions[k].tolist(), "intensity": {"type": "rgb", "value": value}}


# --------------------------------------------------------------------------- meshes


def _write_ply(path: Path, vertices, normals, uv, faces) -> Path:
    """A binary PLY with float positions, normals and texture coordinates (Mitsuba's ``ply`` reads it).

    Faces are wound so that their geometric normal agrees with the mean of their vertex normals.
    """
    v = np.asarray(vertices, np.float64)
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    f = np.asarray(faces, np.int64).copy()
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = np.einsum("ij,ij->i", fn, n[f].sum(1)) < 0
    f[flip] = f[flip][:, ::-1]
    area = np.linalg.norm(fn, axis=1)
    f = f[area > 1e-14]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
              + "".join(f"property float {c}\n" for c in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
              + f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    vert = np.concatenate([v, n, uv], axis=1).astype("<f4")
    face = np.empty(len(f), dtype=[("c", "u1"), ("i", "<i4", (3,))])
    face["c"] = 3
    face["i"] = f
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())
    return path


def _grid_faces(rows: int, cols: int, wrap_cols: bool, wrap_rows: bool = False) -> np.ndarray:
    """Two triangles per cell of a ``rows x cols`` vertex grid (row-major), optionally periodic."""
    r_end = rows if wrap_rows else rows - 1
    c_end = cols if wrap_cols else cols - 1
    i, j = np.meshgrid(np.arange(r_end), np.arange(c_end), indexing="ij")
    a = i * cols + j
    b = i * cols + (j + 1) % cols
    c = ((i + 1) % rows) * cols + j
    d = ((i + 1) % rows) * cols + (j + 1) % cols
    return np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])


def _heightfield_ply(path: Path, fn, radius: float, z0: float, nr: int = 160, nt: int = 480) -> Path:
    """The height field ``z = z0 + h(x, y)`` over a disc of ``radius`` (polar grid), normals from the
    analytic gradient ``(-h_x, -h_y, 1)``; texture coordinates ``(x, y)`` mapped to ``[0, 1]``."""
    r = np.linspace(0.0, radius, nr + 1)[1:]
    t = np.linspace(0.0, 2 * np.pi, nt, endpoint=False)
    rr, tt = np.meshgrid(r, t, indexing="ij")
    x = np.concatenate([[0.0], (rr * np.cos(tt)).ravel()])
    y = np.concatenate([[0.0], (rr * np.sin(tt)).ravel()])
    h, hx, hy = fn(x, y)
    v = np.stack([x, y, z0 + h], 1)
    n = np.stack([-hx, -hy, np.ones_like(hx)], 1)
    uv = np.stack([0.5 + 0.5 * x / radius, 0.5 + 0.5 * y / radius], 1)
    ring = _grid_faces(nr, nt, wrap_cols=True) + 1
    fan = np.stack([np.zeros(nt, np.int64), 1 + np.arange(nt), 1 + (np.arange(nt) + 1) % nt], 1)
    return _write_ply(path, v, n, uv, np.concatenate([fan, ring]))


def _rotation(ax_deg: float, ay_deg: float, az_deg: float) -> np.ndarray:
    """``Rz Ry Rx`` (degrees)."""
    a, b, c = np.deg2rad([ax_deg, ay_deg, az_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _param_ply(path: Path, p, n, centre, rot, nu: int, nv: int, wrap_rows: bool) -> Path:
    """A parametric surface sampled on an ``nv x nu`` grid (periodic in u), rotated and moved."""
    v = p.reshape(-1, 3) @ rot.T + centre
    nn = n.reshape(-1, 3) @ rot.T
    uu, vv = np.meshgrid(np.linspace(0, 1, nu, endpoint=False), np.linspace(0, 1, nv), indexing="xy")
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    return _write_ply(path, v, nn, uv, _grid_faces(nv, nu, wrap_cols=True, wrap_rows=wrap_rows))


def _torus_ply(path: Path, R: float, r: float, centre, rot, nu: int = 320, nv: int = 160) -> Path:
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, nu, endpoint=False), np.linspace(0, 2 * np.pi, nv, endpoint=False), indexing="xy")
    n = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], -1)
    p = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], -1)
    return _param_ply(path, p, n, centre, rot, nu, nv, wrap_rows=True)


def _spow(x, e):
    return np.sign(x) * np.abs(x) ** e


def _superquadric_ply(path: Path, a, e1: float, e2: float, centre, rot, nu: int = 320, nv: int = 160) -> Path:
    """Barr's superellipsoid ``(|x/a1|^(2/e2) + |y/a2|^(2/e2))^(e2/e1) + |z/a3|^(2/e1) = 1``; the normal is
    the implicit function's gradient, ``(cv^(2-e1) cu^(2-e2) / a1, cv^(2-e1) su^(2-e2) / a2, sv^(2-e1) / a3)``."""
    u, v = np.meshgrid(np.linspace(-np.pi, np.pi, nu, endpoint=False), np.linspace(-np.pi / 2, np.pi / 2, nv), indexing="xy")
    cu, su, cv, sv = np.cos(u), np.sin(u), np.cos(v), np.sin(v)
    cv = np.where(np.abs(cv) < 1e-12, 0.0, cv)
    p = np.stack([a[0] * _spow(cv, e1) * _spow(cu, e2), a[1] * _spow(cv, e1) * _spow(su, e2), a[2] * _spow(sv, e1)], -1)
    n = np.stack([_spow(cv, 2 - e1) * _spow(cu, 2 - e2) / a[0], _spow(cv, 2 - e1) * _spow(su, 2 - e2) / a[1],
                  _spow(sv, 2 - e1) / a[2]], -1)
    n[0] = [0.0, 0.0, -1.0]
    n[-1] = [0.0, 0.0, 1.0]
    return _param_ply(path, p, n, centre, rot, nu, nv, wrap_rows=False)


# --------------------------------------------------------------------------- height functions (h, h_x, h_y)


def _gaussians(params):
    """Sum of Gaussian bumps ``A exp(-|p - c|^2 / (2 s^2))``; ``params`` rows ``(A, cx, cy, s)``."""
    def fn(x, y):
        h, hx, hy = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        for A, cx, cy, s in params:
            g = A * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
            h += g
            hx += -g * (x - cx) / (s * s)
            hy += -g * (y - cy) / (s * s)
        return h, hx, hy
    return fn


def _bowl(depth: float, inner: float, rim: float, rim_r: float, rim_w: float, cx: float, cy: float):
    """A bowl: ``-depth (1 - (r / inner)^2)^2`` inside ``inner`` plus a Gaussian rim of height ``rim`` at ``rim_r``."""
    def fn(x, y):
        dx, dy = x - cx, y - cy
        r = np.sqrt(dx * dx + dy * dy)
        s = np.minimum(r / inner, 1.0)
        q = 1.0 - s * s
        h = -depth * q * q
        dh = np.where(r < inner, depth * 4.0 * q * s / inner, 0.0)
        g = rim * np.exp(-((r - rim_r) / rim_w) ** 2)
        h = h + g
        dh = dh - g * 2.0 * (r - rim_r) / (rim_w * rim_w)
        rs = np.maximum(r, 1e-12)
        return h, dh * dx / rs, dh * dy / rs
    return fn


def _ridges(amp: float, k: float, wob: float, kw: float, angle: float):
    """Ridges and grooves ``amp sin(k x' + wob sin(kw y'))`` along a direction rotated by ``angle``."""
    ca, sa = np.cos(angle), np.sin(angle)

    def fn(x, y):
        xr, yr = ca * x + sa * y, -sa * x + ca * y
        ph = k * xr + wob * np.sin(kw * yr)
        h = amp * np.sin(ph)
        dxr = amp * np.cos(ph) * k
        dyr = amp * np.cos(ph) * wob * kw * np.cos(kw * yr)
        return h, ca * dxr - sa * dyr, sa * dxr + ca * dyr
    return fn


# --------------------------------------------------------------------------- scenes


def _texture(rng, size: int = 256) -> np.ndarray:
    """A smooth random RGB reflectance texture in [0.08, 0.92]: a base colour, Gaussian blobs, one sinusoid."""
    y, x = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    tex = np.broadcast_to(rng.uniform(0.3, 0.75, 3), (size, size, 3)).copy()
    for _ in range(8):
        c, s, col = rng.uniform(0, 1, 2), rng.uniform(0.05, 0.2), rng.normal(0.0, 0.2, 3)
        tex += col * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / (2 * s * s))[..., None]
    th, f = rng.uniform(0, np.pi), rng.uniform(3.0, 8.0)
    tex += 0.08 * np.sin(2 * np.pi * f * (x * np.cos(th) + y * np.sin(th)))[..., None] * rng.uniform(0.5, 1.0, 3)
    return np.clip(tex, 0.08, 0.92).astype(np.float32)


def _bsdf(spec: CaptureSpec, rng) -> dict:
    """The Mitsuba BSDF of ``spec.material`` (reflectance colour or texture drawn from ``rng``)."""
    colour = rng.uniform(0.25, 0.8, 3)
    if spec.texture:
        mi = mitsuba()
        refl = {"type": "bitmap", "bitmap": mi.Bitmap(_texture(rng)), "raw": True, "filter_type": "bilinear"}
    else:
        refl = {"type": "rgb", "value": colour.tolist()}
    if spec.material == "diffuse":
        return {"type": "diffuse", "reflectance": refl}
    if spec.material == "roughplastic":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": spec.alpha, "int_ior": 1.49, "diffuse_reflectance": refl}
    if spec.material == "plastic":
        return {"type": "plastic", "int_ior": 1.5, "diffuse_reflectance": refl}
    return {"type": "roughconductor", "distribution": "ggx", "alpha": spec.alpha, "material": "Cu"}


def _support(z: float, radius: float, bsdf: dict) -> dict:
    """A disc facing the camera at height ``z`` (Mitsuba's ``disk``: unit disc, normal +z)."""
    mi = mitsuba()
    T = mi.ScalarTransform4f
    return {"type": "disk", "to_world": T().translate([0.0, 0.0, z]) @ T().scale([radius, radius, 1.0]), "bsdf": bsdf}


def _shapes(spec: CaptureSpec, rng, bsdf: dict, tmp: Path) -> dict:
    """The Mitsuba shape dicts of ``spec.shape`` (meshes written into ``tmp``), all with ``bsdf``."""
    mi = mitsuba()
    T = mi.ScalarTransform4f
    z0 = -D0
    s = spec.shape
    if s == "bumps":
        k = 9
        amp = rng.uniform(0.3, 0.65, k) * rng.choice([-1.0, 1.0], k)
        ang, rad = rng.uniform(0, 2 * np.pi, k), 1.5 * np.sqrt(rng.uniform(0, 1, k))
        params = np.stack([amp, rad * np.cos(ang), rad * np.sin(ang), rng.uniform(0.25, 0.55, k)], 1)
        return {"mesh": {"type": "ply", "filename": str(_heightfield_ply(tmp / "m.ply", _gaussians(params), 2.2, z0)), "bsdf": bsdf}}
    if s == "bowl":
        fn = _bowl(rng.uniform(0.8, 1.0), 1.45, rng.uniform(0.25, 0.4), 1.6, 0.28, *rng.uniform(-0.1, 0.1, 2))
        return {"mesh": {"type": "ply", "filename": str(_heightfield_ply(tmp / "m.ply", fn, 2.2, z0 + 0.3)), "bsdf": bsdf}}
    if s == "ridges":
        fn = _ridges(rng.uniform(0.25, 0.32), rng.uniform(2.6, 3.0), rng.uniform(0.6, 1.0), rng.uniform(1.2, 1.8), rng.uniform(0, np.pi))
        return {"mesh": {"type": "ply", "filename": str(_heightfield_ply(tmp / "m.ply", fn, 2.2, z0, nr=200, nt=600)), "bsdf": bsdf}}
    if s == "sphere_on_plane":
        zp, r = -11.0, rng.uniform(1.15, 1.35)
        c = [*rng.uniform(-0.4, 0.4, 2), zp + r]
        small = [-1.2 + rng.uniform(-0.2, 0.2), -1.0 + rng.uniform(-0.2, 0.2), zp + 0.5]
        return {"plane": _support(zp, 2.7, bsdf), "sphere": {"type": "sphere", "center": c, "radius": r, "bsdf": bsdf},
                "small": {"type": "sphere", "center": small, "radius": 0.5, "bsdf": bsdf}}
    if s == "spheres":
        zp = -11.0
        out = {"plane": _support(zp, 2.7, bsdf)}
        base = np.array([[-0.7, 0.5, 0.95], [0.75, 0.45, 0.75], [0.1, -0.75, 0.65], [-1.3, -0.9, 0.45], [1.35, -0.8, 0.5]])
        for i, (x, y, r) in enumerate(base):
            x, y = x + rng.uniform(-0.1, 0.1), y + rng.uniform(-0.1, 0.1)
            out[f"s{i}"] = {"type": "sphere", "center": [x, y, zp + r], "radius": float(r), "bsdf": bsdf}
        return out
    if s == "torus":
        zp = -11.75
        rot = _rotation(rng.uniform(25, 40), rng.uniform(-15, 15), rng.uniform(0, 90))
        ply = _torus_ply(tmp / "m.ply", 1.45, 0.5, np.array([0.0, 0.0, -10.2]), rot)
        return {"plane": _support(zp, 2.8, bsdf), "mesh": {"type": "ply", "filename": str(ply), "bsdf": bsdf}}
    if s == "steps":
        out = {}
        R = T().translate([0.0, 0.0, -10.6]) @ T().rotate([1, 0, 0], rng.uniform(20, 30)) @ T().rotate([0, 0, 1], rng.uniform(15, 40))
        off = rng.uniform(-0.15, 0.15, 2)
        for k in range(4):
            half = 1.55 - 0.38 * k
            c = [off[0] * k, off[1] * k, 0.22 + 0.44 * k]
            out[f"box{k}"] = {"type": "cube", "to_world": R @ T().translate(c) @ T().scale([half, half, 0.22]), "bsdf": bsdf}
        return out
    rot = _rotation(rng.uniform(25, 40), rng.uniform(-35, -20), rng.uniform(10, 40))
    ply = _superquadric_ply(tmp / "m.ply", (1.35, 1.1, 0.9), rng.uniform(0.35, 0.5), rng.uniform(0.35, 0.6), np.array([0.0, 0.0, -10.0]), rot)
    return {"mesh": {"type": "ply", "filename": str(ply), "bsdf": bsdf}}


def _sensor(K: np.ndarray, size: int, spp: int) -> dict:
    """Mitsuba's perspective sensor equal to gpps's camera ``K`` (centred principal point, square pixels)."""
    mi = mitsuba()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx - fy) > 1e-9 * fx or abs(cx - (size - 1) / 2) > 1e-9 or abs(cy - (size - 1) / 2) > 1e-9:
        raise ValueError(f"K: expected fx = fy and the principal point at the image centre, got {K.tolist()}")
    return {
        "type": "perspective", "fov_axis": "x", "fov": float(np.rad2deg(2 * np.arctan(size / (2 * fx)))),
        "near_clip": 0.1, "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def _ground_truth(scene, K: np.ndarray, size: int):
    """Mask, normals and depth at the pixel centres: gpps's camera rays cast into the Mitsuba scene."""
    mi = mitsuba()
    from gpps.camera import Perspective

    _, dirs = Perspective(K).rays((size, size))
    normals = np.zeros((size, size, 3), np.float32)
    depth = np.zeros((size, size), np.float32)
    mask = np.zeros((size, size), bool)
    for i in range(size):
        for j in range(size):
            d = dirs[i, j]
            si = scene.ray_intersect(mi.Ray3f([0.0, 0.0, 0.0], d.tolist()))
            if not si.is_valid():
                continue
            n = np.array(si.sh_frame.n, np.float64)
            n /= np.linalg.norm(n)
            if -float(n @ d) <= MIN_FACING:
                continue
            mask[i, j] = True
            normals[i, j] = n
            depth[i, j] = -float(si.p[2])
    return mask, normals, depth


def _expose(linear: np.ndarray, mask: np.ndarray, spec: CaptureSpec, rng) -> tuple[np.ndarray, float]:
    """Exposure, shot and read noise, clipping and quantisation: ``(images in [0, 1], gain)``."""
    level = np.percentile(linear[:, mask].max(-1), spec.exposure_percentile)
    gain = spec.exposure_level / max(float(level), 1e-12)
    x = linear.astype(np.float64) * gain
    var = spec.read_noise**2 + (np.maximum(x, 0.0) / spec.full_well if spec.full_well > 0 else 0.0)
    x = x + rng.standard_normal(x.shape) * np.sqrt(var)
    full = 2**spec.bits - 1
    return (np.round(np.clip(x, 0.0, 1.0) * full) / full).astype(np.float32), gain


def render_scene(shapes: dict, lights, K: np.ndarray, size: int, *, spp: int = 64, max_depth: int = 4,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """Render Mitsuba ``shapes`` (dicts or loaded objects) under each of gpps's ``lights``, and the ground truth.

    Args:
        shapes: Mitsuba scene entries (name -> shape dict or loaded shape), in gpps's frame.
        lights: :class:`DirectionalLights` or :class:`PointLights` (gpps units).
        K: (3, 3) intrinsics with fx = fy and the principal point at the image centre.
        size: image side (pixels).
        spp: samples per pixel (box filter over the pixel).
        max_depth: Mitsuba path tracer's path length (2: direct light only).
        seed: the sampler's seed of the first image (image ``k``: ``seed * 1000 + k``).

    Returns:
        ``(linear, mask, normals, depth, timings)``: (N, size, size, 3) float32 renders in gpps's units
        (``kd cos I`` for a Lambertian surface), the ground truth of :func:`_ground_truth` and the
        seconds of each render (``"render"``) and of the ground truth.
    """
    mi = mitsuba()
    shapes = {k: (mi.load_dict(v) if isinstance(v, dict) else v) for k, v in shapes.items()}
    sensor = mi.load_dict(_sensor(K, size, spp))
    integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
    n = len(lights)
    timings = {"render": []}
    linear = np.empty((n, size, size, 3), np.float32)
    scene = None
    for k in range(n):
        scene = mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor, **shapes, "light": _emitter(lights, k)})
        t = time.perf_counter()
        linear[k] = np.asarray(mi.render(scene, seed=int(seed) * 1000 + k, spp=spp), np.float32)
        timings["render"].append(time.perf_counter() - t)
    t = time.perf_counter()
    mask, normals, depth = _ground_truth(scene, K, size)
    timings["ground_truth"] = time.perf_counter() - t
    return linear, mask, normals, depth, timings


def render_capture(spec: CaptureSpec) -> RenderedCapture:
    """Render ``spec`` with Mitsuba (one image per light) and its ground truth; see the module docstring."""
    if not isinstance(spec, CaptureSpec):
        raise TypeError(f"spec: expected CaptureSpec, got {type(spec).__name__}")
    mi = mitsuba()
    rng = np.random.default_rng([spec.seed, SHAPES.index(spec.shape), MATERIALS.index(spec.material), 11])
    lights = light_rig(spec.light_kind, spec.n_lights, spec.seed)
    K = np.array(default_camera("perspective", spec.size).K)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="gpps-mts-") as tmp:
        bsdf = mi.load_dict(_bsdf(spec, rng))
        shapes = {k: mi.load_dict(v) for k, v in _shapes(spec, rng, bsdf, Path(tmp)).items()}
    t_scene = time.perf_counter() - t0
    linear, mask, normals, depth, timings = render_scene(shapes, lights, K, spec.size, spp=spec.spp,
                                                         max_depth=spec.max_depth, seed=spec.seed)
    timings["scene"] = t_scene
    if not mask.any():
        raise ValueError(f"spec: the scene {spec.shape!r} covers no pixel at size {spec.size}")
    images, gain = _expose(linear, mask, spec, np.random.default_rng([spec.seed, 13]))
    return RenderedCapture(spec=spec, images=images, linear=linear, lights=lights, exposure=gain, K=K, mask=mask,
                           normals=normals, depth=depth, timings=timings)


def write_capture(cap: RenderedCapture, folder, *, overwrite: bool = False) -> Path:
    """Write ``cap`` as a gpps capture folder: ``001.png...`` (``spec.bits``), ``filenames.txt``,
    ``light_directions.txt`` or ``light_positions.txt``, ``light_intensities.txt`` (exposure x intensity),
    ``mask.png``, ``K.txt``, ``normal_gt.npy``, ``depth_gt.npy`` and ``scene.json`` (the spec, the
    exposure, the render times, the Mitsuba version)."""
    mi = mitsuba()
    lights = cap.lights
    ds = Dataset(
        images=cap.images, mask=cap.mask,
        light_directions=lights.directions if isinstance(lights, DirectionalLights) else None,
        light_positions=lights.positions if isinstance(lights, PointLights) else None,
        light_intensities=cap.exposure * np.asarray(lights.intensities), K=cap.K, normal_gt=cap.normals,
        depth_gt=cap.depth, material=None, normalised=False,
    )
    folder = write_dataset(folder, ds, bits=cap.spec.bits, overwrite=overwrite)
    info = {"spec": asdict(cap.spec), "version": VERSION, "mitsuba": mi.__version__, "variant": mi.variant(),
            "exposure": cap.exposure, "timings": cap.timings, "light_kind": lights.kind,
            "mean_render_s": float(np.mean(cap.timings["render"]))}
    (folder / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    return folder


def default_root() -> Path:
    """``$GPPS_CACHE_DIR/mitsuba_captures`` (else ``~/.cache/gpps/mitsuba_captures``)."""
    base = os.environ.get("GPPS_CACHE_DIR") or str(Path.home() / ".cache" / "gpps")
    return Path(base) / "mitsuba_captures"


def make_capture(spec: CaptureSpec, root=None, *, reuse: bool = True) -> Path:
    """The capture folder of ``spec`` under ``root`` (None: :func:`default_root`), rendered unless a folder
    with the same spec and :data:`VERSION` is there already (``reuse``).

    Returns:
        The folder (``root / spec.name``).
    """
    root = default_root() if root is None else Path(root)
    folder = root / spec.name
    info = folder / "scene.json"
    if reuse and info.is_file():
        try:
            old = json.loads(info.read_text())
        except ValueError:
            old = {}
        if old.get("spec") == asdict(spec) and old.get("version") == VERSION:
            return folder
    root.mkdir(parents=True, exist_ok=True)
    return write_capture(render_capture(spec), folder, overwrite=True)


def with_lights(spec: CaptureSpec, kind: LightKind, n: int) -> CaptureSpec:
    """``spec`` with other lights (the shape, material and seed kept)."""
    return replace(spec, light_kind=kind, n_lights=n)

