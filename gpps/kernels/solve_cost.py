"""The solver's cost: the reflectance model's value and gradient, and the variable-projection evaluation.

Device math only, defined per specialisation by factories (see
:mod:`gpps.kernels.solve` for the model and :func:`gpps.kernels.solve_methods.solver_funcs`
for how the functions are put together): ``brdf`` fixed at code generation
through ``wp.static``, or ``None`` for the run-time switch on ``mat.model``.
``module`` / ``sfx``: Warp module and key suffix of the functions (distinct per
specialisation; ``module=None`` puts them in this file's module).
"""

import warp as wp

from gpps import names
from gpps.kernels.brdf import LightParams, MaterialParams, ior_from_f0, light_dir, light_radiance
from gpps.kernels.jacobians import (
    ashikhmin_shirley_value_grad,
    blinn_phong_value_grad,
    chart_normal,
    chart_normal_jacobian,
    conductor_value_grad,
    cook_torrance_value_grad,
    diffuse_value_grad,
    diffuse_value_grad_of,
    phong_value_grad,
    plastic_diffuse_value_grad,
    plastic_value_grad,
    specular_value_grad,
)
from gpps.kernels.solve_common import ASIDE, Eval, Pixel, in_fit, lanes_sum6, lanes_sum19, vec6, vec19

# a light's terms between the evaluation's two passes: radiance (3), observation (3), diffuse and specular values
# and their two chart derivatives (6); one row a light, a thread's first ``cache`` lights (evaluate_for)
TERMS = 12


