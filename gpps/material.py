"""Material (reflectance model and its per-scene parameters)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from gpps._check import check_choice, check_choices, check_number
from gpps.names import BRDF, BRDF_NAMES
from gpps.names import BRDF_TAG as _DEVICE_TAG

__all__ = ["Material", "BRDF", "BRDF_NAMES"]


@dataclass(frozen=True)
class Material:
    """Reflectance model with per-scene parameters (the albedo kd is a per-pixel map).

    Attributes:
        brdf: the model: Lambertian (2.13), Phong (2.20), Blinn-Phong (2.21),
            Cook-Torrance (2.22-2.29) or Ashikhmin-Shirley (5.1-5.2).
        ks: specular weight (>= 0), scalar: highlights take the light's colour.
        shininess: Phong / Blinn-Phong exponent n (> 0).
        roughness: Cook-Torrance RMS microfacet slope m (> 0).
        f0: Fresnel reflectance at normal incidence (Schlick, 2.29), in [0, 1].
        eta_u: Ashikhmin-Shirley exponent along the tangent u (> 0; the seed uses 10).
        eta_v: Ashikhmin-Shirley exponent along the tangent v (> 0).
    """

    brdf: BRDF = "blinn-phong"
    ks: float = 0.5
    shininess: float = 30.0
    roughness: float = 0.3
    f0: float = 0.5
    eta_u: float = 10.0
    eta_v: float = 10.0

    def __post_init__(self):
        check_choices(self)
        object.__setattr__(self, "ks", check_number("ks", self.ks, lo=0.0))
        object.__setattr__(self, "shininess", check_number("shininess", self.shininess, lo=0.0, lo_open=True))
        object.__setattr__(self, "roughness", check_number("roughness", self.roughness, lo=0.0, lo_open=True))
        object.__setattr__(self, "f0", check_number("f0", self.f0, lo=0.0, hi=1.0))
        object.__setattr__(self, "eta_u", check_number("eta_u", self.eta_u, lo=0.0, lo_open=True))
        object.__setattr__(self, "eta_v", check_number("eta_v", self.eta_v, lo=0.0, lo_open=True))

    @property
    def device_tag(self) -> int:
        return _DEVICE_TAG[self.brdf]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Material":
        if not isinstance(d, dict):
            raise TypeError(f"material: expected a dict, got {type(d).__name__}")
        known = {k: d[k] for k in ("brdf", "ks", "shininess", "roughness", "f0", "eta_u", "eta_v") if k in d}
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
        }[brdf]
