"""The per-pixel solvers: Levenberg-Marquardt, Powell's dog leg and BFGS, their multi-start and IRLS driver.

Device math only, defined per specialisation ``(method, brdf, robust)`` by
:func:`solver_funcs` (see :mod:`gpps.kernels.solve`): each solver's function
comes from a factory of its own that closes over the cost evaluation of the
reflectance model, and the ``wp.static`` conditions of ``run_method`` and
``solve_pixel`` keep only the chosen solver and loss at code generation.
``None`` for a choice keeps it a run-time switch (the generic build).
"""

from types import SimpleNamespace

import warp as wp

from gpps import names

from gpps.kernels.brdf import LightParams, MaterialParams, light_dir, light_radiance
from gpps.kernels.jacobians import chart_normal, chart_normal_jacobian, tangent_basis_t1
from gpps.kernels.solve_common import (
    ASIDE,
    BFGS,
    CAST_CONFLICT,
    DOGLEG,
    ROBUST_HUBER,
    Pixel,
    PixelSolution,
    SolverParams,
    StartResult,
    brightest_half_vector,
    brightest_half_vector_lanes,
    dot2,
    grey,
    grey_lit_level,
    in_fit,
    lanes_sum,
    lanes_sum19,
    solve22,
    start_normal,
    start_result,
    toward_camera,
    transport,
    vec19,
)
from gpps.kernels.solve_cost import diffuse_value_grad_for, evaluate_for, light_terms_for, specular_value_grad_for

HELD_DARK_CONFLICT = wp.constant(names.HELD_DARK_CONFLICT)


def lm_for(evaluate, module, sfx: str):
    """``run_lm``: Levenberg-Marquardt from one start normal.

    Args:
        evaluate: the cost evaluation (:func:`gpps.kernels.solve_cost.evaluate_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
    """

    @wp.func(name="run_lm" + sfx, module=module)
    def run_lm(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Levenberg-Marquardt (Algorithm 4; Madsen-Nielsen damping update), chart re-centred at each accepted step.

        ``d = -(J^T J + lambda I)^-1 J^T r``; gain ratio
        ``rho = (F(x) - F(x + d)) / (1/2 d^T (lambda d - J^T r))`` (Algorithm 4's
        denominator is ``L(0) - L(d)`` of the Gauss-Newton model); accepted steps
        shrink lambda by ``max(1/3, 1 - (2 rho - 1)^3)``, rejected ones grow it by
        ``nu`` and double ``nu``.  Stops on ``|J^T r|_inf <= tol_grad``, a step
        ``<= tol_step`` (radians), or ``max_iters`` evaluations.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        zero = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, zero, images, weights, px, lights, mat)
        lam = prm.lm_tau * wp.max(wp.max(ev.jtj[0, 0], ev.jtj[1, 1]), 1.0e-20)
        nu = float(2.0)
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad:
                converged = 1
                if prm.early_exit != 0:
                    break
            a = ev.jtj + wp.mat22(lam, 0.0, 0.0, lam)
            d = -solve22(a, g)
            k += 1
            if wp.length(d) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            trial = evaluate(n0, t1, t2, d, images, weights, px, lights, mat)
            pred = 0.5 * (lam * dot2(d, d) - dot2(d, g))
            rho = float(-1.0)
            ok = pred > 0.0
            if ok and px.visible_only != 0:
                ok = wp.dot(chart_normal(n0, t1, t2, d), px.v) > 0.0
            if ok:
                rho = (ev.cost - trial.cost) / pred
            if rho > 0.0:
                # re-centre the chart on the accepted normal, reusing the trial's Jacobian
                dn_old = chart_normal_jacobian(n0, t1, t2, d)
                n0 = chart_normal(n0, t1, t2, d)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                ev = transport(trial, dn_old, t1, t2)
                t = 2.0 * rho - 1.0
                lam = lam * wp.max(1.0 / 3.0, 1.0 - t * t * t)
                nu = 2.0
            else:
                lam = lam * nu
                nu = 2.0 * nu
                if lam > 1.0e16:
                    converged = 1
                    if prm.early_exit != 0:
                        break
        return start_result(n0, ev, k, converged)

    return run_lm


