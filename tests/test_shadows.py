"""Cast shadows from a depth map (gpps.kernels.shadows, gpps.pipeline.shadows.CastShadows) on every device.

Against closed-form shadows (tests/shadow_reference.py: a box and a hemisphere on a plane, ray-box and
ray-sphere intersections in 3D per pixel) under both cameras with directional and point lights: the IoU of the
cast-shadow sets (pixels facing the light, n . l > 0, that the solid hides from it) is >= 0.95 for every light,
also on depth with noise of 0.3 pixel widths rms.  Against the same march in numpy float64: equal but for pixels
on a shadow's boundary.  The degenerate lights, the mask's rules, the device AND into a solver's ``valid`` and
the argument checks."""

import numpy as np
import pytest
from shadow_reference import (
    box_scene,
    directional,
    footprint,
    hemisphere_scene,
    iou,
    march_reference,
    perspective,
)

from gpps._runtime import warp
from gpps.camera import Orthographic
from gpps.lights import DirectionalLights, PointLights
from gpps.pipeline.shadows import CastShadows, ShadowConfig

AZIMUTHS = [20, 135, 250, 300]
ELEVATIONS = {"box": [20, 30, 40, 30], "hemisphere": [20, 25, 30, 30]}
_SCENES = {}


def _camera(name):
    """(camera, plane depth): orthographic with a 1-unit pixel, or a 12-degree pinhole 600 units away (a 1-unit
    pixel on the plane)."""
    return (Orthographic(1.0), 150.0) if name == "orthographic" else (perspective(600.0), 600.0)


def _lights(kind, scene, plane_depth):
    if kind == "directional":
        return directional(ELEVATIONS[scene], AZIMUTHS)
    return PointLights([[90.0, 30.0, -plane_depth + 50.0], [-70.0, -60.0, -plane_depth + 60.0]])


def _scene(camera_name, scene):
    key = (camera_name, scene)
    if key not in _SCENES:
        cam, dp = _camera(camera_name)
        _SCENES[key] = (box_scene if scene == "box" else hemisphere_scene)(cam, plane_depth=dp)
    return _SCENES[key]


def _cast_ious(sc, lights, vis):
    """IoU of the cast-shadow sets (facing the light and hidden from it) of each light."""
    va, fa = sc.visible(lights), sc.facing(lights)
    return [iou(~va[k] & fa[k], ~vis[k] & fa[k]) for k in range(len(lights))]


def _march(device, sc, lights, depth=None, mask=None, config=None):
    depth = sc.depth if depth is None else depth
    mask = sc.mask if mask is None else mask
    with CastShadows((len(lights),) + depth.shape, sc.camera, lights, config, device=device) as st:
        return st.run(depth, mask)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
@pytest.mark.parametrize("scene", ["box", "hemisphere"])
@pytest.mark.parametrize("light_kind", ["directional", "point"])
@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_cast_shadows_match_analytic(device, camera, scene, light_kind, noise):
    """IoU >= 0.95 per light against the closed-form shadows; with ``noise`` pixel widths rms of iid depth noise
    (harsher than integration's smooth errors) the default tolerance of 1 pixel width keeps it."""
    sc = _scene(camera, scene)
    lights = _lights(light_kind, scene, sc.plane_depth)
    depth = sc.depth + noise * footprint(sc.camera, sc.depth) * np.random.default_rng(7).standard_normal(sc.depth.shape)
    vis = _march(device, sc, lights, depth=depth)
    ious = _cast_ious(sc, lights, vis)
    print(f"\n{camera} {scene} {light_kind} noise {noise}: IoU " + " ".join(f"{v:.3f}" for v in ious))
    assert min(ious) >= 0.95, ious
    va, fa = sc.visible(lights), sc.facing(lights)
    assert all(np.count_nonzero(~va[k] & fa[k]) > 1000 for k in range(len(lights)))  # shadows worth measuring


@pytest.mark.parametrize("scene", ["box", "hemisphere"])
def test_thin_shadows_lose_their_boundary_pixels(device, scene):
    """The error is a band about one pixel wide along the shadow's outline (the tolerance shortens a shadow by
    tau / tan(elevation) pixels, nearest sampling moves edges by up to half a pixel), so the IoU falls as the
    shadow thins: at elevation 50 the hemisphere's crescent is 12 pixels wide at its tip.  Measured (noise free,
    orthographic, 128^2): box 0.982 / 0.976 / 0.946 at 35 / 40 / 50 degrees, hemisphere 0.965 / 0.950 / 0.930."""
    sc = _scene("orthographic", scene)
    lights = directional([35.0, 40.0, 50.0], [250.0, 250.0, 250.0])
    ious = _cast_ious(sc, lights, _march(device, sc, lights))
    print(f"\northographic {scene} elevations 35/40/50: IoU " + " ".join(f"{v:.3f}" for v in ious))
    assert min(ious) >= 0.88


