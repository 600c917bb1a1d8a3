"""Depth-parameterised refinement: normals tied to one surface, robust loss on all images, on the device.

After RON's rounds every pixel's normal was fitted on its own.  A pixel that lost observations (cast
shadows, saturation, light bounced from another part) has too few left to fix its normal and keeps whatever
the start gave it.  :class:`DepthRefiner` fits the *depth* instead: the unknown is the integrator's ``u``
(log-depth under perspective, as the seed's perspective PS parameterises the surface; depth under the
orthographic camera), a pixel's normal is the normal of ``u``'s differences (:mod:`gpps.kernels.depth_refine`),
and the energy is the image model's robust misfit summed over every valid observation of every mask pixel (less
those the pixel solver set aside as cast shadows, weight ``gpps.names.ASIDE_WEIGHT``)::

    E(u) = sum_pixels sum_(k, c) rho(I_kc - E_kc (kd_c t_d(n(u), l_k, v) + ks t_s(n(u), l_k, v)))

with the albedo eliminated per pixel (weighted least squares) and ``rho`` Cauchy's loss of scale ``sigma``
(``2.385`` times the residuals' robust scale at the start, ``1.4826`` times their median absolute value over
the valid observations of a pixel grid: Cauchy's 95 %-efficiency constant for Gaussian residuals of that scale;
observations far beyond it, what the model cannot explain, weigh little).  The scale is that of single
observations: a per-pixel RMS would count each pixel's cast shadows into it.  A pixel without observations has no term of its own: integrability through its neighbours is
all that fixes its normal, with no smoothness weight chosen by hand.

Minimised by Levenberg-Marquardt in the integrator's machinery: each iteration takes the per-pixel
Gauss-Newton model (``H``, ``g`` in the two steps, central differences), majorises its 2 x 2 coupling by a
diagonal (so the model separates into the integrator's per-direction weighted least squares), and solves
that system with the integrator's multigrid-preconditioned CG on the device
(:meth:`gpps.pipeline.integration_rounds.DeviceSystem.step_increment`: the increment of ``u``).
The Levenberg damping ``lambda = mu * mean trace(H) / 2`` starts at ``mu = 1e-2`` (the
usual Levenberg-Marquardt start, relative to the curvature) and is divided by 3 after an accepted step
(the energy fell), multiplied by 4 after a rejected one; the refinement stops when an accepted step lowers the
energy by less than ``tol`` of it, after ``max_iterations`` accepted steps, or when the damping passes
``1e8`` times its start.  The images, observations, depth and albedo stay in device buffers (the pixel
solver's frame: :meth:`DepthRefiner.upload_from_solver`); per iteration three float64 sums come back.

Measured (the development set decides the default, DiLiGenT is the final check): the analytic Gaussian bumps with
exact cast shadows, 4 lights, MAEN 1.24 -> 0.43 deg (directional) and 1.02 -> 0.48 (point); the Mitsuba development
set (perf/results/dev_eval_cpu_refine_table.md, 40 captures) better on 28 and worse on 12, worst on reliefs of
one-pixel facets (steps) and the torus under point lights; DiLiGenT 96 images (H100) ball 1.7875 -> 1.7475, bear
4.5741 -> 4.1360.  RON runs it when asked (``RONConfig.refine``: the reasons there).  Where it loses, the energy
is to blame, not the solver: started from the true depth of the Mitsuba sphere on a plane (surface normals 0.23
deg), 8 steps lower the energy by 9 % (12 directional lights) and 18 % (12 point lights) and move the normals to 1.81
and 7.97 deg: the model's misfit (interreflections, the BRDF) has its minimum off the true surface, most under point
lights, whose shading the shape also moves through the light directions and fall-off.

Outputs: the refined depth, its normals (``DepthRefineConfig.normals``: the surface's by default, or each pixel's
Levenberg-Marquardt step toward its own data, :func:`gpps.kernels.depth_refine.refine_targets_kernel`), the
albedo and the per-pixel RMS residual.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gpps import _taichi
from gpps._check import check_choices, check_number
from gpps._runtime import warp
from gpps.kernels.depth_refine import (kept_observations_kernel, refine_eval_kernel, refine_targets_kernel,
                                       residual_sample_kernel, select_normals_kernel)
from gpps.lights import PointLights
from gpps.pipeline.integration import Integrator
from gpps.pipeline.integration_rounds import DeviceSystem
from gpps.pipeline.params import camera_params, material_params
from gpps.pipeline.stage import Stage

__all__ = ["DepthRefineConfig", "DepthRefiner", "cauchy_likelihood"]

RobustLoss = Literal["cauchy", "none"]
RefinedNormals = Literal["surface", "pixel", "test"]
EdgeRule = Literal["bilateral", "central"]

#: Cauchy's constant for 95 % efficiency under Gaussian residuals of unit scale
CAUCHY_C = 2.385
MU_START = 1e-2
MU_DOWN = 3.0
MU_UP = 4.0
MU_SPAN = 1e8
#: chi-square with 2 degrees of freedom at 1 %: the surface's normal is rejected beyond it (normals="test")
CHI2_2_99 = 9.2103
#: the most pixels whose residuals set the robust scale
SCALE_PIXELS = 1 << 14


@dataclass(frozen=True)
class DepthRefineConfig:
    """Settings of :class:`DepthRefiner`.

    Attributes:
        robust: ``"cauchy"`` (default) or ``"none"`` (least squares).
        max_iterations: the most accepted Levenberg-Marquardt steps.
        tol: stop when an accepted step lowers the energy by less than this fraction.
        sigma: Cauchy's scale (image units); None: from the start's residuals (module docstring).
        normals: the returned normals: ``"surface"`` (default), the refined surface's (the normal of ``u``'s
            differences: what the refinement estimates); ``"pixel"``, each pixel's Levenberg-Marquardt step from
            the surface toward its own data (one unverified step: with 3 lights it overfits the model's misfit;
            Mitsuba bumps, plastic, 3 directional lights: surface 2.05 deg, pixel 3.41, RON 2.51); ``"test"``,
            the start's per-pixel normal where the pixel's own data reject the surface's (a likelihood-ratio test of
            the two parameters the surface fixes: twice the robust energy difference over the squared scale of the
            residuals at the refined surface beyond chi-square(2) at 1 %, 9.21), else the surface's.  Measured
            (RON / surface / test): Mitsuba steps (12 directional lights) 8.85 / 14.38 / 11.95, bumps (3) 2.51 /
            2.06 / 2.44, sphere on a plane (12) 2.76 / 2.43 / 2.45, superquadric (3) 5.50 / 5.67 / 5.35: no rule
            wins everywhere, so the default is the surface's.
        step_tol: the relative residual to which each Levenberg-Marquardt step's system is solved by the
            integrator's CG (an inexact Newton step: the step only has to lower the energy, which the damping loop
            checks, so a forcing term of 1e-2 suffices where the integrator's own tolerance is 1e-5).  Measured on
            five 3-light Mitsuba development captures (128^2, CPU): MAEN within 0.03 deg of the 1e-5 solve, CG
            iterations 1.4-2.2x fewer (``perf/results/s18/README.md``).
        edges: a pixel's differences where both neighbours are in the mask: ``"bilateral"`` (default), BiNI's
            blend of the one-sided differences (its sharpness ``k``, the integrator's ``bilateral_k``, and ``N_z``
            factors of the start's per-pixel normals, :func:`gpps.kernels.depth_refine.one_sided`): a pixel at
            a depth edge takes its normal from its own side; ``"central"``: the central difference everywhere.
    """

    robust: RobustLoss = "cauchy"
    max_iterations: int = 8
    tol: float = 1e-3
    sigma: float | None = None
    normals: RefinedNormals = "surface"
    step_tol: float = 1e-2
    edges: EdgeRule = "bilateral"

    def __post_init__(self):
        check_choices(self)
        object.__setattr__(self, "max_iterations", check_number("max_iterations", self.max_iterations, lo=0, integer=True))
        object.__setattr__(self, "tol", check_number("tol", self.tol, lo=0.0))
        object.__setattr__(self, "step_tol", check_number("step_tol", self.step_tol, lo=0.0, hi=0.5, lo_open=True))
        if self.sigma is not None:
            object.__setattr__(self, "sigma", check_number("sigma", self.sigma, lo=0.0, lo_open=True))


def cauchy_likelihood(residuals) -> dict:
    """The Cauchy likelihood of residuals at their maximum-likelihood scale (:meth:`DepthRefiner.likelihood`).

    Args:
        residuals: (M,) residuals (signed or absolute: the density is symmetric).

    Returns:
        ``{"nll": mean of log(pi s) + log(1 + (r / s)^2), "scale": s, "observations": M}`` with ``s`` the root of
        ``mean(r^2 / (r^2 + s^2)) = 1/2`` (found by bisection in log s); ``nll`` is -inf when half or more of the
        residuals are exactly 0 (``s`` -> 0).
    """
    r = np.asarray(residuals, dtype=np.float64).ravel()
    if r.size == 0 or not np.all(np.isfinite(r)):
        raise ValueError("residuals: expected finite values, at least one")
    r2 = r * r
    top = float(np.sqrt(r2.max()))
    frac = lambda ls: float(np.mean(r2 / (r2 + math.exp(2.0 * ls)))) - 0.5  # noqa: E731 (decreasing in ls)
    if not top > 0 or frac(math.log(top) - 60.0) <= 0:  # (half or more of the residuals exactly 0)
        return {"nll": -math.inf, "scale": 0.0, "observations": int(r.size)}
    lo, hi = math.log(top) - 60.0, math.log(top)
    for _ in range(100):  # bisection in log s, to the float64 resolution of s
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if frac(mid) > 0 else (lo, mid)
    s = math.exp(0.5 * (lo + hi))
    nll = float(np.mean(np.log1p(r2 / (s * s)))) + math.log(math.pi * s)
    return {"nll": nll, "scale": s, "observations": int(r.size)}


class DepthRefiner(Stage):
    """The refinement of one pixel solver's frame (its images, observations, camera, lights and material).

    Args:
        solver: a :class:`gpps.pipeline.solver.PixelSolver` holding the frame (its ``images``, ``valid`` and,
            with :meth:`upload_from_solver`, ``albedo`` buffers are read on its device).
        integrator: the :class:`Integrator` whose fields, multigrid and CG solve the steps (plain
            multigrid config: :meth:`DeviceSystem.supports`); its mask is the refinement's.
        config: :class:`DepthRefineConfig`.
    """

    def __init__(self, solver, integrator: Integrator, config: DepthRefineConfig | None = None):
        wp = warp()
        self.config = config if config is not None else DepthRefineConfig()
        if not isinstance(self.config, DepthRefineConfig):
            raise TypeError(f"config: expected DepthRefineConfig, got {type(self.config).__name__}")
        if not isinstance(integrator, Integrator):
            raise TypeError(f"integrator: expected gpps.pipeline.integration.Integrator, got {type(integrator).__name__}")
        n, h, w = solver.shape
        if integrator.shape != (h, w):
            raise ValueError(f"integrator: expected shape ({h}, {w}), got {integrator.shape}")
        self.solver = solver
        self.device = solver.device
        self.shape = (h, w)
        self.system = DeviceSystem(integrator)
        self.integrator = integrator
        d = self.device
        self.cam = camera_params(solver.camera, (h, w))
        self.mask = self._buffer((h, w), wp.uint8, d)
        self.mask.assign(integrator.mask.astype(np.uint8))
        self.depth = self._buffer((h, w), wp.float32, d, fill=1)
        self.trial = self._buffer((h, w), wp.float32, d, fill=1)
        self.albedo = self._buffer((h, w), wp.vec3, d)
        self.albedo_new = self._buffer((h, w), wp.vec3, d)
        self.hess = self._buffer((h, w), wp.vec3, d)
        self.grad = self._buffer((h, w), wp.vec2, d)
        self.rms = self._buffer((h, w), wp.float32, d)
        self.normals = self._buffer((h, w), wp.vec3, d)
        self.nref = self._buffer((h, w), wp.vec3, d)
        self.steps = self._buffer((h, w, 2), wp.float32, d)
        self.conf = self._buffer((h, w, 2), wp.float32, d)
        self.wplus = self._buffer((h, w, 2), wp.float32, d)
        # the solver's valid observations less those its fit set aside as cast shadows (:meth:`step`)
        self.valid = self._buffer((n, h, w), wp.uint8, d)
        self.sums = wp.zeros(3, dtype=wp.float64, device=d)
        self.counts = wp.zeros(1, dtype=wp.int32, device=d)
        # the robust scale's sample: every stride-th pixel in each direction, at most SCALE_PIXELS of them
        self._stride = max(1, int(math.ceil(math.sqrt(h * w / SCALE_PIXELS))))
        self.sample = self._buffer((n, (h + self._stride - 1) // self._stride, (w + self._stride - 1) // self._stride),
                                   wp.float32, d)
        self._views = None
        self._mp = self._lp = None  # (the material and lights of the last step)
        self.last = {}

    # ------------------------------------------------------------------ protocol

    def upload(self, depth, albedo, normals=None) -> None:
        """The start: ``depth`` (H, W) inside the mask (scene units; > 0 for the perspective camera or point
        lights) and ``albedo`` (H, W, 3).  The steps move ``u`` by increments of mean 0 per connected part of
        the mask: each part keeps its mean ``u`` (mean log-depth, or mean depth), which fixes the scale.

        Args:
            depth: the surface to refine (RON's integrated depth).
            albedo: the albedo the robust weights of the first step use.
            normals: (H, W, 3) per-pixel normals whose ``N_z`` factors weigh the one-sided differences
                (``edges="bilateral"``; None: central differences).
        """
        self._check_open()
        h, w = self.shape
        self._set_depth(depth)
        alb = np.asarray(albedo, dtype=np.float32)
        if alb.shape != (h, w, 3):
            raise ValueError(f"albedo: expected shape ({h}, {w}, 3), got {alb.shape}")
        self.albedo.assign(np.nan_to_num(alb))
        if normals is None:
            self.nref.zero_()
        else:
            nrm = np.asarray(normals, dtype=np.float32)
            if nrm.shape != (h, w, 3):
                raise ValueError(f"normals: expected shape ({h}, {w}, 3), got {nrm.shape}")
            self.nref.assign(np.nan_to_num(nrm))

    def upload_from_solver(self, depth) -> None:
        """As :meth:`upload` with the solver's albedo and normals buffers (device to device)."""
        self._check_open()
        self._set_depth(depth)
        warp().copy(self.albedo, self.solver.albedo)
        warp().copy(self.nref, self.solver.normals)

    def _set_depth(self, depth) -> None:
        """Check ``depth`` (H, W) and copy it into :attr:`depth` (1 outside the mask)."""
        h, w = self.shape
        m = self.integrator.mask
        dep = np.asarray(depth, dtype=np.float32)
        if dep.shape != (h, w):
            raise ValueError(f"depth: expected shape ({h}, {w}), got {dep.shape}")
        d = dep[m]
        if not np.all(np.isfinite(d)):
            raise ValueError("depth: expected finite values inside the mask")
        if (self.solver.camera.is_perspective or isinstance(self.solver.lights, PointLights)) and np.any(d <= 0):
            raise ValueError("depth: expected values > 0 inside the mask (perspective camera or point lights)")
        self.depth.assign(np.where(m, dep, 1.0).astype(np.float32))

    def step(self, progress=None) -> None:
        """Levenberg-Marquardt on the depth (module docstring); ``progress(done, total, message)``."""
        self._check_open()
        cfg = self.config
        s = self.solver
        # the material and lights as the solver has them now (RON's final material)
        self._mp = material_params(s.material)
        self._lp = s.lp
        robust = 1 if cfg.robust == "cauchy" else 0
        # the observations: the solver's valid ones less those its last solve set aside as cast shadows (dark at
        # any normal: no evidence about the surface; the robust loss would still feel them)
        warp().launch(kept_observations_kernel, dim=tuple(s.shape), inputs=[s.valid, s.weights], outputs=[self.valid],
                      device=self.device)
        self.scale = cfg.sigma / CAUCHY_C if cfg.sigma is not None else self._scale()
        sigma = CAUCHY_C * self.scale
        self.sigma = sigma
        e0, tr, cnt = self._evaluate(self.depth, self.albedo, sigma, robust)
        if cnt == 0:
            raise ValueError("mask: expected at least one pixel to refine, got none")
        start_energy = e0
        mu = MU_START
        accepted = rejected = 0
        history = [e0]
        total = max(cfg.max_iterations, 1)
        if progress is not None:
            progress(0, total, f"depth refinement: start energy {e0:.4g}")
        while accepted < cfg.max_iterations and mu < MU_START * MU_SPAN:
            lam = mu * tr / (2.0 * max(cnt, 1.0))
            if not lam > 0:
                lam = 1e-12
            self._targets(lam)
            if not self._integrate():
                break
            e1, _, _ = self._evaluate(self.trial, self.albedo, sigma, robust)
            if e1 < e0:
                accepted += 1
                self.depth, self.trial = self.trial, self.depth
                self.albedo, self.albedo_new = self.albedo_new, self.albedo
                e_prev = e0
                e0, tr, cnt = self._evaluate(self.depth, self.albedo, sigma, robust)
                history.append(e0)
                mu /= MU_DOWN
                if progress is not None:
                    progress(accepted, total, f"depth refinement: energy {e0:.4g}")
                if e_prev - e1 < cfg.tol * e_prev:
                    break
            else:
                rejected += 1
                mu *= MU_UP
                if progress is not None:
                    progress(accepted, total, f"depth refinement: step rejected (energy {e1:.4g}), damping x{MU_UP:g}")
                # the model at the current depth again (the trial's evaluation overwrote it)
                e0, tr, cnt = self._evaluate(self.depth, self.albedo, sigma, robust)
        # the final model's normals and albedo at the accepted depth
        lam = mu * tr / (2.0 * max(cnt, 1.0))
        self._targets(lam if lam > 0 else 1e-12)
        warp().copy(self.albedo, self.albedo_new)
        kept = None
        if cfg.normals == "test":
            # the test's scale: the residuals' at the refined surface (what the surface model typically misses)
            s2 = self._scale()
            kept = self._select(CAUCHY_C * s2, s2)
        self.last = {"energy": history, "start_energy": start_energy, "accepted": accepted, "rejected": rejected,
                     "sigma": sigma, "mu": mu, "kept_pixel_normals": kept}

    def fetch(self) -> dict:
        """``depth`` (H, W) (0 outside the mask), ``normals`` (H, W, 3), ``albedo`` (H, W, 3), ``residual`` (H, W)
        (RMS residual of the used observations at the final depth) and ``info`` (energies, steps, ``sigma``)."""
        self._check_open()
        m = self.integrator.mask
        return {
            "depth": np.where(m, self.depth.numpy(), 0.0).astype(np.float32),
            "normals": np.where(m[..., None], self.normals.numpy(), 0.0).astype(np.float32),
            "albedo": np.where(m[..., None], self.albedo.numpy(), 0.0).astype(np.float32),
            "residual": np.array(self.rms.numpy(), copy=True),
            "info": dict(self.last),
        }

    def close(self) -> None:
        """Give the buffers back and the device system's fields to their pool; the refiner refuses work afterwards."""
        self._views = None
        if self.system is not None:
            self.system.close()
            self.system = None
        super().close()
        self._closed = True

    # ------------------------------------------------------------------ pieces

    def _select(self, sigma: float, scale: float) -> int:
        """``normals="test"``: the surface's normals, or the start's where the data reject the surface's; returns
        the pixels that kept the start's."""
        wp = warp()
        s = self.solver
        h, w = self.shape
        counts = self.counts
        counts.zero_()
        wp.launch(select_normals_kernel, dim=(h, w),
                  inputs=[self.depth, self.mask, *self._edges(), s.images, self.valid, self.cam, self._lp, self._mp,
                          self.albedo, float(sigma), float(scale), CHI2_2_99],
                  outputs=[self.normals, counts], device=self.device)
        return int(counts.numpy()[0])

    def _edges(self) -> tuple:
        """``(nref, k, min_nz)`` of the kernels' step rule (``k = 0``: central differences)."""
        ic = self.integrator.config
        k = float(ic.bilateral_k) if self.config.edges == "bilateral" else 0.0
        return self.nref, k, float(ic.min_nz)

    def likelihood(self) -> dict:
        """How well the current surface explains the images, comparable between surfaces of one frame.

        The refinement's Cauchy misfit is a likelihood: Cauchy-distributed residuals of scale ``s`` have the
        negative log-likelihood ``log(pi s) + log(1 + (r / s)^2)`` each.  Here ``s`` is the maximum-likelihood
        scale of the current residuals (the root of ``mean(r^2 / (r^2 + s^2)) = 1/2``), so two surfaces refined
        with different ``sigma`` (each from its own start's residuals) are compared on the same observations by
        the likelihood of each at its own best scale, not by energies of different scales.  The residuals are
        those of the robust scale's sample (:data:`SCALE_PIXELS` pixels at most, every valid observation of each,
        at the current depth and albedo: after :meth:`step`, the refined surface's).

        Returns:
            ``{"nll": mean negative log-likelihood per observation, "scale": s, "observations": count}``.
        """
        self._check_open()
        if self._mp is None:
            self._mp = material_params(self.solver.material)
            self._lp = self.solver.lp
        return cauchy_likelihood(self._residual_sample())

    def _residual_sample(self) -> np.ndarray:
        """The absolute residuals of the valid observations of a grid of at most :data:`SCALE_PIXELS` pixels at
        the current depth and albedo (one read)."""
        wp = warp()
        s = self.solver
        out = self.sample
        wp.launch(residual_sample_kernel, dim=out.shape,
                  inputs=[self.depth, self.mask, *self._edges(), s.images, self.valid, self.cam, self._lp, self._mp,
                          self.albedo, self._stride],
                  outputs=[out], device=self.device)
        r = out.numpy()
        r = r[r >= 0]
        if r.size == 0:
            raise ValueError("valid: expected observations on the mask to refine, got none")
        return r

    def _scale(self) -> float:
        """The residuals' robust scale at the start: 1.4826 times the median absolute residual (MAD about 0) of the
        valid observations of a grid of at most :data:`SCALE_PIXELS` pixels (one read of their residuals)."""
        r = self._residual_sample()
        mad = 1.4826 * float(np.median(r))
        if not mad > 0:
            mad = max(float(np.mean(r)), 1e-12)
        return mad

    def _evaluate(self, depth, albedo_prev, sigma: float, robust: int) -> tuple[float, float, float]:
        wp = warp()
        s = self.solver
        h, w = self.shape
        self.sums.zero_()
        wp.launch(refine_eval_kernel, dim=(h, w),
                  inputs=[depth, self.mask, *self._edges(), s.images, self.valid, self.cam, self._lp, self._mp,
                          albedo_prev, float(sigma), int(robust)],
                  outputs=[self.hess, self.grad, self.albedo_new, self.rms, self.sums], device=self.device)
        e, tr, cnt = (float(v) for v in self.sums.numpy())
        return e, tr, cnt

    def _targets(self, lam: float) -> None:
        wp = warp()
        h, w = self.shape
        wp.launch(refine_targets_kernel, dim=(h, w),
                  inputs=[self.depth, self.mask, *self._edges(), self.cam, self.hess, self.grad, float(lam),
                          int(self.config.normals == "pixel")],
                  outputs=[self.steps, self.conf, self.wplus, self.normals], device=self.device)

    def _view(self, a):
        if self.device.startswith("cuda"):
            return warp().to_torch(a)
        return a.numpy()

    def _integrate(self) -> bool:
        """The majorant's increment solved and :attr:`depth` moved by it into :attr:`trial`."""
        wp = warp()
        cuda = self.device.startswith("cuda")
        if cuda and importlib.util.find_spec("torch") is None:
            raise ImportError("the depth refinement on CUDA needs PyTorch for zero-copy views of the Warp buffers: "
                              "pip install 'gpps[cuda]'")
        if cuda:
            wp.synchronize_device(self.device)
        split = self._view(self.wplus) if self.config.edges == "bilateral" else None
        ok = self.system.step_increment(self._view(self.steps), self._view(self.conf), self._view(self.depth),
                                        self._view(self.trial), split, tol=self.config.step_tol)
        if cuda:
            _taichi.ti.sync()
        return ok