def dogleg_for(evaluate, module, sfx: str):
    """``run_dogleg``: Powell's dog leg from one start normal.

    Args:
        evaluate: the cost evaluation (:func:`gpps.kernels.solve_cost.evaluate_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
    """

    @wp.func(name="run_dogleg" + sfx, module=module)
    def run_dogleg(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Powell's dog leg (Algorithm 5, 4.10-4.15) on the reduced problem.

        ``h_sd = -g`` with ``g = J^T r`` and Cauchy step length
        ``alpha = |g|^2 / |J g|^2`` (4.15); ``h_gn = -(J^T J)^-1 g`` (the
        least-squares form of 4.10 for N > 2 residuals); the dog-leg step is
        (4.12-4.14) with beta chosen so that ``|h_dl| = Delta``.

        Algorithm 5's ``L(0) - L(h_dl)`` is garbled in the text; the correct gain
        ratio denominator is the decrease of the Gauss-Newton model
        ``L(0) - L(h) = -h^T g - 1/2 h^T J^T J h``, which reduces to Madsen et al.'s
        cases: ``F(x)`` for the Gauss-Newton step (when J is square), ``Delta (2
        |alpha g| - Delta) / (2 alpha)`` for the clipped steepest-descent step and
        ``1/2 alpha (1 - beta)^2 |g|^2 + beta (2 - beta) F(x)`` otherwise.  We
        evaluate the general expression.  Radius: ``rho > 0.75`` ->
        ``Delta = max(Delta, 3 |h|)``, ``rho < 0.25`` -> ``Delta / 2``.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        zero = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, zero, images, weights, px, lights, mat)
        delta = prm.dogleg_radius
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad or delta <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            a = ev.jtj
            gag = dot2(g, a * g)
            gg = dot2(g, g)
            alpha = float(0.0)
            if gag > 0.0:
                alpha = gg / gag
            hgn = -solve22(a, g)
            if dot2(hgn, hgn) == 0.0:
                # singular J^T J: a tiny damping keeps the Gauss-Newton leg defined
                tr = a[0, 0] + a[1, 1]
                hgn = -solve22(a + wp.mat22(1.0e-6 * tr + 1.0e-20, 0.0, 0.0, 1.0e-6 * tr + 1.0e-20), g)
            h = wp.vec2(0.0)
            lg = wp.sqrt(gg)
            if wp.length(hgn) <= delta:
                h = hgn
            elif alpha * lg >= delta or alpha == 0.0:
                if lg > 0.0:
                    h = -(delta / lg) * g
            else:
                sa = -alpha * g
                bma = hgn - sa
                c = dot2(sa, bma)
                b2 = dot2(bma, bma)
                disc = wp.max(c * c + b2 * (delta * delta - dot2(sa, sa)), 0.0)
                beta = float(0.0)
                if b2 > 0.0:
                    beta = (-c + wp.sqrt(disc)) / b2
                h = sa + beta * bma
            k += 1
            if wp.length(h) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            trial = evaluate(n0, t1, t2, h, images, weights, px, lights, mat)
            pred = -dot2(h, g) - 0.5 * dot2(h, a * h)
            rho = float(-1.0)
            ok = pred > 0.0
            if ok and px.visible_only != 0:
                ok = wp.dot(chart_normal(n0, t1, t2, h), px.v) > 0.0
            if ok:
                rho = (ev.cost - trial.cost) / pred
            if rho > 0.0:
                dn_old = chart_normal_jacobian(n0, t1, t2, h)
                n0 = chart_normal(n0, t1, t2, h)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                ev = transport(trial, dn_old, t1, t2)
            if rho > 0.75:
                delta = wp.max(delta, 3.0 * wp.length(h))
            elif rho < 0.25:
                delta = 0.5 * delta
        return start_result(n0, ev, k, converged)

    return run_dogleg


