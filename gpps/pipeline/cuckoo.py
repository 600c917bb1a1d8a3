"""The cuckoo search stage (seed 6.1-6.9, Algorithm 6): buffers and launches.

:class:`CuckooSearch` runs ``P`` independent searches of ``K`` nests each (one
per pixel in the photometric refinement) for any objective of
:mod:`gpps.kernels.cuckoo` form.  Example (a test's analytic objective)::

    search = CuckooSearch(P, objective=sphere_objective, data_type=SphereData, config=CuckooConfig(seed=1))
    search.upload(nests0, data)           # (P, K, 5) starting habitats, the objective's data
    search.step(generations=500)          # progress(done, total, message) optional
    x, f = search.fetch()                 # (P, 5), (P,)

:class:`PhotometricCuckoo` is the photometric refinement of the single-image flow on top of it: the
pixels' observations, view directions and prior normals uploaded once, the lights changed between
rounds without re-uploading, the best habitat's normal and albedo reduced on the device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gpps._check import check_choices, check_number
from gpps._runtime import resolve_device, warp
from gpps.kernels import cuckoo as ck
from gpps.pipeline.stage import Stage

__all__ = ["CuckooConfig", "CuckooSearch", "PhotometricCuckoo", "mantegna_sigma_u"]

EggTarget = Literal["own", "random"]


def mantegna_sigma_u(lam: float) -> float:
    """``sigma_u`` of Mantegna's algorithm (6.7) for the Levy exponent ``lam`` (with sigma_v = 1, 6.9)."""
    lam = float(lam)
    num = math.gamma(1.0 + lam) * math.sin(math.pi * lam / 2.0)
    den = math.gamma((1.0 + lam) / 2.0) * lam * 2.0 ** ((lam - 1.0) / 2.0)
    return (num / den) ** (1.0 / lam)


@dataclass(frozen=True)
class CuckooConfig:
    """Cuckoo search settings.

    Attributes:
        nests: habitats per search (K >= 2).
        generations: generations per :meth:`CuckooSearch.run` (>= 0).
        beta: step size of the Levy flight (6.1); the seed's 6.2.5 uses 0.01.
        p_c: probability that a host finds an egg (abandonment fraction, in [0, 1]);
            the seed's 6.2.5 uses 0.4.
        levy_exponent: Mantegna's exponent lambda in (0, 2] (6.5, 6.7); 1.5 as in
            Yang & Deb.  (The seed writes beta for both the step size and this
            exponent; with an exponent of 0.01 the steps would be almost all
            zero or astronomically large, so they are two settings here.)
        seed: random seed: the same seed gives the same result on every device.
        egg_target: which nest an egg competes with: ``"own"`` (the nest that laid it, as in
            Yang & Deb's reference code) or ``"random"`` (Algorithm 6's literal "choose a habitat
            j randomly", which collapses the population early; see :mod:`gpps.kernels.cuckoo`).
    """

    nests: int = 16
    generations: int = 200
    beta: float = 0.01
    p_c: float = 0.4
    levy_exponent: float = 1.5
    seed: int = 0
    egg_target: EggTarget = "own"

    def __post_init__(self):
        check_choices(self)
        if not isinstance(self.nests, (int, np.integer)) or isinstance(self.nests, bool) or self.nests < 2:
            raise ValueError(f"nests: expected an integer >= 2, got {self.nests!r}")
        if not isinstance(self.generations, (int, np.integer)) or isinstance(self.generations, bool) or self.generations < 0:
            raise ValueError(f"generations: expected an integer >= 0, got {self.generations!r}")
        object.__setattr__(self, "beta", check_number("beta", self.beta, lo=0.0, lo_open=True))
        object.__setattr__(self, "p_c", check_number("p_c", self.p_c, lo=0.0, hi=1.0))
        object.__setattr__(self, "levy_exponent", check_number("levy_exponent", self.levy_exponent, lo=0.0, hi=2.0, lo_open=True))
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed: expected an integer in [0, 2^31), got {self.seed!r}")


