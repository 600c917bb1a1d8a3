"""Cast shadows from a depth map: march from each surface point toward each light over the depth map.

Device math only; the buffers live in :class:`gpps.pipeline.shadows.CastShadows`.  The frame and the
cameras are :mod:`gpps.camera`'s (depth ``d = -z``), the lights :mod:`gpps.lights`' (directions toward the
lights; point lights at positions).

For the surface point ``P0`` seen at pixel ``(i, j)`` with depth ``d0`` and light ``k`` the ray is
``P(t) = P0 + t * l`` with ``l`` the unit direction toward the light, ``t`` in scene units, up to the light
(point lights: ``t < |Y - P0|``) or without end (directional).  The march steps along the ray's image:
each step advances ``t`` by ``step_px / |d(u, v)/dt|`` (the image speed at the current point: constant for the
orthographic camera, for the perspective one the derivative of ``u = cx + fx x / d``, ``v = cy - fy y / d``),
so that consecutive samples are about ``step_px`` pixels apart whatever the camera.  At each sample the
depth map is read at the ray point's projection ``(u, v)`` and the observation is **shadowed** when the
surface there lies in front of the ray (closer to the camera) by more than the tolerance::

    d_surface(u, v) < d_ray(t) - tol,      tol = tau * footprint(d0)

``footprint(d)`` is the side of one pixel on the surface: ``pixel_size`` (orthographic), ``d / max(fx, fy)``
(perspective), so the tolerance is ``tau`` pixel widths: relative to depth under the perspective camera
(``tau / fx`` of the depth, the way integration errors of a log-depth grow), and to the pixel size under the
orthographic one, whose depth carries an arbitrary offset (a tolerance relative to that depth would change
with the reference depth).  Depth integrated from normals is wrong by a fraction of a pixel width between
neighbours; the tolerance absorbs that and the self-shadowing of rays that graze the surface.  It costs
``tau / tan(elevation)`` pixels of each shadow's length.  Chosen with iid depth noise of 0.3 pixel widths rms
(harsher than integration's smooth errors) on the analytic scenes (box, hemisphere of radius 32 on a plane,
128^2, both cameras, elevations 25-50 degrees; the worst light's IoU): tau = 0.25 gives 0.74-0.87 (noise pokes
through the rays), 0.5 gives 0.87-0.95, 1 gives 0.92-0.95 and 2 shortens the shadows (0.85-0.90 already
without noise).  The default is 1 (:class:`gpps.pipeline.shadows.ShadowConfig`).

The depth map is read at the **nearest** pixel: a depth map of an object is piecewise smooth with depth edges
at occluding contours, and nearest sampling keeps an edge where it is (half-way between the pixel centres)
while bilinear sampling turns it into a one-pixel ramp that erodes every occluder by half a pixel and shrinks
its shadow.  Bilinear sampling also cuts the chords of convex occluders.  Measured on the same scenes without
noise (tolerance 1, the worst light's IoU, nearest / bilinear): orthographic box 0.946 / 0.919, hemisphere
0.934 / 0.912, perspective box 0.921 / 0.897, hemisphere 0.940 / 0.916.  The staircase of nearest sampling
on slanted surfaces is what the tolerance absorbs (at most half a pixel times the slope; the ray climbs away
from the surface it leaves).  A pixel off the mask does not occlude: the march goes on across holes (another
part of the object can cast a shadow over them), and ends lit when the ray leaves the image, reaches a point light, goes
behind the camera plane (perspective), rises in front of the nearest surface point of the whole map (``d_ray <
dmin - tol``: nothing can occlude it any more) or has taken ``max_steps`` steps.  Where the ray does not move
in the image (a directional light on the optical axis of the orthographic camera) the step in ``t`` is capped
at ``8 * step_px`` footprints: the ray then rises in front of the surface (lit) or sinks behind it (shadowed)
within a few steps.

The depth map is a height field along the camera rays: everything behind the visible surface counts as
solid, so a ray that sinks behind the surface (a light behind the surface, a wall hidden from the camera) is
shadowed.  Under a wide-angle pinhole the hidden sides of an occluder thus flare out along the camera rays
(by ``height * r / d`` at a distance ``r`` from the optical axis) and its shadow grows: a box 40 units tall,
150 units from a 46-degree pinhole, casts shadows with IoU ~0.78 that still cover the true ones
(tests/test_shadows.py); at 12 degrees (600 units) the flare is under 2 pixels.
Attached shadows (``n . l <= 0``) mostly come out shadowed too (the ray enters the surface at once), but
near the terminator the tolerance lets them pass: the solvers' model handles attached shadows (``max(n.l,
0)``), this mask is for the cast ones.
"""

