"""Tiny kernels exposing the BRDF and light device functions to the tests."""

import warp as wp

from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams, brdf_terms, light_dir, light_radiance, pixel_point


@wp.kernel
def eval_brdf_terms(
    n: wp.array(dtype=wp.vec3), l: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), mat: MaterialParams, out: wp.array(dtype=wp.vec2)
):
    t = wp.tid()
    out[t] = brdf_terms(mat, n[t], l[t], v[t])


@wp.kernel
def eval_lights(p: wp.array(dtype=wp.vec3), lights: LightParams, dirs: wp.array2d(dtype=wp.vec3), rad: wp.array2d(dtype=wp.vec3)):
    t = wp.tid()
    for k in range(lights.count):
        dirs[k, t] = light_dir(lights, k, p[t])
        rad[k, t] = light_radiance(lights, k, p[t])


@wp.kernel
def eval_pixel_points(depth: wp.array2d(dtype=wp.float32), cam: CameraParams, out: wp.array2d(dtype=wp.vec3)):
    i, j = wp.tid()
    out[i, j] = pixel_point(cam, i, j, depth[i, j])