class CuckooSearch(Stage):
    """``n_search`` independent cuckoo searches over 5-vectors, on one Warp device.

    Args:
        n_search: number of searches P (>= 1).
        objective: a ``@wp.func (x: vec5, p: int, data) -> float`` to minimise.
        data_type: the ``@wp.struct`` type of its ``data``.
        config: :class:`CuckooConfig`.
        lo, hi: (5,) bounds of the habitats (default +-1e30).
        device: Warp device.
    """

    def __init__(self, n_search: int, *, objective, data_type, config: CuckooConfig | None = None,
                 lo=None, hi=None, device=None):
        wp = warp()
        self.config = config or CuckooConfig()
        if not isinstance(self.config, CuckooConfig):
            raise TypeError(f"config: expected CuckooConfig, got {type(self.config).__name__}")
        n_search = int(n_search)
        if n_search < 1:
            raise ValueError(f"n_search: expected >= 1, got {n_search}")
        self.device = resolve_device(device)
        self.n_search = n_search
        self._eval, self._gen = ck.make_search_kernels(objective, data_type)
        k = self.config.nests
        d = self.device
        self.nests = wp.zeros((n_search, k), dtype=ck.vec5, device=d)
        self.fit = wp.zeros((n_search, k), dtype=wp.float32, device=d)
        self.best_index = wp.zeros(n_search, dtype=wp.int32, device=d)
        self.lo = ck.vec5(*(np.full(5, -1e30) if lo is None else np.asarray(lo, np.float64).reshape(5)))
        self.hi = ck.vec5(*(np.full(5, 1e30) if hi is None else np.asarray(hi, np.float64).reshape(5)))
        self.sigma_u = mantegna_sigma_u(self.config.levy_exponent)
        self.generation = 0
        self.data = None

    def upload(self, nests=None, data=None, *, restart: bool = True) -> None:
        """Set the habitats and/or the objective's data.

        Args:
            nests: (P, K, 5) habitats.
            data: the objective's ``data_type`` struct (kept by reference: its arrays stay on the device).
            restart: the habitats are a new start: clipped to the bounds, generation count back to 0.
                False: habitats the host moved between steps (taken as they are; the random
                sequence goes on).
        """
        if data is not None:
            self.data = data
        if nests is None:
            return
        shape = (self.n_search, self.config.nests, 5)
        a = np.asarray(nests, dtype=np.float32)
        if a.shape != shape:
            raise ValueError(f"nests: expected shape {shape}, got {a.shape}")
        if not restart:
            self.nests.assign(a)
            return
        lo = np.array(self.lo, np.float32)
        hi = np.array(self.hi, np.float32)
        self.nests.assign(np.clip(a, lo, hi))
        self.generation = 0

    def step(self, generations: int | None = None, *, progress=None) -> None:
        """Evaluate every nest, then run ``generations`` generations (default ``config.generations``; 0 only
        evaluates, after new habitats or data).

        The random stream of generation g is ``rand_init(seed, g * P + p)``, g counted from the last
        upload of habitats, so steps continue the same sequence and are reproducible.
        """
        wp = warp()
        if self.data is None:
            raise ValueError("data: expected the objective's data (upload(data=...)) before step(), got none")
        data = self.data
        g_total = self.config.generations if generations is None else int(generations)
        if g_total < 0:
            raise ValueError(f"generations: expected >= 0, got {g_total}")
        wp.launch(self._eval, dim=self.n_search, inputs=[self.nests, data], outputs=[self.fit, self.best_index],
                  device=self.device)
        c = self.config
        for g in range(g_total):
            wp.launch(
                self._gen, dim=self.n_search,
                inputs=[self.nests, self.fit, self.best_index, data, int(c.seed), int(self.generation),
                        float(c.beta), float(c.p_c), float(self.sigma_u), float(c.levy_exponent), self.lo, self.hi,
                        int(c.egg_target == "random")],
                device=self.device,
            )
            self.generation += 1
            if progress is not None and (g % 10 == 9 or g == g_total - 1):
                progress(g + 1, g_total, "cuckoo search")

    def fetch(self) -> tuple[np.ndarray, np.ndarray]:
        """The best habitat (P, 5) and its objective value (P,) of every search."""
        nests = self.nests.numpy()
        fit = self.fit.numpy()
        b = self.best_index.numpy()
        idx = np.arange(self.n_search)
        return nests[idx, b], fit[idx, b]