import warp as wp

from gpps.kernels.brdf import POINT, CameraParams, LightParams, light_dir, pixel_point

__all__ = ["cast_shadow_kernel", "min_depth_kernel", "and_visible_kernel", "shadowed_valid_kernel"]

BIG = wp.constant(1.0e30)


@wp.func
def footprint(cam: CameraParams, d: float):
    """Side of one pixel on a surface at depth ``d`` (scene units)."""
    if cam.perspective != 0:
        return d / wp.max(cam.fx, cam.fy)
    return cam.pixel_size


@wp.func
def project_u(cam: CameraParams, p: wp.vec3):
    """Image column ``u`` of the point ``p`` (depth ``-p.z`` > 0 for the pinhole)."""
    if cam.perspective != 0:
        return cam.cx + cam.fx * p[0] / (-p[2])
    return cam.cx + p[0] / cam.pixel_size


@wp.func
def project_v(cam: CameraParams, p: wp.vec3):
    """Image row ``v`` of the point ``p`` (rows go down, y goes up)."""
    if cam.perspective != 0:
        return cam.cy - cam.fy * p[1] / (-p[2])
    return cam.cy - p[1] / cam.pixel_size


@wp.func
def image_speed(cam: CameraParams, p: wp.vec3, l: wp.vec3):
    """``|d(u, v)/dt|`` of the ray ``p + t l`` at ``t = 0``, pixels per scene unit."""
    if cam.perspective != 0:
        d = -p[2]
        du = cam.fx * (l[0] * d + p[0] * l[2]) / (d * d)
        dv = -cam.fy * (l[1] * d + p[1] * l[2]) / (d * d)
        return wp.sqrt(du * du + dv * dv)
    return wp.sqrt(l[0] * l[0] + l[1] * l[1]) / cam.pixel_size


@wp.func
def depth_at(depth: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8), u: float, v: float):
    """Surface depth at the image point ``(u, v)``: the nearest pixel's, or -1 when that pixel is off the
    image or the mask (no surface: it does not occlude)."""
    j = int(wp.floor(u + 0.5))
    i = int(wp.floor(v + 0.5))
    if i >= 0 and j >= 0 and i < depth.shape[0] and j < depth.shape[1]:
        if mask[i, j] != wp.uint8(0):
            return depth[i, j]
    return -1.0


@wp.func
def march(depth: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8), cam: CameraParams,
          p0: wp.vec3, l: wp.vec3, t_end: float, dmin: float, tau: float, step_px: float, max_steps: int):
    """1 when the ray ``p0 + t l`` (0 < t < t_end) reaches its light over the depth map, 0 when shadowed."""
    h = float(depth.shape[0])
    w = float(depth.shape[1])
    fp = footprint(cam, -p0[2])
    tol = tau * fp
    floor_speed = 1.0 / (8.0 * fp)  # caps a step at 8 footprints per pixel of step
    t = float(0.0)
    p = p0
    for _s in range(max_steps):
        t = t + step_px / wp.max(image_speed(cam, p, l), floor_speed)
        if t >= t_end:
            return 1
        p = p0 + t * l
        dr = -p[2]
        if dr <= 0.0:
            return 1  # behind the camera plane: nothing in the image occludes it
        if l[2] > 0.0 and dr - tol < dmin:
            return 1  # in front of every surface point and rising
        u = project_u(cam, p)
        v = project_v(cam, p)
        if u < -0.5 or v < -0.5 or u > w - 0.5 or v > h - 0.5:
            return 1
        ds = depth_at(depth, mask, u, v)
        if ds > 0.0 and ds < dr - tol:
            return 0
    return 1


@wp.kernel(enable_backward=False)
def cast_shadow_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    cam: CameraParams,
    lights: LightParams,
    dmin: wp.array(dtype=wp.float32),
    tau: float,
    step_px: float,
    max_steps: int,
    visible: wp.array3d(dtype=wp.uint8),
):
    """Visibility of every (light, pixel) pair (dim (N, H, W)).

    Args:
        depth: (H, W) depth (> 0 in the mask, scene units).
        mask: (H, W) 1 on the object.
        cam: the camera; lights: the N lights.
        dmin: (1,) the smallest depth in the mask (:data:`min_depth_kernel`).
        tau: the tolerance in pixel widths (module docstring).
        step_px: march step in pixels.
        max_steps: the most steps of one march (then lit).
        visible: (N, H, W) out: 1 lit, 0 in a cast shadow; 1 off the mask.
    """
    k, i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        visible[k, i, j] = wp.uint8(1)
        return
    p0 = pixel_point(cam, i, j, depth[i, j])
    t_end = BIG
    l = lights.vec[k]
    if lights.kind == POINT:
        dl = l - p0
        t_end = wp.length(dl)
        l = dl / wp.max(t_end, 1.0e-30)
    visible[k, i, j] = wp.uint8(march(depth, mask, cam, p0, l, t_end, dmin[0], tau, step_px, max_steps))