def test_tolerance_absorbs_depth_noise(device):
    """Why the tolerance: 0.3 pixel widths of depth noise make a quarter-pixel tolerance shadow lit plane
    pixels (the IoU falls below 0.9); one pixel width keeps >= 0.95 (test above)."""
    sc = _scene("orthographic", "box")
    lights = _lights("directional", "box", sc.plane_depth)
    depth = sc.depth + 0.3 * np.random.default_rng(7).standard_normal(sc.depth.shape)
    vis = _march(device, sc, lights, depth=depth, config=ShadowConfig(tolerance_px=0.25))
    assert min(_cast_ious(sc, lights, vis)) < 0.9


def test_strong_perspective_hidden_sides(device):
    """The depth map is a height field along the camera rays: a 46-degree pinhole 150 units from the plane
    sees the box's top but not its walls, so the solid behind the top flares out along the rays and its
    shadow grows (IoU ~0.78); it still covers the true shadow (documented in gpps.kernels.shadows)."""
    cam = perspective(150.0)
    sc = box_scene(cam, plane_depth=150.0)
    lights = _lights("directional", "box", 150.0)
    vis = _march(device, sc, lights)
    va, fa = sc.visible(lights), sc.facing(lights)
    for k in range(len(lights)):
        true, got = ~va[k] & fa[k], ~vis[k] & fa[k]
        assert np.count_nonzero(true & ~got) <= 0.05 * np.count_nonzero(true)
        assert np.count_nonzero(got & ~true) > 0.1 * np.count_nonzero(true)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
@pytest.mark.parametrize("light_kind", ["directional", "point"])
def test_kernel_equals_numpy_reference(device, camera, light_kind):
    """The kernel (float32) against the march in float64 numpy on a noisy hemisphere: equal except at pixels
    on a shadow's boundary (a 4-neighbour with the other value), at most 0.2 % of the pairs."""
    sc = _scene(camera, "hemisphere")
    lights = _lights(light_kind, "hemisphere", sc.plane_depth)
    depth = sc.depth + 0.3 * footprint(sc.camera, sc.depth) * np.random.default_rng(3).standard_normal(sc.depth.shape)
    depth = depth.astype(np.float32)
    got = _march(device, sc, lights, depth=depth)
    ref = march_reference(depth, sc.mask, sc.camera, lights)
    diff = got != ref
    print(f"\n{camera} {light_kind}: {np.count_nonzero(diff)} of {diff.size} differ")
    assert np.count_nonzero(diff) <= 0.002 * diff.size
    pad = np.pad(ref, ((0, 0), (1, 1), (1, 1)), mode="edge")
    boundary = np.zeros_like(ref)
    for di, dj in ((0, 1), (2, 1), (1, 0), (1, 2)):
        boundary |= pad[:, di:di + ref.shape[1], dj:dj + ref.shape[2]] != ref
    assert np.all(boundary[diff])


# ------------------------------------------------------------------------------------------ degenerate cases


def test_light_at_the_horizon(device):
    """Elevation 0: the plane does not shadow itself (its grazing attached shadow is the solvers' business) and
    the box's shadow runs to the image border."""
    sc = _scene("orthographic", "box")
    lights = directional([0.0, 0.0], [20.0, 200.0])
    vis = _march(device, sc, lights)
    plane = sc.depth == sc.plane_depth
    va = sc.visible(lights)
    for k in range(2):
        assert iou(~va[k] & plane, ~vis[k] & plane) >= 0.95
        assert np.count_nonzero(~vis[k] & plane) > 2000


def test_light_behind_the_surface(device):
    """A light behind the plane (directional or point): every ray sinks behind the surface, so every pixel is
    shadowed but those whose ray leaves the image within the tolerance (tau |l_xy| / |l_z| = 1.7 pixels)."""
    cam = Orthographic(1.0)
    h, w = 40, 50
    depth = np.full((h, w), 100.0)
    mask = np.ones((h, w), bool)
    lights = directional([-30.0], [0.0])  # toward +x, below the plane
    with CastShadows((1, h, w), cam, lights, device=device) as st:
        vis = st.run(depth, mask)[0]
    assert not vis[:, : w - 2].any()
    assert vis[:, w - 1].all()
    pl = PointLights([[0.0, 0.0, -200.0]])
    with CastShadows((1, h, w), cam, pl, device=device) as st:
        vis = st.run(depth, mask)[0]
    assert np.count_nonzero(vis) <= 4  # the pixels right over the light (its ray leaves along the view axis)


def test_light_on_the_view_axis(device):
    """Orthographic camera, light along +z: the ray does not move in the image and rises: all lit, box too;
    along -z it sinks behind its own pixel: all shadowed."""
    sc = _scene("orthographic", "box")
    up = DirectionalLights([[0.0, 0.0, 1.0]])
    assert _march(device, sc, up).all()
    down = DirectionalLights([[0.0, 0.0, -1.0]])
    assert not _march(device, sc, down).any()


def test_mask_rules(device):
    """Off the mask the visibility is 1 and the pixels do not occlude (the box cut out of the mask casts
    nothing); an empty mask gives all ones."""
    sc = _scene("orthographic", "box")
    lights = _lights("directional", "box", sc.plane_depth)
    vis = _march(device, sc, lights)
    assert not vis.all()
    holes = sc.depth == sc.plane_depth
    vis = _march(device, sc, lights, mask=holes)
    assert vis.all()
    vis = _march(device, sc, lights, mask=np.zeros_like(sc.mask))
    assert vis.all()


