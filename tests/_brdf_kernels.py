"""Tiny kernels exposing the BRDF and light device functions to the tests."""

import warp as wp

from gpps.kernels.brdf import (
    CameraParams,
    LightParams,
    MaterialParams,
    brdf_terms,
    fresnel_dielectric,
    ior_from_f0,
    light_dir,
    light_radiance,
    pixel_point,
)
from gpps.kernels.jacobians import fresnel_dielectric_value_grad


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


@wp.kernel
def eval_fresnel(c: wp.array(dtype=wp.float32), eta: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec3)):
    """out[t] = (F(c, eta) of the renderer, F and dF/dc of the Jacobians)."""
    t = wp.tid()
    g = fresnel_dielectric_value_grad(c[t], eta[t])
    out[t] = wp.vec3(fresnel_dielectric(c[t], eta[t]), g[0], g[1])


@wp.kernel
def eval_ior(f0: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    t = wp.tid()
    out[t] = ior_from_f0(f0[t])
