"""The single-image network's random scenes (:mod:`shapes`) rendered by Mitsuba 3's path tracer (issue 24).

Recipe v2 renders its random scenes with gpps's own image model plus approximations of what that model lacks
(cast shadows marched over the depth map, an "indirect fill" term).  A network trained on it alone was barely
better than a flat plane on physically based renders.  This module renders the *same shape generator* with
an independent physically based renderer, so that part of the training data carries real interreflections,
real cast shadows, rough dielectric and metallic lobes with Fresnel, and Monte Carlo noise:

* geometry: the scene's depth map as the camera sees it, turned into a triangle mesh (a "2.5D shell"): every
  pixel centre back-projected through the perspective camera (:func:`gpps.host.scenes.default_camera`) to its
  depth; two triangles per 2x2 block of mask pixels of one surface piece (``RandomScene.parts``), one where
  three of the four are; no triangle spans an occlusion boundary.  Vertex normals are the ground-truth normals
  (``SceneRenderer.normals``: the depth map's normals within each piece), so the shading normal at each pixel
  centre is the ground truth.  The shell has no back faces: light passing behind a solid is not blocked by
  its hidden half (the shadows of tall thin parts are shorter than a closed solid's);
* reflectance: the support and the objects draw their Mitsuba BSDF independently half the time: ``diffuse``,
  ``roughplastic`` (GGX or Beckmann, alpha log-uniform in [0.02, 0.6], index 1.3-1.8), smooth ``plastic``,
  ``roughconductor`` (one of :data:`METALS`), ``principled`` (metallic, roughness, specular random); the
  diffuse colour is the scene's albedo texture (``random_albedo``), mapped pixel to texel;
* one light per scene (``random_light``: directional or point, slant up to 60 deg), sometimes a dim constant
  environment (light bounced from the room); path tracer ``max_depth`` 4 (up to three bounces);
* a camera: exposure (a percentile of the object's pixels to a level below full scale: highlights clip),
  shot and read noise, 8- or 16-bit quantisation.

Shards (``mts_<first seed>.npz``) hold, per scene: ``images`` (n, S, S, 3), or (n, L, S, S, 3) with ``--lights L``
> 1, uint8 ``round(255 sqrt(x))`` of the exposed image x in [0, 1] (square-root coded: 8-bit steps near black stay below the read noise),
``normals`` (n, S, S, 3) int8 ``round(127 n)`` (renormalised when read: under half a degree; the first shards
held only ``n_x, n_y``, which lose precision near the occluding contours, and :func:`pack_shard` recomputes
their normals from the seeds), ``mask`` (n, S, S)
packed bits, ``seeds`` and a JSON ``info`` list.  Training code decodes them with :func:`decode_shard`.

Run (CPU; Mitsuba's ``scalar_rgb`` variant, see :mod:`mitsuba_scenes`)::

    python training/mitsuba_random.py --out DIR --first 500000 --count 1000 [--shard 250] [--spp 32]
"""

from __future__ import annotations

import argparse
import json
import lzma
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (str(ROOT), str(Path(__file__).resolve().parent)):
    if p not in sys.path:
        sys.path.insert(0, p)

from gpps.host.scenes import D0, default_camera  # noqa: E402
from gpps.lights import DirectionalLights  # noqa: E402
from mitsuba_scenes import CaptureSpec, _emitter, _sensor, _write_ply, mitsuba  # noqa: E402
from mitsuba_scenes import _expose as _expose_capture  # noqa: E402
from shapes import SceneRenderer, random_light, random_scene  # noqa: E402

__all__ = ["METALS", "BSDF_KINDS", "scene_normals", "shell_mesh", "render_random", "decode_shard", "write_shard", "pack_shard"]

#: Mitsuba's tabulated conductors the metallic scenes draw from
METALS = ("Cu", "Au", "Al", "Ag", "Cr", "Ni_palik", "Ir", "W", "Rh")
#: the first seed of these scenes: far from recipe v2's training seeds (0..7000) and its validation seeds (near 10^6)
FIRST_SEED = 500_000
#: the validation scenes of this recipe start here (never rendered for training)
VAL_FIRST_SEED = 900_000


