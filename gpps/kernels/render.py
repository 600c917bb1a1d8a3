"""Forward image formation kernels (seed ch. 2)."""

import warp as wp

from gpps.kernels.brdf import (
    CameraParams,
    LightParams,
    MaterialParams,
    light_dir,
    light_radiance,
    pixel_point,
    shade,
    view_dir,
)


@wp.kernel
def render_kernel(
    depth: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    mask: wp.array2d(dtype=wp.uint8),
    albedo: wp.array2d(dtype=wp.vec3),
    cam: CameraParams,
    lights: LightParams,
    mat: MaterialParams,
    images: wp.array3d(dtype=wp.vec3),
):
    """Render N images (N, H, W) RGB; one thread per pixel, zero outside the mask.

    Args:
        depth: (H, W) depth > 0 (scene units) inside the mask.
        normals: (H, W) unit normals (gpps frame) inside the mask.
        mask: (H, W) 1 inside the object.
        albedo: (H, W) RGB diffuse colour kd.
        images: (N, H, W) output.
    """
    i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        for k in range(lights.count):
            images[k, i, j] = wp.vec3(0.0)
        return
    p = pixel_point(cam, i, j, depth[i, j])
    v = view_dir(cam, p)
    n = normals[i, j]
    kd = albedo[i, j]
    for k in range(lights.count):
        l = light_dir(lights, k, p)
        images[k, i, j] = shade(mat, kd, n, l, v, light_radiance(lights, k, p))


@wp.func
def _point_at(cam: CameraParams, depth: wp.array2d(dtype=wp.float32), i: int, j: int):
    return pixel_point(cam, i, j, depth[i, j])


@wp.kernel
def normals_from_depth_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    cam: CameraParams,
    normals: wp.array2d(dtype=wp.vec3),
):
    """Unit normals from a depth map by differences of back-projected points (2.33-2.34).

    ``n ~ dP/du x dP/d(-v)`` with central differences inside the mask and
    one-sided ones at its border (u to the right, -v up, so n points to the
    camera).  Pixels with no masked neighbour along an axis get (0, 0, 1)
    components from the other axis only; isolated pixels get (0, 0, 1).
    """
    i, j = wp.tid()
    h = depth.shape[0]
    w = depth.shape[1]
    if mask[i, j] == wp.uint8(0):
        normals[i, j] = wp.vec3(0.0)
        return
    p = _point_at(cam, depth, i, j)
    # derivative along +u (columns)
    jl = j
    jr = j
    if j > 0 and mask[i, j - 1] != wp.uint8(0):
        jl = j - 1
    if j < w - 1 and mask[i, j + 1] != wp.uint8(0):
        jr = j + 1
    # derivative along -v (rows go down, so "up" is i - 1)
    iu = i
    idn = i
    if i > 0 and mask[i - 1, j] != wp.uint8(0):
        iu = i - 1
    if i < h - 1 and mask[i + 1, j] != wp.uint8(0):
        idn = i + 1
    du = wp.vec3(1.0, 0.0, 0.0)
    dv = wp.vec3(0.0, 1.0, 0.0)
    if jr != jl:
        du = _point_at(cam, depth, i, jr) - _point_at(cam, depth, i, jl)
    if iu != idn:
        dv = _point_at(cam, depth, iu, j) - _point_at(cam, depth, idn, j)
    n = wp.cross(du, dv)
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
        if wp.dot(n, view_dir(cam, p)) < 0.0:
            n = -n
    else:
        n = wp.vec3(0.0, 0.0, 1.0)
    normals[i, j] = n