def specular_value_grad_for(brdf, module, sfx: str):
    """:func:`gpps.kernels.jacobians.specular_value_grad` with the model fixed at code generation.

    Same gating and lobes as the run-time dispatcher (``mat.model`` is not
    read); ``brdf=None`` returns the run-time dispatcher itself.
    """
    if brdf is None:
        return specular_value_grad

    @wp.func(name="specular_value_grad" + sfx, module=module)
    def spec_vg(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
        """Specular value and its gradient in ``n``: ``(s, ds/dn)`` as a vec4 (0 outside the lit, visible side)."""
        if wp.static(brdf == "lambertian" or brdf == "conductor"):
            return wp.vec4(0.0)
        else:
            if wp.dot(n, l) <= 0.0 or wp.dot(n, v) <= 0.0:
                return wp.vec4(0.0)
            if wp.static(brdf == "phong"):
                return phong_value_grad(n, l, v, mat.shininess)
            elif wp.static(brdf == "blinn-phong"):
                return blinn_phong_value_grad(n, l, v, mat.shininess)
            elif wp.static(brdf == "cook-torrance"):
                return cook_torrance_value_grad(n, l, v, mat.roughness, mat.f0)
            elif wp.static(brdf == "ashikhmin-shirley"):
                return ashikhmin_shirley_value_grad(n, l, v, mat.eta_u, mat.eta_v, mat.f0)
            else:
                return plastic_value_grad(n, l, v, mat.roughness, ior_from_f0(mat.f0))

    return spec_vg


def diffuse_value_grad_for(brdf, module, sfx: str):
    """The diffuse factor and its gradient with the model fixed at code generation: plastic's
    :func:`gpps.kernels.jacobians.plastic_diffuse_value_grad`, the conductor's GGX lobe
    (:func:`gpps.kernels.jacobians.conductor_value_grad`), every other model's ``max(n.l, 0)``
    (:func:`gpps.kernels.jacobians.diffuse_value_grad`); ``brdf=None``: the run-time switch
    :func:`gpps.kernels.jacobians.diffuse_value_grad_of`."""
    if brdf is None:
        return diffuse_value_grad_of

    @wp.func(name="diffuse_value_grad" + sfx, module=module)
    def diff_vg(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
        """Diffuse factor and its gradient in ``n``: ``(d, dd/dn)`` as a vec4 (0 in attached shadow)."""
        if wp.static(brdf == "plastic"):
            return plastic_diffuse_value_grad(n, l, v, ior_from_f0(mat.f0))
        elif wp.static(brdf == "conductor"):
            return conductor_value_grad(n, l, v, mat.roughness, mat.f0)
        else:
            return diffuse_value_grad(n, l)

    return diff_vg


def light_terms_for(spec_vg, diff_vg, module, sfx: str):
    """``light_terms``: one light's radiance, observation and model terms with their chart derivatives.

    Args:
        spec_vg: the specular value-and-gradient function (:func:`specular_value_grad_for`).
        diff_vg: the diffuse value-and-gradient function (:func:`diffuse_value_grad_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
    """

    @wp.func(name="light_terms" + sfx, module=module)
    def light_terms(
        images: wp.array3d(dtype=wp.vec3),
        lights: LightParams,
        mat: MaterialParams,
        k: int,
        i: int,
        j: int,
        p: wp.vec3,
        n: wp.vec3,
        v: wp.vec3,
        dn0: wp.vec3,
        dn1: wp.vec3,
    ):
        """Light k at the pixel: radiance, observation, diffuse and specular values and their chart derivatives."""
        l = light_dir(lights, k, p)
        dg = diff_vg(mat, n, l, v)
        sg = spec_vg(mat, n, l, v)
        gd = wp.vec3(dg[1], dg[2], dg[3])
        gs = wp.vec3(sg[1], sg[2], sg[3])
        return (
            light_radiance(lights, k, p),
            images[k, i, j],
            dg[0],
            sg[0],
            wp.dot(gd, dn0),
            wp.dot(gd, dn1),
            wp.dot(gs, dn0),
            wp.dot(gs, dn1),
        )

    return light_terms


def evaluate_for(light_terms, module, sfx: str, lanes: bool = False, cache: int = names.SOLVE_TERM_CACHE):
    """``evaluate``: the reduced cost, its gradient and Gauss-Newton matrix at one normal.

    Args:
        light_terms: the per-light terms (:func:`light_terms_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function (distinct per ``cache`` too).
        lanes: the lights-parallel build: the pixel's lanes (``px.lane`` of ``px.lanes``, one
            block) each sum a strided share of the lights, and each pass's sums are reduced over
            the block before they are used (the same sums in another order: equal up to float
            rounding).  False: one thread sums every light in order.
        cache: lights (a thread's first) whose terms pass 2 reads back from pass 1 instead of evaluating them
            again: a local (cache, 12) matrix, zeroed at every evaluation (:func:`gpps.kernels.solve.term_cache_size`).
    """

    size = int(cache)
    if size < 1:
        raise ValueError(f"cache: expected at least 1 light, got {cache}")
    cache_t = wp.types.matrix(shape=(size, TERMS), dtype=wp.float32)

    @wp.func(name="evaluate" + sfx, module=module)
    def evaluate(
        n0: wp.vec3,
        t1: wp.vec3,
        t2: wp.vec3,
        x: wp.vec2,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
    ):
        """Variable-projection evaluation of the reduced cost at ``n(x)`` (4.2 with kd eliminated).

        Two passes over the lights: the albedo's normal equations (and their
        derivatives) must be complete before the residuals can be formed.  The
        first ``cache`` lights' ``light_terms`` (a thread's first lights in
        the lanes build) are kept in a local matrix between the passes; the
        later lights' are evaluated again in pass 2 (N is a run-time size).
        """
        i = px.i
        j = px.j
        p = px.p
        v = px.v
        grey_albedo = px.grey_albedo
        n = chart_normal(n0, t1, t2, x)
        dn = chart_normal_jacobian(n0, t1, t2, x)
        dn0 = wp.vec3(dn[0, 0], dn[1, 0], dn[2, 0])
        dn1 = wp.vec3(dn[0, 1], dn[1, 1], dn[2, 1])
        ks = mat.ks
        # pass 1: normal equations of the albedo and their derivatives
        saa = wp.vec3(0.0)
        say = wp.vec3(0.0)
        dsaa0 = wp.vec3(0.0)
        dsaa1 = wp.vec3(0.0)
        dsay0 = wp.vec3(0.0)
        dsay1 = wp.vec3(0.0)
        wsum = float(0.0)
        k0 = int(0)
        dk = int(1)
        if wp.static(lanes):
            k0 = px.lane
            dk = px.lanes
        # the first `size` lights' terms are kept for pass 2 (dark observations, w < 0, included: pass 2
        # reads them); the values are the same as evaluating them again, so the sums are too
        kept = cache_t()
        for k in range(k0, lights.count, dk):
            w = weights[k, i, j]
            slot = (k - k0) // dk
            if w > 0.0 or (w < 0.0 and w != ASIDE and slot < size):
                e, obs, dval, sval, da0, da1, ds0, ds1 = light_terms(images, lights, mat, k, i, j, p, n, v, dn0, dn1)
                if slot < size:
                    for c in range(3):
                        kept[slot, c] = e[c]
                        kept[slot, 3 + c] = obs[c]
                    kept[slot, 6] = dval
                    kept[slot, 7] = sval
                    kept[slot, 8] = da0
                    kept[slot, 9] = da1
                    kept[slot, 10] = ds0
                    kept[slot, 11] = ds1
                if w > 0.0:
                    wsum += w
                    for c in range(3):
                        a = e[c] * dval
                        y = obs[c] - e[c] * ks * sval
                        a0 = e[c] * da0
                        a1 = e[c] * da1
                        y0 = -e[c] * ks * ds0
                        y1 = -e[c] * ks * ds1
                        saa[c] += w * a * a
                        say[c] += w * a * y
                        dsaa0[c] += w * 2.0 * a * a0
                        dsaa1[c] += w * 2.0 * a * a1
                        dsay0[c] += w * (a0 * y + a * y0)
                        dsay1[c] += w * (a1 * y + a * y1)
        if wp.static(lanes):
            t = vec19()
            for c in range(3):
                t[c] = saa[c]
                t[3 + c] = say[c]
                t[6 + c] = dsaa0[c]
                t[9 + c] = dsaa1[c]
                t[12 + c] = dsay0[c]
                t[15 + c] = dsay1[c]
            t[18] = wsum
            t = lanes_sum19(t)
            saa = wp.vec3(t[0], t[1], t[2])
            say = wp.vec3(t[3], t[4], t[5])
            dsaa0 = wp.vec3(t[6], t[7], t[8])
            dsaa1 = wp.vec3(t[9], t[10], t[11])
            dsay0 = wp.vec3(t[12], t[13], t[14])
            dsay1 = wp.vec3(t[15], t[16], t[17])
            wsum = t[18]
        if grey_albedo != 0:
            saa = wp.vec3(saa[0] + saa[1] + saa[2])
            say = wp.vec3(say[0] + say[1] + say[2])
            dsaa0 = wp.vec3(dsaa0[0] + dsaa0[1] + dsaa0[2])
            dsaa1 = wp.vec3(dsaa1[0] + dsaa1[1] + dsaa1[2])
            dsay0 = wp.vec3(dsay0[0] + dsay0[1] + dsay0[2])
            dsay1 = wp.vec3(dsay1[0] + dsay1[1] + dsay1[2])
        kd = wp.vec3(0.0)
        dkd0 = wp.vec3(0.0)
        dkd1 = wp.vec3(0.0)
        if px.fix_kd != 0:
            kd = px.kd
        for c in range(3):
            if px.fix_kd == 0 and saa[c] > 1.0e-20:
                kc = say[c] / saa[c]
                if kc > 0.0:
                    kd[c] = kc
                    dkd0[c] = (dsay0[c] - kc * dsaa0[c]) / saa[c]
                    dkd1[c] = (dsay1[c] - kc * dsaa1[c]) / saa[c]
        # pass 2: residuals r = y - kd a and their exact derivatives
        cost = float(0.0)
        jtj = wp.mat22(0.0)
        jtr = wp.vec2(0.0)
        for k in range(k0, lights.count, dk):
            w = weights[k, i, j]
            if in_fit(w):
                slot = (k - k0) // dk
                e = wp.vec3(0.0)
                obs = wp.vec3(0.0)
                dval = float(0.0)
                sval = float(0.0)
                da0 = float(0.0)
                da1 = float(0.0)
                ds0 = float(0.0)
                ds1 = float(0.0)
                if slot < size:
                    e = wp.vec3(kept[slot, 0], kept[slot, 1], kept[slot, 2])
                    obs = wp.vec3(kept[slot, 3], kept[slot, 4], kept[slot, 5])
                    dval = kept[slot, 6]
                    sval = kept[slot, 7]
                    da0 = kept[slot, 8]
                    da1 = kept[slot, 9]
                    ds0 = kept[slot, 10]
                    ds1 = kept[slot, 11]
                else:
                    e, obs, dval, sval, da0, da1, ds0, ds1 = light_terms(images, lights, mat, k, i, j, p, n, v, dn0,
                                                                         dn1)
                for c in range(3):
                    a = e[c] * dval
                    r = obs[c] - e[c] * ks * sval - kd[c] * a
                    # a dark observation (w < 0) only bounds the model from above: n.l <= about 0
                    if w > 0.0 or r < 0.0:
                        wa = wp.abs(w)
                        j0 = -e[c] * ks * ds0 - dkd0[c] * a - kd[c] * e[c] * da0
                        j1 = -e[c] * ks * ds1 - dkd1[c] * a - kd[c] * e[c] * da1
                        cost += 0.5 * wa * r * r
                        jtr += wa * r * wp.vec2(j0, j1)
                        jtj += wa * wp.mat22(j0 * j0, j0 * j1, j0 * j1, j1 * j1)
        if wp.static(lanes):
            u = lanes_sum6(vec6(cost, jtr[0], jtr[1], jtj[0, 0], jtj[0, 1], jtj[1, 1]))
            cost = u[0]
            jtr = wp.vec2(u[1], u[2])
            jtj = wp.mat22(u[3], u[4], u[4], u[5])
        if px.prior_w > 0.0:
            dp = n - px.prior_n
            cost += 0.5 * px.prior_w * wp.dot(dp, dp)
            jtr += px.prior_w * wp.vec2(wp.dot(dn0, dp), wp.dot(dn1, dp))
            jtj += px.prior_w * wp.mat22(wp.dot(dn0, dn0), wp.dot(dn0, dn1), wp.dot(dn0, dn1), wp.dot(dn1, dn1))
        ev = Eval()
        ev.cost = cost
        ev.jtj = jtj
        ev.jtr = jtr
        ev.kd = kd
        ev.wsum = wsum
        return ev

    return evaluate