def shell_mesh(depth: np.ndarray, mask: np.ndarray, parts: np.ndarray | None, K: np.ndarray):
    """The depth map's visible surface as triangles: ``(vertices (V, 3), faces (F, 3), pixel (V,) flat index,
    covered (H, W) bool)`` in gpps's frame (camera at the origin looking down -z, depth = -z).

    A vertex per mask pixel, at its centre's ray times its depth; the faces of each 2x2 block whose pixels
    lie in the mask and in one surface piece (two triangles with four such pixels, one with three).
    ``covered``: the mask pixels that are a vertex of some face (isolated pixels have no surface).
    """
    h, w = mask.shape
    piece = np.where(mask, 0 if parts is None else parts, -1).astype(np.int64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = depth.astype(np.float64)
    verts_all = np.stack([(jj - cx) / fx * d, -(ii - cy) / fy * d, -d], -1)
    index = np.full((h, w), -1, np.int64)
    index[mask] = np.arange(int(mask.sum()))
    a, b = piece[:-1, :-1], piece[:-1, 1:]
    c, e = piece[1:, :-1], piece[1:, 1:]
    ia, ib, ic, ie = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = []
    four = (a >= 0) & (a == b) & (a == c) & (a == e)
    faces.append(np.stack([ia[four], ib[four], ie[four]], -1))
    faces.append(np.stack([ia[four], ie[four], ic[four]], -1))
    # three of four in one piece: the triangle of those three
    for keep, tri in (((a >= 0) & (a == b) & (a == c) & ~four, (ia, ib, ic)),
                      ((b >= 0) & (b == e) & (b == a) & ~four, (ia, ib, ie)),
                      ((e >= 0) & (e == c) & (e == b) & ~four, (ib, ie, ic)),
                      ((c >= 0) & (c == a) & (c == e) & ~four, (ia, ie, ic))):
        faces.append(np.stack([t[keep] for t in tri], -1))
    faces = np.concatenate(faces).astype(np.int64)
    covered = np.zeros(h * w, bool)
    flat = np.flatnonzero(mask)
    covered[flat[np.unique(faces)]] = True
    return verts_all[mask], faces, flat, covered.reshape(h, w)


def _log_uniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


BSDF_KINDS = ("diffuse", "roughplastic", "plastic", "roughconductor", "principled")
BSDF_P = (0.25, 0.35, 0.1, 0.15, 0.15)


def _random_bsdf(rng, albedo_tex, kind: str | None = None) -> tuple[dict, str]:
    """A random Mitsuba BSDF over the diffuse colour ``albedo_tex`` (a bitmap texture dict) and its name
    (``kind``: one of :data:`BSDF_KINDS`, else drawn; the kind is drawn from ``rng`` either way)."""
    drawn = str(rng.choice(BSDF_KINDS, p=BSDF_P))
    kind = kind or drawn
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": albedo_tex}, kind
    if kind == "roughplastic":
        return {"type": "roughplastic", "distribution": str(rng.choice(["ggx", "beckmann"])),
                "alpha": _log_uniform(rng, 0.02, 0.6), "int_ior": float(rng.uniform(1.3, 1.8)),
                "nonlinear": bool(rng.random() < 0.3), "diffuse_reflectance": albedo_tex}, kind
    if kind == "plastic":
        return {"type": "plastic", "int_ior": float(rng.uniform(1.3, 1.8)), "nonlinear": bool(rng.random() < 0.3),
                "diffuse_reflectance": albedo_tex}, kind
    if kind == "roughconductor":
        return {"type": "roughconductor", "distribution": "ggx", "alpha": _log_uniform(rng, 0.03, 0.6),
                "material": str(rng.choice(METALS))}, kind
    return {"type": "principled", "base_color": albedo_tex, "metallic": float(rng.uniform(0.0, 1.0) ** 2),
            "roughness": float(rng.uniform(0.1, 0.9)), "specular": float(rng.uniform(0.2, 0.8))}, kind


def _expose(linear: np.ndarray, mask: np.ndarray, rng) -> tuple[np.ndarray, dict]:
    """A random camera (a percentile of the mask's brightest channel to a level, shot and read noise, 8 or 16 bits)
    applied to ``linear`` (L, S, S, 3) by :func:`mitsuba_scenes._expose` (one exposure for all images): the images
    in [0, 1] and the draws."""
    pct, level = float(rng.uniform(97.0, 99.9)), float(rng.uniform(0.6, 1.0))
    full_well, read = _log_uniform(rng, 1e3, 5e4), float(rng.uniform(0.0, 2e-3))
    bits = 8 if rng.random() < 0.5 else 16
    camera = CaptureSpec(bits=bits, full_well=full_well, read_noise=read, exposure_percentile=pct, exposure_level=level)
    images, _ = _expose_capture(linear, mask, camera, rng)
    return images, {"percentile": pct, "level": level, "full_well": full_well, "read_noise": read, "bits": bits}


def scene_normals(size: int, seed: int, renderer: SceneRenderer | None = None, *, family: str | None = None):
    """The random scene of ``seed`` seen by the perspective camera (the shell is back-projected through it) and
    its ground-truth normals (H, W, 3) (``SceneRenderer.normals``: within each surface piece)."""
    sc = random_scene(size, seed, family=family)
    sc.camera_kind = "perspective"
    return sc, (renderer or SceneRenderer("cpu")).normals(sc)


def render_random(size: int, seed: int, *, spp: int = 32, max_depth: int = 4, renderer: SceneRenderer | None = None,
                  tmp: Path | None = None, family: str | None = None, bsdf: str | None = None, lights=None,
                  expose: bool = True, n_lights: int = 1) -> dict:
    """Render the random scene of ``seed`` (perspective camera) under ``n_lights`` random lights (one image
    each, one exposure for all) with Mitsuba.

    ``family``, ``bsdf`` (one of :data:`BSDF_KINDS` for every part, its parameters drawn), ``lights`` (gpps
    lights, one image each) override the random draws; ``expose=False`` returns the linear render
    (gpps's units: ``kd cos I`` for a Lambertian surface) without the camera model (tests).

    Returns:
        ``{"image": (S, S, 3) float32 (in [0, 1] when exposed) the first light's, "images": (L, S, S, 3) every
        light's, "normals": (S, S, 3) float32, "mask": (S, S) bool, "height": (S, S) float32 relative height,
        "albedo": (S, S, 3) float32, "info": dict}``.
    """
    mi = mitsuba()
    rng = np.random.default_rng([seed, 29])
    sc, normals = scene_normals(size, seed, renderer, family=family)
    K = np.array(default_camera("perspective", size).K)
    verts, faces, flat, covered = shell_mesh(sc.depth, sc.mask, sc.parts, K)
    mask = covered
    n_v = normals.reshape(-1, 3)[flat]
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    uv = np.stack([(jj.ravel()[flat] + 0.5) / size, (ii.ravel()[flat] + 0.5) / size], -1)
    albedo = np.clip(sc.albedo, 0.02, 1.0).astype(np.float32)
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(albedo), "raw": True, "filter_type": "nearest"}
    parts = np.zeros(sc.mask.shape, np.int32) if sc.parts is None else sc.parts
    groups = {"objects": parts.ravel()[flat] > 0, "support": parts.ravel()[flat] <= 0}
    if bsdf is not None and bsdf not in BSDF_KINDS:
        raise ValueError(f"bsdf: expected one of {list(BSDF_KINDS)} or None, got {bsdf!r}")
    bsdf_obj, kind_obj = _random_bsdf(rng, tex, bsdf)
    same = rng.random() < 0.5 or bsdf is not None
    bsdf_sup, kind_sup = (bsdf_obj, kind_obj) if same else _random_bsdf(rng, tex)
    lights_drawn = random_light(rng, int(n_lights))
    lights = lights_drawn if lights is None else lights
    shapes = {}
    own = tmp is None
    tmpdir = Path(tempfile.mkdtemp(prefix="gpps-mtsr-")) if own else tmp
    try:
        for name, sel in groups.items():
            fsel = sel[faces].all(1)
            if not fsel.any():
                continue
            ply = _write_ply(tmpdir / f"{name}.ply", verts, n_v, uv, faces[fsel])
            shapes[name] = mi.load_dict({"type": "ply", "filename": str(ply), "face_normals": False,
                                         "bsdf": mi.load_dict(bsdf_obj if name == "objects" else bsdf_sup)})
    finally:
        if own:
            for f in tmpdir.glob("*.ply"):
                f.unlink()
            tmpdir.rmdir()
    sensor = mi.load_dict(_sensor(K, size, spp))
    env = float(rng.uniform(0.01, 0.08)) if rng.random() < 0.3 else 0.0
    t = time.perf_counter()
    linear = []
    for k in range(len(lights)):
        scene_dict = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}, "sensor": sensor,
                      **shapes, "light": _emitter(lights, k)}
        if env > 0:
            scene_dict["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": [env] * 3}}
        linear.append(np.asarray(mi.render(mi.load_dict(scene_dict), seed=(int(seed) + 1_000_003 * k) % 2**31, spp=spp),
                                 np.float32))
    t_render = time.perf_counter() - t
    linear = np.stack(linear)
    linear = np.where(np.isfinite(linear), np.maximum(linear, 0.0), 0.0)
    images, cam = _expose(linear, mask, rng) if expose else (linear, {})
    rel = None if isinstance(lights, DirectionalLights) else lights.positions - np.array([0.0, 0.0, -D0])
    dirs = lights.directions if rel is None else rel / np.linalg.norm(rel, axis=1, keepdims=True)  # from the scene's centre
    info = {"seed": int(seed), "family": sc.family, "bsdf_objects": kind_obj, "bsdf_support": kind_sup,
            "light": lights.kind, "environment": env, "render_s": round(t_render, 3), **cam,
            "light_direction": dirs[0].tolist(), "light_directions": dirs.tolist()}
    normals = np.where(mask[..., None], normals, 0.0).astype(np.float32)
    return {"image": images[0], "images": images, "normals": normals, "mask": mask, "height": sc.relative_height() * mask,
            "albedo": albedo, "info": info}


