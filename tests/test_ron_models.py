"""RON's choice of reflectance model by residual (``RONConfig.models``, ``gpps.reconstruct(material=(...))``, issue
25): the first material fit runs for each model on the same sample pixels and the lowest sampled energy wins
(where it is lower beyond the sample's noise: tests/test_model_evidence.py).
Scenes rendered by gpps with one model each (the image model is exact, so the rendered model must win and its
parameters come back); configuration errors name the argument."""

import numpy as np
import pytest

import gpps
from conftest import RENDER_DEVICE
from gpps.flows.ron import RON, RONConfig
from gpps.flows.synthetic import default_lights, render
from gpps.host.metrics import normal_errors
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights
from gpps.material import Material

PLASTIC = Material.from_ior("plastic", 1.5, ks=1.2, roughness=0.15)
COOK = Material("cook-torrance", ks=0.6, roughness=0.25, f0=0.5)
_CASES: dict = {}


def _case(material):
    if material.brdf not in _CASES:
        sc = make_scene("sphere", 48, "perspective")
        L = default_lights("directional", 8, layout="spiral")
        img = render(sc, material, L, bits=16, noise=0.0, seed=1) / np.asarray(L.intensities, np.float32)[:, None, None, :]
        _CASES[material.brdf] = (img, DirectionalLights(L.directions), sc, float(0.999 / np.min(L.intensities)))
    return _CASES[material.brdf]


@pytest.mark.parametrize("true,first", [(PLASTIC, "cook-torrance"), (COOK, "plastic")])
def test_the_rendered_model_wins(device, true, first):
    """Whichever model is named first, the one the scene was rendered with has the lower sampled energy (by more
    than 2x: measured) and is kept; its parameters come back (within 10 %) and its normals are close."""
    img, L, sc, sat = _case(true)
    other = "plastic" if first == "cook-torrance" else "cook-torrance"
    rec = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=(first, other), saturation=sat,
                           reference_depth=float(sc.depth[sc.mask].mean()), device=device)
    fit = rec.details.material_fit[0]
    e = fit["models"]
    print(f"\nrendered {true.brdf}: energies {e}, estimated {rec.estimated}")
    assert set(e) == {"cook-torrance", "plastic"}
    assert e[true.brdf] < 0.5 * e[other if true.brdf == first else first]
    assert rec.material.brdf == true.brdf and set(rec.estimated) == {"ks", "roughness"}
    assert rec.fixed == {"f0": pytest.approx(true.f0)}
    for k in ("ks", "roughness"):
        assert rec.estimated[k] == pytest.approx(getattr(true, k), rel=0.1), (k, rec.estimated)
    assert normal_errors(rec.normals, sc.normals, sc.mask)["mean"] <= 1.0


def test_one_model_is_unchanged(device):
    """``models=()`` (the default): one fit, no ``models`` entry; a tuple of one name is the same run."""
    img, L, sc, sat = _case(PLASTIC)
    ref = float(sc.depth[sc.mask].mean())
    a = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material="plastic", saturation=sat, reference_depth=ref,
                         device=device)
    b = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("plastic",), saturation=sat,
                         reference_depth=ref, device=device)
    assert "models" not in a.details.material_fit[0] and "models" not in b.details.material_fit[0]
    np.testing.assert_array_equal(a.normals, b.normals)
    assert a.estimated == b.estimated


def test_models_config_errors():
    with pytest.raises(ValueError, match="models"):
        RONConfig(models=("plastik",))
    with pytest.raises(TypeError, match="models"):
        RONConfig(models="plastic")
    assert RONConfig(models=["plastic"]).models == ("plastic",)
    img, L, sc, _ = _case(PLASTIC)
    # comparing models needs every lobe parameter of the material estimated, by the photometric rule
    with pytest.raises(ValueError, match="models"):
        RON(img.shape[:3], sc.camera, L, PLASTIC, sc.mask, RONConfig(models=("cook-torrance",), estimate=("ks",)),
            device="cpu")
    with pytest.raises(TypeError, match="material"):
        gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=(), device="cpu")
    with pytest.raises(ValueError, match="material"):
        gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("plastic", "wood"), device="cpu")
    with pytest.raises(ValueError, match="estimate"):
        gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("plastic", "cook-torrance"), estimate=("ks",),
                         device="cpu")


def test_folder_and_cli_pass_the_models(tmp_path, monkeypatch, capsys, device):
    """``FolderConfig(models=...)`` / ``gpps reconstruct --compare-models`` reach RON when every lobe parameter
    is estimated; with a known parameter they are left out and the report says so; a bad name names the option;
    ``FolderConfig(cast_shadows=...)`` reaches RON too."""
    import gpps.flows.folder as folder
    from gpps.cli import main
    from gpps.flows.reconstruction import ResidentFrame
    from gpps.io import write_dataset

    sc = make_scene("sphere", 24, "orthographic")
    ds = gpps.render_dataset(sc, COOK, default_lights("directional", 6), bits=16, seed=0, device=RENDER_DEVICE)
    cap = write_dataset(tmp_path / "cap", ds)
    seen = []
    real = folder.reconstruct
    real_init = ResidentFrame.__init__

    def spy(*a, config=None, **k):
        seen.append(config.models)
        shadows.append(config.cast_shadows)
        return real(*a, config=config, **k)

    def spy_init(self, *a, config=None, **k):  # the folder flow's first reconstruction keeps its frame resident
        seen.append(config.models)
        shadows.append(config.cast_shadows)
        return real_init(self, *a, config=config, **k)

    shadows = []

    monkeypatch.setattr(folder, "reconstruct", spy)
    monkeypatch.setattr(ResidentFrame, "__init__", spy_init)
    cfg = gpps.FolderConfig(brdf="cook-torrance", rounds=2, models=("plastic",), integrate=False)
    res = gpps.reconstruct_folder(cap, cfg, device=device)
    assert seen[-1] == ("plastic",) and set(res.report["timings"]) >= {"material"}
    e = res.report["model_energies"]
    assert set(e) == {"cook-torrance", "plastic"} and res.report["material"]["brdf"] == min(e, key=e.get)
    res = gpps.reconstruct_folder(cap, gpps.FolderConfig(brdf="cook-torrance", rounds=2, models=("plastic",),
                                                         integrate=False, ks=0.6), device=device)
    assert seen[-1] == () and "models" in res.report["models_ignored"]
    gpps.reconstruct_folder(cap, gpps.FolderConfig(brdf="cook-torrance", rounds=2, integrate=False, known_material=True,
                                                   cast_shadows=True), device=device)
    assert shadows == [False, False, True]  # (FolderConfig.cast_shadows reaches RON; off by default)
    with pytest.raises(ValueError, match="models"):
        gpps.FolderConfig(models=("wood",))
    # the given material parameters' ranges are the material's, checked when the config is made (not after the
    # images are read); eta is the config's name for Material's eta_u and eta_v
    for kw, match in ((dict(ks=-1), "ks: expected >= 0"), (dict(shininess=0), "shininess: expected > 0"),
                      (dict(f0=2), "f0: expected <= 1"), (dict(brdf="ashikhmin-shirley", eta=-1), "eta: expected > 0")):
        with pytest.raises(ValueError, match=match):
            gpps.FolderConfig(**kw)
    with pytest.raises(TypeError, match="integrate: expected True or False"):
        gpps.SingleConfig(integrate=0)
    assert main(["reconstruct", str(cap), "--compare-models", "wood", "--out", str(tmp_path / "o")]) == 2
    assert "--compare-models: expected one of" in capsys.readouterr().err
