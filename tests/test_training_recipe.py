"""The single-image network's training recipe v2 (training/shapes.py): primitives against their geometry, the
z-buffer composition, per-piece ground-truth normals, cast shadows in the renders, determinism."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/shapes.py

import shapes  # noqa: E402


def test_box_front_face_is_the_upper_face(monkeypatch):
    # an axis-aligned box: its front surface is the plane z = c_z + s_z over the rectangle |x - c_x| < s_x, ...
    monkeypatch.setattr(shapes, "_rotation3", lambda rng: np.eye(3))
    X, Y = shapes._grid(64)
    rng = np.random.default_rng(0)
    h, inside = shapes._box(X, Y, rng, (0.1, -0.2), 0.5, 0.3)
    s = 0.5 * np.random.default_rng(0).uniform(0.3, 0.8, 3)  # the sizes _box drew
    want = (np.abs(X - 0.1) < s[0]) & (np.abs(Y + 0.2) < s[1])
    assert np.array_equal(inside, want)
    np.testing.assert_allclose(h[inside], 0.3 + 0.6 * 0.5 + s[2], atol=1e-12)


def test_rotated_box_surface_lies_on_the_box():
    # any orientation: every front-surface point is inside the box and on one of its faces
    R = shapes._rotation3(np.random.default_rng(5))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    X, Y = shapes._grid(64)
    rng = np.random.default_rng(7)
    state = np.random.default_rng(7)
    Rb = shapes._rotation3(state)
    s = 0.45 * state.uniform(0.3, 0.8, 3)
    h, inside = shapes._box(X, Y, rng, (0.0, 0.0), 0.45, 0.0)
    assert inside.sum() > 50
    c3 = np.array([0.0, 0.0, 0.6 * 0.45])
    P = np.stack([X[inside], Y[inside], h[inside]], 1) - c3
    local = np.abs(P @ Rb)  # coordinates along the box's axes
    assert np.all(local <= s + 1e-9)
    assert np.all(np.min(s - local, 1) < 1e-9)  # on a face


def test_composition_keeps_the_nearer_part():
    X, Y = shapes._grid(64)
    rng = np.random.default_rng(1)
    items = [("superellipsoid", (-0.2, 0.0), 0.5, 0.0), ("superellipsoid", (0.2, 0.0), 0.5, 0.4)]
    hgt, inside, parts, names = shapes._compose(X, Y, rng, items)
    rng = np.random.default_rng(1)
    h0, m0 = shapes._superellipsoid(X, Y, rng, (-0.2, 0.0), 0.5, 0.0)
    h1, m1 = shapes._superellipsoid(X, Y, rng, (0.2, 0.0), 0.5, 0.4)
    both = m0 & m1
    assert both.any() and np.array_equal(inside, m0 | m1) and names == ["superellipsoid", "superellipsoid"]
    np.testing.assert_allclose(hgt[both], np.maximum(h0, h1)[both])
    assert np.array_equal(parts[both], np.where(h1 > h0, 1, 0)[both])
    assert np.all(parts[~inside] == -1)


@pytest.mark.parametrize("family", ["solids", "tabletop", "relief"])
def test_scenes_render_with_valid_normals_and_shadows(family):
    r = shapes.SceneRenderer("cpu")
    for seed in range(3):
        sc, n, imgs, lights = shapes.render_random_sample(64, 100 + seed, r, n_lights=2, family=family)
        m = sc.mask
        assert sc.family == family and m.sum() > 0.08 * m.size
        np.testing.assert_allclose(np.linalg.norm(n[m], axis=1), 1.0, atol=1e-4)
        assert np.mean(n[m][:, 2] > 0) > 0.98  # visible normals face the camera
        assert np.all(n[~m] == 0) and np.all(imgs[:, ~m] == 0) and np.all(np.isfinite(imgs))
        if sc.parts is not None:  # a piece's normals are its own: differenced within the piece
            k = int(sc.parts[m].max())
            piece = sc.parts == k
            alone = r._renderer(sc, lights).normals_from_depth(np.where(piece, sc.depth, 1.0).astype(np.float32), piece)
            np.testing.assert_allclose(n[piece], alone[piece], atol=1e-6)
    again = shapes.render_random_sample(64, 100, r, n_lights=2, family=family)
    first = shapes.render_random_sample(64, 100, r, n_lights=2, family=family)
    assert np.array_equal(again[2], first[2])  # a sample is a function of its seed


def test_cast_shadows_darken_the_render():
    # the same tabletop scene with and without the shadow pass: shadowed pixels lose their direct light only
    r = shapes.SceneRenderer("cpu")
    sc = shapes.random_scene(64, 3, family="tabletop")
    from gpps.lights import DirectionalLights

    lights = DirectionalLights(np.array([[0.6, 0.0, 0.8]]))
    n = r.normals(sc)
    vis = r.shadows(sc, lights)[0]
    lit = r.render(sc, lights, n, shadows=False, ambient=0.05)[0]
    dark = r.render(sc, lights, n, shadows=True, ambient=0.05)[0]
    fill = 0.05 * sc.albedo * (0.5 + 0.5 * n[..., 2:3])
    assert (~vis & sc.mask).sum() > 0
    np.testing.assert_allclose(dark[~vis & sc.mask], fill[~vis & sc.mask], atol=1e-6)
    np.testing.assert_allclose(dark[vis], lit[vis], atol=1e-6)
