"""The uncalibrated refinement stage: gradient descent through the image model (seed 5.1-5.7).

Allocates its parameter and gradient buffers once per problem size and runs
Adam steps on the loss of :func:`gpps.kernels.uncalibrated.lambert_as_loss`,
with gradients from Warp's autodiff (``wp.Tape``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpps._runtime import resolve_device, warp


@dataclass
class RefineResult:
    normals: np.ndarray  # (P, 3) unit
    albedo: np.ndarray  # (P, 3)
    lights: np.ndarray  # (N, 3): direction * intensity
    ks: float
    eta: float
    losses: list = field(default_factory=list)


class Refiner:
    """Adam on normals, albedo, lights and (ks, eta) of the Lambertian + Ashikhmin-Shirley model.

    Args:
        n_images: N.
        n_pixels: P.
        device: Warp device.
    """

    def __init__(self, n_images: int, n_pixels: int, device=None):
        wp = warp()
        from gpps.kernels import uncalibrated as uk

        self._k = uk
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

    def _check(self, name, a, shape):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")

    def run(
        self,
        images,
        weights,
        views,
        normals,
        albedo,
        lights,
        *,
        ks: float = 0.1,
        eta: float = 20.0,
        f0: float = 0.5,
        specular: int = 1,
        fit_lights: bool = True,
        robust: float = 0.0,
        iterations: int = 300,
        lr: float = 0.01,
        progress=None,
    ) -> RefineResult:
        """Run ``iterations`` Adam steps from the given start.

        Args:
            images: (N, P, 3) observations.
            weights: (N, P) observation weights.
            views: (P, 3) unit view vectors.
            normals, albedo: (P, 3) starts.
            lights: (N, 3) start (direction times intensity).
            ks, eta: starting specular weight and Ashikhmin-Shirley exponent.
            f0: Fresnel reflectance at normal incidence (fixed).
            specular: specular lobe: 0 none (Lambertian), 1 Ashikhmin-Shirley, 2 Blinn-Phong.
            fit_lights: update the lights (else keep them fixed).
            robust: Cauchy scale of the residuals (intensity units); 0: least squares.
        """
        wp = warp()
        from warp.optim import Adam

        N, P = self.N, self.P
        for name, a, s in [("images", images, (N, P, 3)), ("weights", weights, (N, P)), ("views", views, (P, 3)), ("normals", normals, (P, 3)), ("albedo", albedo, (P, 3)), ("lights", lights, (N, 3))]:
            self._check(name, np.asarray(a), s)
        self.images.assign(np.asarray(images, np.float32))
        self.weights.assign(np.asarray(weights, np.float32) / max(float(np.sum(weights)), 1e-12))
        self.views.assign(np.asarray(views, np.float32))
        self.normals.assign(np.asarray(normals, np.float32))
        self.albedo.assign(np.asarray(albedo, np.float32))
        self.lights.assign(np.asarray(lights, np.float32))
        self.spec.assign(np.log(np.array([max(ks, 1e-4), max(eta, 1.0)], np.float32)))
        params = [self.normals, self.albedo]
        if fit_lights:
            params.append(self.lights)
        if specular:
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
                    self._k.lambert_as_loss,
                    dim=(N, P),
                    inputs=[self.images, self.weights, self.views, self.normals, self.albedo, self.lights, self.spec, float(f0), int(specular), float(robust)],
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
        n = self.normals.numpy().astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        ks_, eta_ = np.exp(self.spec.numpy().astype(np.float64))
        return RefineResult(n, self.albedo.numpy().astype(np.float64), self.lights.numpy().astype(np.float64), float(ks_) if specular else 0.0, float(eta_), losses)
