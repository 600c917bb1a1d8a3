"""The uncalibrated refinement stage: gradient descent through the image model (seed 5.1-5.7).

Allocates its parameter and gradient buffers once per problem size and runs
Adam steps on the loss of :func:`gpps.kernels.uncalibrated.lambert_as_loss`,
with gradients from Warp's autodiff (``wp.Tape``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from warp.optim import Adam

from gpps._check import check_choice
from gpps._runtime import resolve_device, warp
from gpps.kernels import uncalibrated as uk
from gpps.pipeline.stage import Stage

__all__ = ["Refiner", "RefineResult", "Lobe"]

Lobe = Literal["lambertian", "ashikhmin-shirley", "blinn-phong"]
LOBE_TAG = {"lambertian": 0, "ashikhmin-shirley": 1, "blinn-phong": 2}  # gpps.kernels.uncalibrated's ``specular``


@dataclass
class RefineResult:
    normals: np.ndarray  # (P, 3) unit
    albedo: np.ndarray  # (P, 3)
    lights: np.ndarray  # (N, 3): direction * intensity
    ks: float
    eta: float
    losses: list = field(default_factory=list)


class Refiner(Stage):
    """Adam on normals, albedo, lights and (ks, eta) of the Lambertian + Ashikhmin-Shirley model.

    Args:
        n_images: N.
        n_pixels: P.
        device: Warp device.
    """

    def __init__(self, n_images: int, n_pixels: int, device=None):
        wp = warp()
        self.device = resolve_device(device)
        self.N, self.P = int(n_images), int(n_pixels)
        d = self.device
        self.images = wp.zeros((self.N, self.P), dtype=wp.vec3, device=d)
        self.weights = wp.zeros((self.N, self.P), dtype=wp.float32, device=d)
        self.views = wp.zeros(self.P, dtype=wp.vec3, device=d)
        self.normals = wp.zeros(self.P, dtype=wp.vec3, device=d, requires_grad=True)
        self.albedo = wp.zeros(self.P, dtype=wp.vec3, device=d, requires_grad=True)
        self.lights = wp.zeros(self.N, dtype=wp.vec3, device=d, requires_grad=True)
        self.spec = wp.zeros(2, dtype=wp.float32, device=d, requires_grad=True)
        self.loss = wp.zeros(1, dtype=wp.float32, device=d, requires_grad=True)
        self._last = None

    def _check(self, name, a, shape):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")

    def upload(self, images, weights, views, normals, albedo, lights, *, ks: float = 0.1, eta: float = 20.0) -> None:
        """Copy the observations and the start into the stage's buffers.

        Args:
            images: (N, P, 3) observations.
            weights: (N, P) observation weights.
            views: (P, 3) unit view vectors.
            normals, albedo: (P, 3) starts.
            lights: (N, 3) start (direction times intensity).
            ks, eta: starting specular weight and Ashikhmin-Shirley exponent.
        """
        N, P = self.N, self.P
        for name, a, s in [("images", images, (N, P, 3)), ("weights", weights, (N, P)), ("views", views, (P, 3)),
                           ("normals", normals, (P, 3)), ("albedo", albedo, (P, 3)), ("lights", lights, (N, 3))]:
            self._check(name, np.asarray(a), s)
        self.images.assign(np.asarray(images, np.float32))
        self.weights.assign(np.asarray(weights, np.float32) / max(float(np.sum(weights)), 1e-12))
        self.views.assign(np.asarray(views, np.float32))
        self.normals.assign(np.asarray(normals, np.float32))
        self.albedo.assign(np.asarray(albedo, np.float32))
        self.lights.assign(np.asarray(lights, np.float32))
        self.spec.assign(np.log(np.array([max(ks, 1e-4), max(eta, 1.0)], np.float32)))

    def step(self, *, f0: float = 0.5, specular: Lobe = "ashikhmin-shirley", fit_lights: bool = True,
             robust: float = 0.0, iterations: int = 300, lr: float = 0.01, progress=None) -> None:
        """Run ``iterations`` Adam steps from the uploaded start.

        Args:
            f0: Fresnel reflectance at normal incidence (fixed).
            specular: the specular lobe of the model: "lambertian" (none), "ashikhmin-shirley" or "blinn-phong".
            fit_lights: update the lights (else keep them fixed).
            robust: Cauchy scale of the residuals (intensity units); 0: least squares.
            iterations: Adam steps (the step size decays geometrically to lr/100).
            lr: Adam's first step size.
            progress: optional ``progress(done, total, message)``.
        """
        wp = warp()
        lobe = LOBE_TAG[check_choice("specular", specular, Lobe)]
        N, P = self.N, self.P
        params = [self.normals, self.albedo]
        if fit_lights:
            params.append(self.lights)
        if lobe:
            params.append(self.spec)
        opt = Adam(params, lr=lr)
        losses = []
        tape = wp.Tape()
        iterations = int(iterations)
        for it in range(iterations):
            # Adam's steps have the size of the step size whatever the gradient: decay it
            # geometrically to lr/100 so that the fit settles instead of hovering.
            opt.lr = lr * 0.01 ** (it / max(iterations - 1, 1))
            self.loss.zero_()
            with tape:
                wp.launch(
                    uk.lambert_as_loss,
                    dim=(N, P),
                    inputs=[self.images, self.weights, self.views, self.normals, self.albedo, self.lights, self.spec,
                            float(f0), int(lobe), float(robust)],
                    outputs=[self.loss],
                    device=self.device,
                )
            tape.backward(loss=self.loss)
            opt.step([p.grad for p in params])
            tape.zero()
            tape.reset()
            if it % 10 == 0 or it == iterations - 1:
                losses.append(float(self.loss.numpy()[0]))
                if progress is not None:
                    progress(it + 1, iterations, f"loss {losses[-1]:.3e}")
        self._last = {"losses": losses, "specular": bool(lobe)}

    def fetch(self) -> RefineResult:
        """The fitted normals (unit), albedo, lights and specular parameters of the last :meth:`step`."""
        n = self.normals.numpy().astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        ks_, eta_ = np.exp(self.spec.numpy().astype(np.float64))
        last = self._last or {"losses": [], "specular": True}
        return RefineResult(n, self.albedo.numpy().astype(np.float64), self.lights.numpy().astype(np.float64),
                            float(ks_) if last["specular"] else 0.0, float(eta_), last["losses"])

    def run(self, images, weights, views, normals, albedo, lights, *, ks: float = 0.1, eta: float = 20.0,
            progress=None, **settings) -> RefineResult:
        """:meth:`upload` (observations, start, ``ks``, ``eta``), :meth:`step` (``settings``, ``progress``)
        and :meth:`fetch` in one call."""
        self.upload(images, weights, views, normals, albedo, lights, ks=ks, eta=eta)
        self.step(progress=progress, **settings)
        return self.fetch()
