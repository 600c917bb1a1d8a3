"""The Mitsuba-rendered training scenes of the single-image network (training/mitsuba_random.py, issue 24): the
depth map's shell mesh against the camera, the shard formats, and (with Mitsuba) a Lambertian shell rendered by
Mitsuba against gpps's own renderer of the same scene."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from gpps.camera import Perspective  # noqa: E402
from gpps.host.scenes import default_camera  # noqa: E402
from mitsuba_random import decode_shard, pack_shard, shell_mesh, write_shard  # noqa: E402


def _pieces():
    """A 6 x 7 depth map with two surface pieces, a hole and an isolated pixel."""
    h, w = 6, 7
    depth = 10.0 + 0.1 * np.arange(h * w, dtype=np.float32).reshape(h, w)
    mask = np.ones((h, w), bool)
    mask[0, 6] = False
    mask[2:4, 3] = False  # a gap between the pieces' columns
    mask[5, 1:] = False  # (5, 0) joins (4, 0) and (4, 1) in a three-pixel block
    parts = np.zeros((h, w), np.int32)
    parts[:, 4:] = 1
    parts[~mask] = -1
    return depth, mask, parts


def test_shell_vertices_lie_on_the_pixel_rays_at_their_depth():
    depth, mask, parts = _pieces()
    K = np.array(default_camera("perspective", mask.shape).K)
    verts, faces, flat, covered = shell_mesh(depth, mask, parts, K)
    assert verts.shape == (mask.sum(), 3) and np.array_equal(flat, np.flatnonzero(mask))
    np.testing.assert_allclose(-verts[:, 2], depth.ravel()[flat], rtol=1e-12)
    uv = Perspective(K).project(verts)
    ii, jj = np.divmod(flat, mask.shape[1])
    np.testing.assert_allclose(uv, np.stack([jj, ii], -1), atol=1e-9)
    assert covered.shape == mask.shape and not np.any(covered & ~mask)


def test_shell_faces_stay_inside_one_piece_and_one_block():
    depth, mask, parts = _pieces()
    K = np.array(default_camera("perspective", mask.shape).K)
    verts, faces, flat, covered = shell_mesh(depth, mask, parts, K)
    pix = flat[faces]  # (F, 3) flat pixel indices
    ii, jj = np.divmod(pix, mask.shape[1])
    assert np.all(ii.max(1) - ii.min(1) <= 1) and np.all(jj.max(1) - jj.min(1) <= 1)  # one 2x2 block
    p = parts.ravel()[pix]
    assert np.all(p == p[:, :1])  # no face joins two pieces (an occlusion boundary)
    assert len({tuple(sorted(f)) for f in faces.tolist()}) == len(faces)  # no face twice
    # every 2x2 block of one piece gives two faces: count them independently
    full = sum(1 for i in range(mask.shape[0] - 1) for j in range(mask.shape[1] - 1)
               if len({parts[i, j], parts[i, j + 1], parts[i + 1, j], parts[i + 1, j + 1]}) == 1 and parts[i, j] >= 0)
    three = 0
    for i in range(mask.shape[0] - 1):
        for j in range(mask.shape[1] - 1):
            q = [parts[i, j], parts[i, j + 1], parts[i + 1, j], parts[i + 1, j + 1]]
            if any(len([x for x in q if x == v and v >= 0]) == 3 for v in set(q)):
                three += 1
    assert len(faces) == 2 * full + three
    # a pixel is covered exactly when some face uses it
    assert set(np.flatnonzero(covered)) == set(np.unique(pix))


def test_shards_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    samples = []
    for k in range(3):
        mask = rng.random((16, 16)) > 0.3
        n = rng.normal(size=(16, 16, 3))
        n[..., 2] = np.abs(n[..., 2]) + 0.2
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n[~mask] = 0
        img = (rng.random((16, 16, 3)) * mask[..., None]).astype(np.float32)
        samples.append({"image": img, "normals": n.astype(np.float32), "mask": mask, "info": {"seed": 100 + k}})
    raw = write_shard(tmp_path / "mts_100.npz", samples)
    assert not list(tmp_path.glob("*.part*"))
    d = decode_shard(raw)
    assert list(d["seeds"]) == [100, 101, 102] and [r["seed"] for r in d["info"]] == [100, 101, 102]
    for k, s in enumerate(samples):
        assert np.array_equal(d["mask"][k], s["mask"])
        # square-root code: the error is half a code step in sqrt(x)
        assert np.max(np.abs(np.sqrt(d["images"][k]) - np.sqrt(s["image"]))) <= 0.5 / 255 + 1e-6
        ang = np.degrees(np.arccos(np.clip(np.sum(d["normals"][k] * s["normals"], -1)[s["mask"]], -1, 1)))
        assert ang.max() < 0.5  # int8 codes of n, renormalised
        assert np.all(d["normals"][k][~s["mask"]] == 0)
    packed = decode_shard(pack_shard(raw, tmp_path / "packed.npz"))
    assert np.array_equal(packed["normals"], d["normals"]) and np.array_equal(packed["mask"], d["mask"])
    err = np.abs(np.sqrt(packed["images"]) - np.sqrt(d["images"])) * 255  # JPEG of the codes
    assert err.mean() < 4.0


def test_lambertian_shell_agrees_with_gpps_render():
    """A height-field scene's shell rendered by Mitsuba (direct light only) against gpps's renderer of the same
    depth map, albedo and light: the mesh, its normals, the texture mapping and the light units agree."""
    pytest.importorskip("mitsuba")
    from gpps.lights import DirectionalLights
    from mitsuba_random import render_random
    from shapes import SceneRenderer

    lights = DirectionalLights(np.array([[0.3, -0.2, 0.93]]) / np.linalg.norm([0.3, -0.2, 0.93]), np.ones((1, 3)))
    r = SceneRenderer("cpu")
    out = render_random(48, 7, spp=64, max_depth=2, renderer=r, family="heightfield", lights=lights, expose=False,
                        bsdf="diffuse")
    m = out["mask"]
    from scipy.ndimage import binary_erosion

    cos = np.clip(out["normals"] @ lights.directions[0], 0, None)
    ref = out["albedo"] * cos[..., None]
    inner = binary_erosion(m, iterations=2) & (cos > 0.2)
    ratio = out["image"][inner] / ref[inner]
    assert inner.sum() > 100
    assert abs(np.median(ratio) - 1.0) < 0.03, np.median(ratio)
    assert np.mean(np.abs(ratio - 1.0) < 0.1) > 0.9


def test_first_shards_normals_come_back_from_their_seeds(tmp_path):
    """The first shards held (n_x, n_y) codes only: decoding derives n_z from unit length, and packing recomputes
    the normals from the scenes' seeds (the same scene_normals the renders used), masked as stored."""
    import json

    from mitsuba_random import scene_normals

    size, seeds = 32, [500000, 500001]
    normals, masks = [], []
    for s in seeds:
        _, n = scene_normals(size, s)
        m = np.linalg.norm(n, axis=-1) > 0.5
        m[0, :] = False  # a mask smaller than the scene's (the shell's covered pixels)
        normals.append(np.where(m[..., None], n, 0.0))
        masks.append(m)
    np.savez_compressed(tmp_path / "mts_500000.npz", images=np.zeros((2, size, size, 3), np.uint8),
                        normals=np.stack([np.round(127 * n[..., :2]).astype(np.int8) for n in normals]),
                        mask=np.stack([np.packbits(m.ravel()) for m in masks]), seeds=np.array(seeds), size=np.array(size),
                        info=np.array(json.dumps([{"seed": s} for s in seeds])))
    legacy = decode_shard(tmp_path / "mts_500000.npz")
    packed = decode_shard(pack_shard(tmp_path / "mts_500000.npz", tmp_path / "packed.npz"))
    for k in range(2):
        m = masks[k]
        ok = normals[k][..., 2] > 0.5  # away from grazing, the derived n_z is close
        cos = np.sum(legacy["normals"][k] * normals[k], -1)
        assert np.degrees(np.arccos(np.clip(cos[m & ok], -1, 1))).max() < 1.0
        cos = np.sum(packed["normals"][k] * normals[k], -1)
        assert np.degrees(np.arccos(np.clip(cos[m], -1, 1))).max() < 0.5  # everywhere, grazing too
        assert np.all(packed["normals"][k][~m] == 0) and np.array_equal(packed["mask"][k], m)