def test_device_path_and_apply(device):
    """``step`` on device buffers (a solver's depth and mask) equals the host upload; ``apply`` ANDs the
    visibility into an (N, H, W) uint8 ``valid`` on the device."""
    wp = warp()
    sc = _scene("perspective", "hemisphere")
    lights = _lights("point", "hemisphere", sc.plane_depth)
    n, (h, w) = len(lights), sc.depth.shape
    with CastShadows((n, h, w), sc.camera, lights, device=device) as st:
        host = st.run(sc.depth, sc.mask)
        st.upload(np.ones((h, w)), np.zeros((h, w), bool))  # other contents in the stage's own buffers
        dep = wp.array(sc.depth.astype(np.float32), dtype=wp.float32, device=st.device)
        msk = wp.array(sc.mask.astype(np.uint8), dtype=wp.uint8, device=st.device)
        st.step(depth=dep, mask=msk)
        assert np.array_equal(st.fetch(), host)
        rng = np.random.default_rng(0)
        valid0 = rng.random((n, h, w)) < 0.8
        valid = wp.array(valid0.astype(np.uint8), dtype=wp.uint8, device=st.device)
        st.apply(valid)
        assert np.array_equal(valid.numpy().astype(bool), valid0 & host)


# --------------------------------------------------------------------------------------------- bad input


def test_bad_input_names_the_argument(device):
    wp = warp()
    cam = Orthographic(1.0)
    L = directional([30.0, 40.0], [0.0, 90.0])
    with pytest.raises(ValueError, match="lights"):
        CastShadows((3, 8, 8), cam, L, device=device)
    with pytest.raises(ValueError, match="shape"):
        CastShadows((2, 0, 8), cam, L, device=device)
    with pytest.raises(TypeError, match="shape"):
        CastShadows((2, 8), cam, L, device=device)
    with pytest.raises(TypeError, match="lights"):
        CastShadows((2, 8, 8), cam, np.zeros((2, 3)), device=device)
    with pytest.raises(TypeError, match="camera"):
        CastShadows((2, 8, 8), "pinhole", L, device=device)
    with pytest.raises(TypeError, match="config"):
        CastShadows((2, 8, 8), cam, L, config={"tolerance_px": 1.0}, device=device)
    with pytest.raises(ValueError, match="tolerance_px"):
        ShadowConfig(tolerance_px=-1.0)
    with pytest.raises(ValueError, match="step_px"):
        ShadowConfig(step_px=0.0)
    with pytest.raises(TypeError, match="max_steps"):
        ShadowConfig(max_steps=2.5)
    st = CastShadows((2, 8, 8), cam, L, device=device)
    m = np.ones((8, 8), bool)
    with pytest.raises(ValueError, match="depth"):
        st.upload(np.ones((8, 9)), m)
    with pytest.raises(ValueError, match="depth"):
        st.upload(-np.ones((8, 8)), m)
    bad = np.ones((8, 8))
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="depth"):
        st.upload(bad, m)
    bad[3, 3] = -1.0  # off the mask: ignored
    st.upload(bad, m & (bad > 0))
    with pytest.raises(ValueError, match="mask"):
        st.upload(np.ones((8, 8)), np.ones((8, 9), bool))
    with pytest.raises(TypeError, match="depth"):
        st.step(depth=np.ones((8, 8), np.float32))
    with pytest.raises(ValueError, match="depth"):
        st.step(depth=wp.ones((8, 8), dtype=wp.float64, device=st.device))
    with pytest.raises(ValueError, match="mask"):
        st.step(mask=wp.ones((8, 9), dtype=wp.uint8, device=st.device))
    with pytest.raises(ValueError, match="valid"):
        st.apply(wp.ones((3, 8, 8), dtype=wp.uint8, device=st.device))
    st.close()
    with pytest.raises(RuntimeError, match="closed"):
        st.step()


def test_on_a_solvers_buffers(device):
    """The path RON would take: march on a PixelSolver's own depth and mask buffers (no copy) and AND the
    visibility into its ``valid`` on the device; the solver's other observations are untouched."""
    from gpps.material import Material
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    sc = _scene("perspective", "box")
    lights = _lights("directional", "box", sc.plane_depth)
    n, (h, w) = len(lights), sc.depth.shape
    images = np.full((n, h, w, 3), 0.5, np.float32)
    solver = PixelSolver((n, h, w), sc.camera, lights, Material.default_for("lambertian"),
                         SolverConfig(solver="none"), device=device)
    valid0 = np.ones((n, h, w), bool)
    valid0[:, :, :10] = False
    solver.upload(images, sc.mask, depth=sc.depth, valid=valid0)
    with CastShadows((n, h, w), sc.camera, lights, device=solver.device) as st:
        st.step(depth=solver.depth, mask=solver.mask)
        st.apply(solver.valid)
        vis = st.fetch()
    assert np.array_equal(vis, _march(device, sc, lights))
    assert np.array_equal(solver.valid.numpy().astype(bool), valid0 & vis)