class PhotometricCuckoo(Stage):
    """Per-pixel cuckoo refinement of normal and albedo (seed 6.2, Algorithm 6) on the Blinn-Phong
    reprojection error plus ``prior_weight |n - n_prior|^2`` (:func:`gpps.kernels.cuckoo.photometric_error`).

    Buffers for ``n_images`` images of ``n_pixels`` pixels are allocated once; the lights, the specular
    parameters and the prior change between rounds through :meth:`upload` without re-uploading the images.

    Args:
        n_images: N images.
        n_pixels: P pixels (one search each).
        config: :class:`CuckooConfig`.
        device: Warp device.
    """

    #: habitat bounds: normal's (x, y) in the unit disc's square, RGB albedo in [0, 4]
    LO = (-1.0, -1.0, 0.0, 0.0, 0.0)
    HI = (1.0, 1.0, 4.0, 4.0, 4.0)

    def __init__(self, n_images: int, n_pixels: int, *, config: CuckooConfig | None = None, device=None):
        wp = warp()
        self.search = CuckooSearch(n_pixels, objective=ck.photometric_error, data_type=ck.PhotoData, config=config,
                                   lo=self.LO, hi=self.HI, device=device)
        self.device, self.shape = self.search.device, (int(n_images), int(n_pixels))
        n, p, d = self.shape[0], self.shape[1], self.device
        data = ck.PhotoData()
        data.images = wp.zeros((n, p), dtype=wp.vec3, device=d)
        data.view = wp.zeros(p, dtype=wp.vec3, device=d)
        data.prior = wp.zeros(p, dtype=wp.vec3, device=d)
        data.weight = wp.array(np.ones(p, np.float32), dtype=wp.float32, device=d)
        data.light_dir = wp.zeros(n, dtype=wp.vec3, device=d)
        data.light_rgb = wp.zeros(n, dtype=wp.vec3, device=d)
        data.ks, data.shininess, data.prior_weight, data.albedo_from_normal = 0.0, 1.0, 0.0, 0
        self.data = data
        self.search.upload(data=data)
        self._normals = wp.zeros(p, dtype=wp.vec3, device=d)
        self._albedo = wp.zeros(p, dtype=wp.vec3, device=d)
        self._error = wp.zeros(p, dtype=wp.float32, device=d)

    def _put(self, name: str, a, shape) -> None:
        a = np.asarray(a, np.float32)
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
        getattr(self.data, name).assign(a)

    def upload(self, images=None, view=None, prior=None, nests=None, *, light_dir=None, light_rgb=None, ks=None,
               shininess=None, prior_weight=None, albedo_from_normal=None, weight=None, restart: bool = True) -> None:
        """Copy what is given into the stage's buffers (the rest stays as it was).

        Args:
            images: (N, P, 3) RGB observations.
            view: (P, 3) unit directions toward the camera.
            prior: (P, 3) prior unit normals.
            nests: (P, K, 5) habitats (normal x, y and RGB albedo).
            restart: as :meth:`CuckooSearch.upload` (False for habitats moved between rounds).
            light_dir, light_rgb: (N, 3) unit light directions and RGB intensities.
            ks, shininess: Blinn-Phong specular weight and exponent.
            prior_weight: weight of the prior term.
            albedo_from_normal: the albedo is the least-squares one for each habitat's normal.
            weight: (P,) per-pixel weight of the reprojection error (default ones).
        """
        n, p = self.shape
        for name, a, shape in (("images", images, (n, p, 3)), ("view", view, (p, 3)), ("prior", prior, (p, 3)),
                               ("light_dir", light_dir, (n, 3)), ("light_rgb", light_rgb, (n, 3)), ("weight", weight, (p,))):
            if a is not None:
                self._put(name, a, shape)
        for name, v in (("ks", ks), ("shininess", shininess), ("prior_weight", prior_weight)):
            if v is not None:
                setattr(self.data, name, float(check_number(name, v)))
        if albedo_from_normal is not None:
            self.data.albedo_from_normal = int(bool(albedo_from_normal))
        if nests is not None:
            self.search.upload(nests, restart=restart)

    def step(self, generations: int | None = None, *, progress=None) -> None:
        """Evaluate and run ``generations`` generations (0: only evaluate), then reduce each pixel's best habitat."""
        self.search.step(generations, progress=progress)
        warp().launch(ck.best_habitat_kernel, dim=self.shape[1], inputs=[self.search.nests, self.search.best_index,
                      self.search.fit, self.data], outputs=[self._normals, self._albedo, self._error], device=self.device)

    def fetch(self) -> dict:
        """``normals`` (P, 3), ``albedo`` (P, 3) and ``error`` (P,) of the best habitats, ``fit`` (P,) the
        search's best objective values."""
        b = self.search.best_index.numpy()
        fit = self.search.fit.numpy()[np.arange(self.shape[1]), b]
        return {"normals": self._normals.numpy(), "albedo": self._albedo.numpy(), "error": self._error.numpy(), "fit": fit}

    def fetch_nests(self) -> np.ndarray:
        """The current habitats (P, K, 5), for moves the host makes between rounds (a bas-relief)."""
        return self.search.nests.numpy()
