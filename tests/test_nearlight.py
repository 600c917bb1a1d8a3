"""The near-light capture reader (gpps.io.nearlight) on the real hehe12 capture, and a smoke reconstruction."""

import numpy as np
import pytest

from gpps.camera import Perspective
from gpps.lights import PointLights
from gpps.io.nearlight import aim_distance, estimate_distance, read_nearlight

# a window on the object (full-resolution pixels: rows 300-620, columns 760-1180), 8x smaller
CROP = (300, 620, 760, 1180)


@pytest.fixture(scope="module")
def capture(data_root):
    root = data_root / "nearlight" / "hehe12"
    if not root.is_dir():
        pytest.skip(f"near-light capture not found at {root}")
    return read_nearlight(root, downsample=4), root


def test_reader_shapes_camera_and_lights(capture):
    cap, _ = capture
    assert cap.images.shape == (8, 300, 480) and cap.images.dtype == np.float32
    assert cap.mask.shape == (300, 480) and cap.mask.dtype == bool and 15000 < cap.mask.sum() < 30000
    assert cap.saturated.shape == cap.images.shape
    assert np.all(np.isfinite(cap.images)) and cap.images.min() >= 0
    # camera.mat stores K transposed; downsampling by 4 scales f and moves the centre to (c - 1.5) / 4
    assert isinstance(cap.camera, Perspective)
    np.testing.assert_allclose(cap.K[2], [0, 0, 1])
    assert cap.K[0, 1] == cap.K[1, 0] == 0
    np.testing.assert_allclose([cap.K[0, 0], cap.K[1, 1]], [3043.07961 / 4, 3026.46497 / 4], rtol=1e-6)
    np.testing.assert_allclose([cap.K[0, 2], cap.K[1, 2]], [(970.607028 - 1.5) / 4, (762.656992 - 1.5) / 4], rtol=1e-6)
    assert isinstance(cap.lights, PointLights) and len(cap.lights) == 8 and cap.phi.shape == (8,)
    np.testing.assert_allclose(cap.lights.mu, 1.0)


def test_reader_frame_conventions(capture):
    """gpps frame: camera at the origin, x right, y up, z toward the camera (the scene has z < 0)."""
    cap, _ = capture
    pos, ax = cap.lights.positions, cap.lights.axes
    # LEDs ~74 mm in front of the camera centre, aimed into the scene and inward toward the optical axis
    assert np.all(pos[:, 2] < -60) and np.all(ax[:, 2] < 0)
    assert np.all(np.sign(ax[:, :2]) == -np.sign(pos[:, :2]))
    assert 80 < cap.working_distance < 400
    # y up: LEDs above the axis (y > 0) light the top rows of the object more than the bottom rows
    rows = np.flatnonzero(cap.mask.any(1))
    third = (rows.max() - rows.min()) // 3
    top, bottom = cap.mask.copy(), cap.mask.copy()
    top[rows.min() + third:] = False
    bottom[: rows.max() - third] = False
    ratio = np.array([im[top].mean() / im[bottom].mean() for im in cap.images])
    up = pos[:, 1] > 0
    assert ratio[up].min() > ratio[~up].max()
    # x right: LEDs on the left (x < 0) light the left half more
    cols = np.flatnonzero(cap.mask.any(0))
    left = cap.mask.copy()
    left[:, (cols.min() + cols.max()) // 2:] = False
    right = cap.mask & ~left
    lr = np.array([im[left].mean() / im[right].mean() for im in cap.images])
    assert lr[pos[:, 0] < 0].mean() > lr[pos[:, 0] > 0].mean()


def test_distance_estimate_has_an_interior_minimum(capture):
    cap, _ = capture
    best, scores = estimate_distance(cap.images, cap.mask, cap.camera, cap.lights, np.geomspace(100, 1000, 13),
                                     samples=1000)
    assert 150 < best < 400
    assert scores[best] < scores[100.0] and scores[best] < scores[1000.0]


def test_aim_distance_and_bad_input(capture, tmp_path):
    S = np.array([[50.0, 0, 0], [-50, 0, 0], [0, 50, 0]])
    D = np.array([[-1.0, 0, 1], [1, 0, 1], [0, -1, 1]])
    assert aim_distance(S, D) == pytest.approx(50.0)
    _, root = capture
    with pytest.raises(ValueError, match="downsample"):
        read_nearlight(root, downsample=0)
    with pytest.raises(ValueError, match="crop"):
        read_nearlight(root, crop=(0, 10, 0, 10))  # no object pixels there
    with pytest.raises(FileNotFoundError, match="root"):
        read_nearlight(tmp_path / "missing")


def test_smoke_reconstruct_on_a_downsampled_crop(capture):
    from gpps.material import Material
    from gpps.flows.ron import RONConfig
    from gpps.pipeline.solver import SolverConfig
    from gpps.flows.reconstruction import reconstruct

    _, root = capture
    cap = read_nearlight(root, downsample=8, crop=CROP)
    assert cap.images.shape == (8, 40, 52)
    np.testing.assert_allclose(cap.K[0, 2], (970.607028 - 760 - 3.5) / 8, rtol=1e-6)
    # the material is given (its fit is exercised by tests/test_ron.py): two rounds of normals and depth
    cfg = RONConfig(rounds=2, solver=SolverConfig(robust="cauchy", shadow_threshold=0.02, starts=2, max_iters=20))
    mat = Material("blinn-phong", ks=0.1, shininess=30.0)
    rec = reconstruct(cap.images, cap.mask, cap.lights, camera=cap.camera, material=mat,
                      reference_depth=230.0, valid=~cap.saturated, config=cfg, device="cpu")
    d = rec.depth[rec.depth_mask]
    assert rec.depth_mask.sum() > 0.9 * cap.mask.sum()
    assert np.all(np.isfinite(d)) and np.all(d > 0)
    assert abs(d.mean() - 230.0) < 5.0
    n = rec.normals[cap.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-3)
    assert np.mean(n[:, 2]) > 0.5  # facing the camera