def write_shard(path: Path, samples: list[dict]) -> Path:
    """Write ``samples`` (:func:`render_random` outputs) as one compressed shard (temporary name, then rename)."""
    multi = any(len(s.get("images", [None])) > 1 for s in samples)
    key = "images" if multi else "image"
    imgs = np.stack([np.round(255.0 * np.sqrt(np.clip(s[key], 0.0, 1.0))).astype(np.uint8) for s in samples])
    nrm = np.stack([np.round(127.0 * s["normals"]).astype(np.int8) for s in samples])
    masks = np.stack([np.packbits(s["mask"].ravel()) for s in samples])
    path = Path(path)
    tmp = path.with_name(path.name + ".part.npz")
    np.savez_compressed(tmp, images=imgs, normals=nrm, mask=masks, seeds=np.array([s["info"]["seed"] for s in samples]),
                        size=np.array(samples[0]["mask"].shape[0]), info=np.array(json.dumps([s["info"] for s in samples])))
    os.replace(tmp, path)
    return path


_NORMAL_FILTERS = [{"id": lzma.FILTER_DELTA, "dist": 3}, {"id": lzma.FILTER_LZMA2, "preset": 6}]


def pack_shard(src, dst, *, quality: int = 95) -> Path:
    """A smaller copy of shard ``src`` for carrying to the GPU machine (about a third of the size): each image's
    square-root code as a JPEG of ``quality`` without chroma subsampling (mean error about two code steps, the
    size of the renders' shot noise at mid grey; images from the wild are JPEGs too), the normals' int8 codes
    through a delta + LZMA2 filter (lossless; a first shard's normals recomputed from its seeds); the mask,
    seeds and info as they are.  :func:`decode_shard`
    reads both forms."""
    import cv2

    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    blobs = []
    images = arrays.pop("images")
    arrays["images_shape"] = np.array(images.shape)
    for im in images.reshape((-1,) + images.shape[-3:]):
        ok, buf = cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, int(quality),
                                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        if not ok:
            raise ValueError(f"src: could not encode an image of {src} as JPEG")
        blobs.append(buf.ravel())
    nrm = arrays.pop("normals")
    if nrm.shape[-1] == 2:  # the first shards' (n_x, n_y) codes: the normals again from the seeds
        s = int(arrays["size"])
        mask = np.unpackbits(arrays["mask"], axis=1)[:, : s * s].reshape(-1, s, s).astype(bool)
        renderer = SceneRenderer("cpu")
        nrm = np.stack([np.round(127.0 * scene_normals(s, int(seed), renderer)[1] * m[..., None]).astype(np.int8)
                        for seed, m in zip(arrays["seeds"], mask)])
    arrays["jpeg"] = np.concatenate(blobs)
    arrays["jpeg_offsets"] = np.cumsum([0] + [len(b) for b in blobs])
    arrays["normals_xz"] = np.frombuffer(lzma.compress(nrm.tobytes(), format=lzma.FORMAT_RAW, filters=_NORMAL_FILTERS), np.uint8)
    arrays["normals_shape"] = np.array(nrm.shape)
    dst = Path(dst)
    tmp = dst.with_name(dst.name + ".part.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, dst)
    return dst


def decode_shard(path) -> dict:
    """A shard's arrays (:func:`write_shard`'s or :func:`pack_shard`'s form): ``images`` (n, S, S, 3) float32 in
    [0, 1] ((n, L, S, S, 3) for scenes of L lights), ``normals`` (n, S, S, 3) float32 unit (zero outside), ``mask`` (n, S, S) bool, ``seeds`` (n,),
    ``info`` list."""
    with np.load(path, allow_pickle=False) as z:
        s = int(z["size"])
        if "jpeg" in z.files:
            import cv2

            blob, off = z["jpeg"], z["jpeg_offsets"]
            codes = np.stack([cv2.imdecode(blob[off[k] : off[k + 1]], cv2.IMREAD_UNCHANGED) for k in range(len(off) - 1)])
            if "images_shape" in z.files:
                codes = codes.reshape(tuple(int(x) for x in z["images_shape"]))
            shape = tuple(int(x) for x in z["normals_shape"])
            raw = lzma.decompress(z["normals_xz"].tobytes(), format=lzma.FORMAT_RAW, filters=_NORMAL_FILTERS)
            ncode = np.frombuffer(raw, np.int8).reshape(shape)
        else:
            codes, ncode = z["images"], z["normals"]
        img = (codes.astype(np.float32) / 255.0) ** 2
        n = ncode.astype(np.float32) / 127.0
        mask = np.unpackbits(z["mask"], axis=1)[:, : s * s].reshape(-1, s, s).astype(bool)
        seeds, info = z["seeds"], json.loads(str(z["info"]))
    if n.shape[-1] == 2:  # the first shards: n_z from unit length
        n = np.concatenate([n, np.sqrt(np.clip(1.0 - (n**2).sum(-1), 0.0, 1.0))[..., None]], -1)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
    n[~mask] = 0.0
    return {"images": img, "normals": n, "mask": mask, "seeds": seeds, "info": info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--first", type=int, default=FIRST_SEED)
    ap.add_argument("--count", type=int, default=1000)
    ap.add_argument("--shard", type=int, default=250)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--max-depth", type=int, default=4)
    ap.add_argument("--lights", type=int, default=1, help="lights (images) per scene")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    renderer = SceneRenderer("cpu")
    with tempfile.TemporaryDirectory(prefix="gpps-mtsr-") as tmp:
        for s0 in range(args.first, args.first + args.count, args.shard):
            path = out / f"mts_{s0}.npz"
            if path.exists():
                continue
            t = time.perf_counter()
            samples = [render_random(args.size, s, spp=args.spp, max_depth=args.max_depth, renderer=renderer, tmp=Path(tmp),
                                     n_lights=args.lights)
                       for s in range(s0, min(s0 + args.shard, args.first + args.count))]
            write_shard(path, samples)
            print(f"{path.name}: {len(samples)} scenes in {time.perf_counter() - t:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