def bfgs_for(evaluate, module, sfx: str):
    """``run_bfgs``: quasi-Newton BFGS from one start normal.

    Args:
        evaluate: the cost evaluation (:func:`gpps.kernels.solve_cost.evaluate_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
    """

    @wp.func(name="run_bfgs" + sfx, module=module)
    def run_bfgs(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Quasi-Newton with BFGS updates (Algorithm 3, 4.4-4.8) and a backtracking Armijo line search.

        The chart is kept fixed (so the secant pairs live in one coordinate system)
        and re-centred, with B reset, only when ``|x| > 0.5``.  ``B0`` is the
        Gauss-Newton matrix ``J^T J`` (plus a tiny ridge), a standard choice for
        least squares.  B is updated only when ``Theta^T Y > sqrt(eps) |Theta| |Y|``
        (Algorithm 3).  Stops on ``|grad| <= tol_grad``, a step ``<= tol_step`` or
        ``max_iters`` line-search evaluations.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        x = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, x, images, weights, px, lights, mat)
        tr = ev.jtj[0, 0] + ev.jtj[1, 1]
        ridge = 1.0e-6 * tr + 1.0e-20
        b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad:
                converged = 1
                if prm.early_exit != 0:
                    break
            d = -solve22(b, g)
            gd = dot2(g, d)
            if gd >= 0.0:
                d = -g
                gd = -dot2(g, g)
                b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
            # keep steps in the chart's useful range (about 0.5 rad)
            ld = wp.length(d)
            if ld > 0.5:
                d = d * (0.5 / ld)
                gd = gd * (0.5 / ld)
            step = float(1.0)
            accepted = int(0)
            trial = ev
            while k < prm.max_iters:
                k += 1
                trial = evaluate(n0, t1, t2, x + step * d, images, weights, px, lights, mat)
                ok = trial.cost <= ev.cost + 1.0e-4 * step * gd
                if ok and px.visible_only != 0:
                    ok = wp.dot(chart_normal(n0, t1, t2, x + step * d), px.v) > 0.0
                if ok:
                    accepted = 1
                    break
                step = 0.5 * step
                if step * ld <= prm.tol_step:
                    break
            if accepted == 0:
                converged = 1
                break
            theta = step * d
            yv = trial.jtr - g
            x = x + theta
            ev = trial
            ty = dot2(theta, yv)
            if ty > 3.45e-4 * wp.length(theta) * wp.length(yv):  # sqrt(float32 eps)
                u = b * theta
                tu = dot2(theta, u)
                if tu > 0.0:
                    b = b + wp.outer(yv, yv) / ty - wp.outer(u, u) / tu
            if wp.length(theta) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            if wp.length(x) > 0.5:
                n0 = chart_normal(n0, t1, t2, x)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                x = wp.vec2(0.0)
                ev = evaluate(n0, t1, t2, x, images, weights, px, lights, mat)
                tr = ev.jtj[0, 0] + ev.jtj[1, 1]
                ridge = 1.0e-6 * tr + 1.0e-20
                b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
        return start_result(chart_normal(n0, t1, t2, x), ev, k, converged)

    return run_bfgs