@wp.kernel(enable_backward=False)
def min_depth_kernel(depth: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8),
                     dmin: wp.array(dtype=wp.float32)):
    """``dmin[0] = min(dmin[0], depth)`` over the mask (dim (H, W); set ``dmin[0]`` large first)."""
    i, j = wp.tid()
    if mask[i, j] != wp.uint8(0):
        wp.atomic_min(dmin, 0, depth[i, j])


@wp.kernel(enable_backward=False)
def and_visible_kernel(visible: wp.array3d(dtype=wp.uint8), valid: wp.array3d(dtype=wp.uint8)):
    """``valid &= visible`` (dim (N, H, W)): drop the shadowed observations from a solver's ``valid``."""
    k, i, j = wp.tid()
    if visible[k, i, j] == wp.uint8(0):
        valid[k, i, j] = wp.uint8(0)


@wp.func
def cast_shadowed(visible: wp.array3d(dtype=wp.uint8), k: int, i: int, j: int, n: wp.vec3, p: wp.vec3,
                  lights: LightParams, facing_min: float) -> bool:
    """Observation ``k`` of pixel (i, j) is in a cast shadow: the march found the light hidden and the surface
    faces it (``n . l > facing_min``).  Where it faces away the observation is in the attached shadow, which the
    image model explains (its shading term is 0 there): it stays."""
    if visible[k, i, j] != wp.uint8(0):
        return False
    return wp.dot(n, light_dir(lights, k, p)) > facing_min


@wp.kernel(enable_backward=False)
def shadowed_valid_kernel(valid0: wp.array3d(dtype=wp.uint8), visible: wp.array3d(dtype=wp.uint8),
                          mask: wp.array2d(dtype=wp.uint8), normals: wp.array2d(dtype=wp.vec3),
                          depth: wp.array2d(dtype=wp.float32), cam: CameraParams, lights: LightParams,
                          facing_min: float, keep_below: int, valid: wp.array3d(dtype=wp.uint8),
                          counts: wp.array(dtype=wp.int32)):
    """``valid = valid0 & not cast_shadowed`` per pixel (dim (H, W)), recomputed from ``valid0`` (nothing
    accumulates); :func:`cast_shadowed` with the pixel's current ``normals`` and its point at ``depth``.

    A mask pixel whose shadowed observations would leave it fewer than ``keep_below`` valid ones keeps
    ``valid0`` instead (``keep_below = 0``: never; the solver then flags the pixels left with fewer than 3).
    Off the mask ``valid = valid0``.

    Args:
        valid0: (N, H, W) the observations before shadows (1 = use).
        visible: (N, H, W) 1 lit, 0 in a cast shadow.
        mask: (H, W) 1 on the pixels the shadows apply to.
        keep_below: see above.
        valid: (N, H, W) out.
        counts: (3,) int32, added to: [0] observations dropped, [1] pixels that kept ``valid0`` (the rule
            above), [2] pixels left with fewer than 3 valid observations by the drop.
    """
    i, j = wp.tid()
    n = valid0.shape[0]
    on = mask[i, j] != wp.uint8(0)
    nrm = normals[i, j]
    p = pixel_point(cam, i, j, depth[i, j])
    c0 = int(0)
    c = int(0)
    if on:
        for k in range(n):
            if valid0[k, i, j] != wp.uint8(0):
                c0 += 1
                if not cast_shadowed(visible, k, i, j, nrm, p, lights, facing_min):
                    c += 1
    drop = c0 - c
    keep = (not on) or drop == 0 or c < keep_below
    for k in range(n):
        v = valid0[k, i, j]
        if not keep and cast_shadowed(visible, k, i, j, nrm, p, lights, facing_min):
            v = wp.uint8(0)
        valid[k, i, j] = v
    if drop > 0:
        if keep:
            wp.atomic_add(counts, 1, 1)
        else:
            wp.atomic_add(counts, 0, drop)
            if c < 3:
                wp.atomic_add(counts, 2, 1)
