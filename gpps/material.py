"""Material (reflectance model and its per-scene parameters)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from gpps._check import check_choice, check_choices, check_number, warn
from gpps.names import BRDF, BRDF_NAMES, CONDUCTOR_MIN_IMAGES, DEFAULT_F0
from gpps.names import BRDF_TAG as _DEVICE_TAG

__all__ = ["Material", "BRDF", "BRDF_NAMES", "check_model_images"]


@dataclass(frozen=True)
class Material:
    """Reflectance model with per-scene parameters (the albedo kd is a per-pixel map).

    Attributes:
        brdf: the model: Lambertian (2.13), Phong (2.20), Blinn-Phong (2.21),
            Cook-Torrance (2.22-2.29), Ashikhmin-Shirley (5.1-5.2) or plastic (a
            dielectric coating over a diffuse base, :mod:`gpps.kernels.brdf`: Cook-Torrance's
            microfacet lobe with the exact dielectric Fresnel, and a diffuse term that loses
            what the coating reflects) or conductor (a rough metal: a GGX microfacet lobe, no
            diffuse term; the per-pixel albedo is the metal's colour at normal incidence and weighs
            the lobe, :mod:`gpps.kernels.brdf`).
        ks: specular weight (>= 0), scalar: highlights take the light's colour.  The conductor
            does not use it (its albedo map weighs its lobe).
        shininess: Phong / Blinn-Phong exponent n (> 0).
        roughness: Cook-Torrance and plastic RMS microfacet slope m (> 0); the conductor's GGX alpha.
        f0: Fresnel reflectance at normal incidence, in [0, 1]: Schlick's (2.29) for
            Cook-Torrance and Ashikhmin-Shirley; for plastic it fixes the coating's index of
            refraction ``ior = (1 + sqrt(f0)) / (1 - sqrt(f0))`` and must be < 1; for the conductor
            it shapes Schlick's rise toward grazing incidence relative to normal incidence and must
            be > 0.  None (default): :data:`gpps.names.DEFAULT_F0` of the model (0.5; plastic 0.04,
            i.e. ior 1.5; conductor 1, no rise).
            :meth:`from_ior` sets it from an index of refraction.
        eta_u: Ashikhmin-Shirley exponent along the tangent u (> 0; the seed uses 10).
        eta_v: Ashikhmin-Shirley exponent along the tangent v (> 0).
    """

    brdf: BRDF = "blinn-phong"
    ks: float = 0.5
    shininess: float = 30.0
    roughness: float = 0.3
    f0: float | None = None
    eta_u: float = 10.0
    eta_v: float = 10.0

    def __post_init__(self):
        check_choices(self)
        object.__setattr__(self, "ks", check_number("ks", self.ks, lo=0.0))
        object.__setattr__(self, "shininess", check_number("shininess", self.shininess, lo=0.0, lo_open=True))
        object.__setattr__(self, "roughness", check_number("roughness", self.roughness, lo=0.0, lo_open=True))
        f0 = DEFAULT_F0[self.brdf] if self.f0 is None else self.f0
        object.__setattr__(self, "f0", check_number("f0", f0, lo=0.0, hi=1.0))
        if self.brdf == "plastic" and self.f0 >= 1.0:
            raise ValueError(f"f0: plastic needs f0 < 1 (a finite index of refraction), got {f0!r}")
        if self.brdf == "conductor" and self.f0 <= 0.0:
            raise ValueError(f"f0: the conductor needs f0 in (0, 1] (its Fresnel is relative to f0), got {f0!r}")
        object.__setattr__(self, "eta_u", check_number("eta_u", self.eta_u, lo=0.0, lo_open=True))
        object.__setattr__(self, "eta_v", check_number("eta_v", self.eta_v, lo=0.0, lo_open=True))

    @property
    def device_tag(self) -> int:
        return _DEVICE_TAG[self.brdf]

    @property
    def ior(self) -> float:
        """Index of refraction with this ``f0`` at normal incidence: ``(1 + sqrt(f0)) / (1 - sqrt(f0))`` (inf at f0 = 1)."""
        r = math.sqrt(self.f0)
        return math.inf if r >= 1.0 else (1.0 + r) / (1.0 - r)

    @staticmethod
    def f0_from_ior(ior: float) -> float:
        """Normal-incidence reflectance ``((ior - 1) / (ior + 1))^2`` of a dielectric of index ``ior`` >= 1 (air outside)."""
        ior = check_number("ior", ior, lo=1.0)
        return ((ior - 1.0) / (ior + 1.0)) ** 2

    @classmethod
    def from_ior(cls, brdf: str, ior: float, **params) -> "Material":
        """``Material(brdf, f0=f0_from_ior(ior), **params)``, e.g. ``Material.from_ior("plastic", 1.49, roughness=0.2)``.

        Raises:
            ValueError: ``ior`` not a finite number >= 1, or ``f0`` also given.
        """
        if "f0" in params:
            raise ValueError("f0: give either ior or f0, not both")
        return cls(brdf, f0=cls.f0_from_ior(ior), **params)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Material":
        if not isinstance(d, dict):
            raise TypeError(f"material: expected a dict, got {type(d).__name__}")
        names = ("brdf", "ks", "shininess", "roughness", "f0", "eta_u", "eta_v")
        known = {k: d[k] for k in names if k in d}
        unknown = sorted(str(k) for k in d if k not in names and k != "ior")
        if unknown:  # (a misspelt parameter would otherwise be its model's default without a word)
            warn(f"material: ignored {unknown}: not material parameters (expected some of {list(names)} or 'ior')")
        if d.get("ior") is not None:  # an index of refraction instead of f0 (e.g. a hand-written material.json)
            f0 = cls.f0_from_ior(d["ior"])
            if known.get("f0") is not None and not math.isclose(float(known["f0"]), f0, rel_tol=1e-6, abs_tol=1e-9):
                raise ValueError(f"material: f0 {known['f0']!r} and ior {d['ior']!r} disagree (ior {d['ior']!r} is f0 {f0:.6g})")
            known["f0"] = f0
        return cls(**known)

    @classmethod
    def default_for(cls, brdf: str) -> "Material":
        """Parameters that give visible, in-range highlights for each model."""
        check_choice("brdf", brdf, BRDF)
        return {
            "lambertian": cls("lambertian", ks=0.0),
            "phong": cls("phong", ks=0.5, shininess=30.0),
            "blinn-phong": cls("blinn-phong", ks=0.5, shininess=40.0),
            "cook-torrance": cls("cook-torrance", ks=0.6, roughness=0.25, f0=0.5),
            "ashikhmin-shirley": cls("ashikhmin-shirley", ks=0.8, eta_u=30.0, eta_v=30.0, f0=0.5),
            # ks 1 is the physical coating (gpps.kernels.brdf.plastic_spec), ior 1.5 (f0 0.04)
            "plastic": cls("plastic", ks=1.0, roughness=0.2),
            # the lobe peaks at 1 / (4 alpha^2) at normal incidence: 1 at alpha 0.5, in range for an albedo below 1
            "conductor": cls("conductor", ks=0.0, roughness=0.5),
        }[brdf]


def check_model_images(brdfs, n_images: int, sink: list | None = None) -> None:
    """Warn (:class:`gpps.GppsWarning`, the message appended to ``sink``) when a model asked for cannot determine
    the normals from ``n_images`` images: the conductor below :data:`gpps.names.CONDUCTOR_MIN_IMAGES`.

    Args:
        brdfs: the model names in play (the material's, and any compared with it).
        n_images: the number of images N.
        sink: list that collects the warning message.
    """
    if "conductor" in brdfs and n_images < CONDUCTOR_MIN_IMAGES:
        msg = (f"material: the conductor (a metal, no diffuse term) does not determine the normals from {n_images} "
               f"images: a pixel's normal and colour are seen only through its lobe, which most lights miss; use "
               f"{CONDUCTOR_MIN_IMAGES} or more images")
        warn(msg, sink)