def run_method_for(method, run_lm, run_dogleg, run_bfgs, module, sfx: str):
    """``run_method``: the chosen solver from one start normal (``method=None``: switch on ``prm.method``).

    Args:
        method: ``"lm"``, ``"dogleg"``, ``"bfgs"`` or None.
        run_lm, run_dogleg, run_bfgs: the solvers (:func:`lm_for`, :func:`dogleg_for`, :func:`bfgs_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
    """

    @wp.func(name="run_method" + sfx, module=module)
    def run_method(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        if wp.static(method == "lm"):
            return run_lm(nstart, images, weights, px, lights, mat, prm)
        elif wp.static(method == "dogleg"):
            return run_dogleg(nstart, images, weights, px, lights, mat, prm)
        elif wp.static(method == "bfgs"):
            return run_bfgs(nstart, images, weights, px, lights, mat, prm)
        else:
            # generic build: run-time switch
            if prm.method == DOGLEG:
                return run_dogleg(nstart, images, weights, px, lights, mat, prm)
            if prm.method == BFGS:
                return run_bfgs(nstart, images, weights, px, lights, mat, prm)
            return run_lm(nstart, images, weights, px, lights, mat, prm)

    return run_method


def solve_pixel_for(robust, run_method, spec_vg, diff_vg, module, sfx: str, lanes: bool = False):
    """``solve_pixel``: multi-start, then the IRLS rounds of the robust loss (``robust=None``: switch on ``prm.robust``).

    Args:
        robust: ``"none"``, ``"huber"``, ``"cauchy"`` or None.
        run_method: the solver (:func:`run_method_for`).
        spec_vg: the specular value-and-gradient (:func:`gpps.kernels.solve_cost.specular_value_grad_for`).
        diff_vg: the diffuse value-and-gradient (:func:`gpps.kernels.solve_cost.diffuse_value_grad_for`).
        module: Warp module of the function (None: this file's).
        sfx: key suffix of the function.
        lanes: the lights-parallel build (see :func:`gpps.kernels.solve_cost.evaluate_for`): the
            brightest light is found over the lanes and each lane reweights its own lights.
    """

    @wp.func(name="model_value" + sfx, module=module)
    def model_value(best: StartResult, k: int, px: Pixel, lights: LightParams, mat: MaterialParams):
        """The model's RGB value of light ``k`` at ``best``'s normal and albedo (the image model of
        :mod:`gpps.kernels.solve`)."""
        l = light_dir(lights, k, px.p)
        e = light_radiance(lights, k, px.p)
        dg = diff_vg(mat, best.n, l, px.v)
        sg = spec_vg(mat, best.n, l, px.v)
        pred = wp.vec3(0.0)
        for c in range(3):
            pred[c] = e[c] * (best.kd[c] * dg[0] + mat.ks * sg[0])
        return pred

    @wp.func(name="irls_rounds" + sfx, module=module)
    def irls_rounds(
        best_in: StartResult,
        total_in: int,
        gmax: float,
        aside: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """``prm.irls_rounds`` robust reweighting rounds (Huber / Cauchy IRLS) from ``best_in``.  An observation set
        aside (weight ``ASIDE``; ``aside`` is ``prm.shadow_relative`` times the lit level) is taken back in the
        first round whose fit does not contradict it: as a one-sided term where the fit predicts it below
        ``aside`` too, as an ordinary one where it predicts less than ``CAST_CONFLICT`` times the lit level;
        until then it stays out."""
        i = px.i
        j = px.j
        v = px.v
        best = best_in
        total = total_in
        for rnd in range(prm.irls_rounds):
            scale = prm.robust_scale * wp.max(gmax, 1.0e-12)
            k0 = int(0)
            dk = int(1)
            if wp.static(lanes):
                k0 = px.lane
                dk = px.lanes
            for k in range(k0, lights.count, dk):
                wk = weights[k, i, j]
                if wk != 0.0:
                    o = images[k, i, j]
                    pred = model_value(best, k, px, lights, mat)
                    keep_aside = int(0)
                    if wk == ASIDE:
                        if grey(pred) < aside:
                            wk = -1.0  # the fit predicts it dark too: evidence it agrees with, one-sided
                        elif grey(pred) < CAST_CONFLICT * aside / prm.shadow_relative:
                            wk = 1.0  # no contradiction: an ordinary observation again
                        else:
                            keep_aside = 1
                    r2 = float(0.0)
                    for c in range(3):
                        r = o[c] - pred[c]
                        if wk < 0.0:
                            # a dark term's residual is one-sided; a cast shadow is its outlier
                            r = wp.min(r, 0.0)
                        r2 += r * r
                    rr = wp.sqrt(r2 / 3.0) / scale
                    w = float(1.0)
                    if wp.static(robust == "huber"):
                        if rr > 1.0:
                            w = 1.0 / rr
                    elif wp.static(robust == "cauchy"):
                        w = 1.0 / (1.0 + rr * rr)
                    else:
                        # generic build: run-time switch
                        if prm.robust == ROBUST_HUBER:
                            if rr > 1.0:
                                w = 1.0 / rr
                        else:
                            w = 1.0 / (1.0 + rr * rr)
                    w = wp.max(w, 1.0e-6)
                    if wk < 0.0:
                        w = -w
                    if keep_aside != 0:
                        w = ASIDE
                    weights[k, i, j] = w
            res = run_method(best.n, images, weights, px, lights, mat, prm)
            total += res.iters
            if wp.dot(res.n, v) <= 0.0 and wp.dot(best.n, v) > 0.0:
                # the reweighted fit turned the normal away from the camera, which no visible surface
                # does (the rule the pick of starts applies): the round before stands, and the last
                break
            best = res
        out = PixelSolution()
        out.best = best
        out.total = total
        return out

    @wp.func(name="cast_shadow_start" + sfx, module=module)
    def cast_shadow_start(
        sol: PixelSolution,
        gmax: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """The start of the refit of ``SolverConfig.shadow_relative``, after the IRLS rounds' solution ``sol``.

        The fit contradicts the pixel's split into lit and dark observations when it predicts an observation
        darker than ``prm.shadow_relative`` times the lit level (:func:`grey_lit_level`) at ``CAST_CONFLICT``
        times that level or more, or one at the lit level or above at less than ``CAST_CONFLICT`` times its
        value: a cast shadow (dark at any normal) that the fit could not tell from its other explanation, a
        tilted normal (or a low albedo) under which the lit observations became the outliers.  A third kind (session
        37): the pixel has a dark observation and the fit misses its lit ones (those at or above the dark level) by more
        than the dark level, RMS over their channels: with few lights a fit can keep a cast shadow's observation dark by
        tilting the normal until the light grazes it, paying with every lit observation (a plane under a torus's shadow,
        5 lights: lit ones off by 20-30 %, the normal by 46 deg), which neither test above sees; a fit of its lit
        observations alone is the other explanation.  It counts when the fit turned the surface away from a dark
        observation's light (its n.l below ``CAST_CONFLICT`` times the lit observations' mean): a metal's dark
        observations are dark by its lobe at any n.l, and its misfit is the model's (the rough-conductor superquadric,
        no cast shadows, lost 0.5-3.9 deg without this).  When the pixel has a contradiction, every observation dark
        against the lit level is set aside (weight ``ASIDE``), the others return to their
        weights before reweighting, and the normal is solved again on the lit observations from their
        Lambertian least squares, from the fit's normal and from the view direction (the lowest cost facing the
        camera); the IRLS rounds that follow (:func:`irls_rounds`, from the returned start) take a set-aside
        observation back where the new fit does not contradict it (an attached shadow, a specular lobe's dark
        flank), so that only the observations it predicts bright (the cast shadows) stay out.

        Returns:
            ``(solution, aside)``: the refit's start and the grey value below which observations were set aside;
            ``(sol, 0)`` (``sol`` and its weights unchanged) when the fit has no contradiction, and the first fit
            with every observation kept, ``aside`` 0, when no refit faces the camera."""
        i = px.i
        j = px.j
        v = px.v
        best = sol.best
        k0 = int(0)
        dk = int(1)
        if wp.static(lanes):
            k0 = px.lane
            dk = px.lanes
        level = grey_lit_level(images, prm, i, j, lights.count, gmax)
        aside = prm.shadow_relative * level
        conflicts = float(0.0)
        darks = float(0.0)
        lit_r2 = float(0.0)  # the fit's squared misfit of the lit observations (at or above the dark level), summed
        lit_n = float(0.0)
        for k in range(k0, lights.count, dk):
            go = grey(images[k, i, j])
            if in_fit(weights[k, i, j]):
                pred = model_value(best, k, px, lights, mat)
                if go < aside:
                    darks += 1.0
                    if grey(pred) >= CAST_CONFLICT * level:
                        conflicts += 1.0  # dark, predicted lit
                else:
                    o = images[k, i, j]
                    for c in range(3):
                        dr = o[c] - pred[c]
                        lit_r2 += dr * dr
                    lit_n += 3.0
                    if go >= level and grey(pred) < CAST_CONFLICT * go:
                        conflicts += 1.0  # lit, predicted dark: the fit gave the lit observations up as outliers
        if wp.static(lanes):
            conflicts = lanes_sum(conflicts)
            darks = lanes_sum(darks)
            lit_r2 = lanes_sum(lit_r2)
            lit_n = lanes_sum(lit_n)
        if conflicts == 0.0 and darks > 0.0 and lit_n > 0.0 and lit_r2 > aside * aside * lit_n:
            # the fit misses its lit observations by more than the dark level (RMS over their channels): it may
            # have bent the normal to keep a dark observation dark, which a cast shadow is at any normal.  That
            # is its doing when the fit turned the surface away from that light: its n.l below CAST_CONFLICT
            # times the lit observations' mean n.l (a metal's dark observations are dark by its lobe instead,
            # at any n.l, and a misfit there is the model's)
            ndl_lit = float(0.0)
            n_lit = float(0.0)
            for k in range(k0, lights.count, dk):
                if in_fit(weights[k, i, j]) and grey(images[k, i, j]) >= aside:
                    ndl_lit += wp.dot(best.n, light_dir(lights, k, px.p))
                    n_lit += 1.0
            if wp.static(lanes):
                ndl_lit = lanes_sum(ndl_lit)
                n_lit = lanes_sum(n_lit)
            turned = float(0.0)
            for k in range(k0, lights.count, dk):
                if in_fit(weights[k, i, j]) and grey(images[k, i, j]) < aside:
                    if wp.dot(best.n, light_dir(lights, k, px.p)) * n_lit < CAST_CONFLICT * ndl_lit:
                        turned += 1.0
            if wp.static(lanes):
                turned = lanes_sum(turned)
            if turned > 0.0:
                conflicts = 1.0
        if conflicts == 0.0:
            return sol, 0.0
        # set aside every observation dark against the lit level; the others back to 1 (kept) or -1 (dark);
        # the lit ones' Lambertian least squares (I / E = kd l.n, grey) as a start
        t = vec19()
        for k in range(k0, lights.count, dk):
            wk = weights[k, i, j]
            if wk != 0.0:
                o = images[k, i, j]
                if grey(o) < aside:
                    weights[k, i, j] = ASIDE
                elif wk > 0.0:
                    weights[k, i, j] = 1.0
                    l = light_dir(lights, k, px.p)
                    y = grey(o) / wp.max(grey(light_radiance(lights, k, px.p)), 1.0e-30)
                    for r in range(3):
                        for c in range(3):
                            t[3 * r + c] += l[r] * l[c]
                        t[9 + r] += y * l[r]
                else:
                    weights[k, i, j] = -1.0
        if wp.static(lanes):
            t = lanes_sum19(t)
        a = wp.mat33(t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8])
        g = wp.vec3(t[9], t[10], t[11])
        fa = wp.sqrt(wp.ddot(a, a))
        total = sol.total
        # the starts: the lit observations' least squares (when their lights determine it), the fit's normal,
        # the view direction (a while loop: one call site of the solver, which a constant range would unroll)
        lsq = wp.vec3(0.0)
        if fa > 0.0 and wp.abs(wp.determinant(a)) > 1.0e-6 * fa * fa * fa:
            lsq = wp.inverse(a) * g
        s = int(0)
        if wp.length(lsq) <= 0.0:
            s = 1
        pick = StartResult()
        pick.cost = 1.0e30
        while s < 3:
            n0 = best.n
            if s == 0:
                n0 = toward_camera(wp.normalize(lsq), v)
            if s == 2:
                n0 = v
            res = run_method(n0, images, weights, px, lights, mat, prm)
            total += res.iters
            if res.cost < pick.cost and wp.dot(res.n, v) > 0.0:
                pick = res
            s += 1
        out = PixelSolution()
        out.total = total
        if pick.cost >= 1.0e30:
            # no refit faces the camera: the first fit stands, with every observation kept
            for k in range(k0, lights.count, dk):
                if weights[k, i, j] == ASIDE:
                    weights[k, i, j] = 1.0
            out.best = best
            return out, 0.0
        out.best = pick
        return out, aside

    @wp.func(name="finish_pixel" + sfx, module=module)
    def finish_pixel(
        best_in: StartResult,
        total_in: int,
        ninit: wp.vec3,
        gmax: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """After the starts (``best_in``: the best visible one, cost 1e30 if none; ``total_in`` evaluations):
        the least-squares start's run when no start ended facing the camera, then the IRLS rounds; then, with
        ``prm.shadow_relative``, the cast-shadow refit when the fit contradicts the pixel's split into lit and dark
        observations (:func:`cast_shadow_start`)."""
        v = px.v
        best = best_in
        total = total_in
        if best.cost >= 1.0e30:
            # every start ended facing away from the camera: the least-squares start's run, from that start
            # pulled toward the camera when it faces away (as start 0 is) and with the solver's steps held on
            # the visible side (Pixel.visible_only), so that this run cannot end facing away either
            pxv = px
            pxv.visible_only = 1
            best = run_method(start_normal(0, ninit, v, v, prm), images, weights, pxv, lights, mat, prm)
            total += best.iters
        out = PixelSolution()
        out.best = best
        out.total = total
        if wp.static(robust != "none"):
            # (robust "none" runs no reweighting round: irls_rounds is 0).  The rounds, then with
            # prm.shadow_relative the cast-shadow refit's rounds from its start: one call site of the rounds in
            # a loop (each call site of a solver is inlined again by NVRTC)
            aside = float(0.0)
            phases = int(1)
            if prm.shadow_relative > 0.0 and prm.irls_rounds > 0:
                phases = 2  # (a run-time trip count: Warp unrolls a constant one, which would inline twice)
            for phase in range(phases):
                out = irls_rounds(out.best, out.total, gmax, aside, images, weights, px, lights, mat, prm)
                if phase == phases - 1 or wp.dot(out.best.n, v) <= 0.0:
                    break
                out, aside = cast_shadow_start(out, gmax, images, weights, px, lights, mat, prm)
                if aside <= 0.0:
                    break
        return out

    @wp.func(name="solve_pixel" + sfx, module=module)
    def solve_pixel(
        ninit: wp.vec3,
        gmax: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Multi-start nonlinear least squares, then IRLS rounds from the best start (:func:`finish_pixel`)."""
        v = px.v
        best = StartResult()
        best.cost = 1.0e30
        best.n = ninit
        total = int(0)
        nstarts = wp.max(prm.starts, 1)
        if prm.warm_start != 0:
            nstarts = 1
        hbright = wp.vec3(0.0)
        if wp.static(lanes):
            hbright = brightest_half_vector_lanes(images, weights, px, lights)
        else:
            hbright = brightest_half_vector(images, weights, px, lights)
        for s in range(nstarts):
            res = run_method(start_normal(s, ninit, v, hbright, prm), images, weights, px, lights, mat, prm)
            total += res.iters
            if res.cost < best.cost and wp.dot(res.n, v) > 0.0:
                best = res
        return finish_pixel(best, total, ninit, gmax, images, weights, px, lights, mat, prm)

    @wp.func(name="one_start" + sfx, module=module)
    def one_start(
        s: int,
        ninit: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Start ``s`` of :func:`solve_pixel`'s multi-start alone (the starts-parallel build: one thread a
        start, the best picked afterwards in start order by the same rule, then :func:`finish_pixel`)."""
        hbright = brightest_half_vector(images, weights, px, lights)
        return run_method(start_normal(s, ninit, px.v, hbright, prm), images, weights, px, lights, mat, prm)

    @wp.func(name="held_dark_refit" + sfx, module=module)
    def held_dark_refit(
        sol: PixelSolution,
        ninit: wp.vec3,
        gmax: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """The neighbour pass's choice between an attached and a cast shadow (``held_dark_refit``).

        A pixel of the neighbour pass (fewer than 3 lit observations; albedo held at its neighbours', weak prior
        toward their extrapolated normal) keeps its unlit observations in the fit: right for an attached shadow,
        where the normal faces away from the light, wrong for a cast shadow, dark at any normal, where the term
        pulls the normal away from a light that does face it.  Dropping every unlit observation instead (the
        many-images setting ``shadow_threshold`` 0.02 with 3 images; Mitsuba development captures under 3 point
        lights, the pixel solver, session 35): rough-plastic spheres on a plane, pixels with a cast shadow 35.2 ->
        16.1 deg, pixels with attached shadows only 12.9 -> 14.2; a plastic superquadric (attached shadows only)
        3.4 -> 7.7.  So each pixel is asked which it is.

        The rule: the pixel is fitted again with its unlit observations (in the fit, at most ``prm.lit_threshold``
        of the brightest: the one-sided dark terms and the dim ordinary ones) set aside (``ASIDE``), from the prior's
        start ``ninit``, and that fit is taken when it predicts a set-aside observation brighter than the dark level
        ``HELD_DARK_CONFLICT gmax`` (a contradiction, as in ``cast_shadow_start``) and the first fit paid for its
        terms: it costs more than ``1.5 (HELD_DARK_CONFLICT gmax)^2`` above the refit (one observation off by the
        dark level in all 3 channels, the cost being ``1/2 sum w r^2``).  An attached shadow costs the first fit
        about nothing (one of the two normals the lit observations allow faces away from the light); a cast shadow
        where neither does leaves no normal that explains the lit observations with the held albedo.  Where the
        other normal does face away, the pixel's data cannot tell the two shadows apart, and the first fit stands:
        taking the refit there when the first fit's normal was the farther from the neighbours' prior (twice the
        angle) mended analytic cast shadows (gpps's bumps with exact shadows, the pixel solver on the true depth:
        31.9 -> 1.5 deg) but, through the folder flow, turned attached shadows into the wrong normal (the same
        bumps: attached pixels 1.25 -> 7.01 deg), and a metal's too (below).

        Measured (session 35, this CPU, the folder flow, 3 lights; perf/results/s35): the Mitsuba development set's
        dielectric mean 11.43 -> 8.67 deg (largest loss 0.34), diffuse 9.74 -> 6.55, metals 25.46 -> 25.50; the
        held-out captures (seeds 1000+, run for both forms; the prior's form gave 7.49, 9.47 and 18.49 there)
        dielectric 12.58 -> 8.10 (largest loss 0.21), diffuse 14.73 -> 9.53, metals 19.71 -> 19.37; the bumps
        above 1.035 -> 0.694 (cast-shadow pixels 9.70 -> 5.36, attached 1.25 unchanged).  Also requiring the
        refit to predict the observation at ``CAST_CONFLICT`` times the lit level (the robust refit's test) kept
        most cast shadows' terms (a development capture 8.4 -> 17.1 deg).  A metal breaks the premise: its dark
        observations say where the lobe is not, and the refit moves the lobe (the prior's form: development
        metals 25.46 -> 27.69).

        A refit taken leaves the unlit observations set aside in ``weights``; otherwise they are restored and the
        first fit stands (its evaluations counted with the second's).  Only without reweighting rounds
        (``prm.irls_rounds == 0``: the weights are exactly -1 or 1, restored from a bit mask, hence at most 32
        lights; with them the robust fit's own cast-shadow refit, ``SolverConfig.shadow_relative``, decides) and
        with ``prm.held_dark`` (``SolverConfig.held_dark_refit``).
        """
        if prm.irls_rounds > 0 or prm.held_dark == 0 or lights.count > 32:
            return sol
        i = px.i
        j = px.j
        dark = int(0)
        two_sided = int(0)  # (bit k: observation k was an ordinary term, weight 1, not a one-sided one)
        for k in range(lights.count):
            w = weights[k, i, j]
            if in_fit(w) and grey(images[k, i, j]) <= prm.lit_threshold * gmax:
                if w > 0.0:
                    two_sided = two_sided | (1 << k)
                weights[k, i, j] = ASIDE
                dark += 1
        if dark == 0:
            return sol
        alt = run_method(ninit, images, weights, px, lights, mat, prm)
        out = sol
        out.total = sol.total + alt.iters
        level = HELD_DARK_CONFLICT * gmax
        if wp.dot(alt.n, px.v) > 0.0:
            # a contradiction, as in cast_shadow_start: the refit predicts a set-aside observation lit
            conflict = int(0)
            for k in range(lights.count):
                if weights[k, i, j] == ASIDE:
                    if grey(model_value(alt, k, px, lights, mat)) > level:
                        conflict = 1
            # ... and the first fit paid for its terms: a misfit above the dark level
            if conflict != 0 and sol.best.cost > alt.cost + 1.5 * level * level:
                out.best = alt
                return out
        for k in range(lights.count):
            if weights[k, i, j] == ASIDE:
                if ((two_sided >> k) & 1) != 0:
                    weights[k, i, j] = 1.0
                else:
                    weights[k, i, j] = -1.0
        return out

    return solve_pixel, finish_pixel, one_start, held_dark_refit


def solver_funcs(method, brdf, robust, module=None, sfx: str = "", lanes: bool = False,
                 cache: int = names.SOLVE_TERM_CACHE):
    """Define the solver functions for one ``(method, brdf, robust)``.

    ``None`` for any of them keeps that choice a run-time switch on
    ``prm.method`` / ``mat.model`` / ``prm.robust`` (the generic build).  The
    ``wp.static`` conditions are evaluated at code generation, so only the
    chosen branches are emitted.  ``module`` / ``sfx``: Warp module and key
    suffix of the functions (distinct per specialisation).  ``lanes``: the
    lights-parallel build (one block of lanes a pixel, launched tiled; see
    :func:`gpps.kernels.solve_cost.evaluate_for`).  ``cache``: the lights whose terms the evaluation keeps
    between its passes (:func:`gpps.kernels.solve_cost.evaluate_for`; part of the specialisation).

    Returns:
        A namespace with ``evaluate``, ``run_lm``, ``run_dogleg``, ``run_bfgs``,
        ``run_method``, ``solve_pixel``, ``finish_pixel``, ``one_start`` and ``held_dark_refit``.
    """
    spec_vg = specular_value_grad_for(brdf, module, sfx)
    diff_vg = diffuse_value_grad_for(brdf, module, sfx)
    evaluate = evaluate_for(light_terms_for(spec_vg, diff_vg, module, sfx), module, sfx, lanes, cache)
    run_lm = lm_for(evaluate, module, sfx)
    run_dogleg = dogleg_for(evaluate, module, sfx)
    run_bfgs = bfgs_for(evaluate, module, sfx)
    run_method = run_method_for(method, run_lm, run_dogleg, run_bfgs, module, sfx)
    solve_pixel, finish_pixel, one_start, held_dark_refit = solve_pixel_for(robust, run_method, spec_vg, diff_vg,
                                                                            module, sfx, lanes)
    return SimpleNamespace(
        evaluate=evaluate, run_lm=run_lm, run_dogleg=run_dogleg, run_bfgs=run_bfgs, run_method=run_method,
        solve_pixel=solve_pixel, finish_pixel=finish_pixel, one_start=one_start, held_dark_refit=held_dark_refit,
    )
