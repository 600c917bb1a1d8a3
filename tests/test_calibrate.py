"""Light calibration from sphere images (gpps.host.calibrate, gpps calibrate-lights) on renders with known lights."""

import json

import numpy as np
import pytest

from gpps.host.calibrate import (_disc_mask, circle_points, find_outline, fit_sphere, highlight_direction, mask_outline,
                            matte_intensities, mirror_directions, render_spheres, sphere_normals, triangulate_lights)
from gpps.camera import Orthographic, Perspective
from gpps.lights import DirectionalLights, PointLights

SIZE = 120


def _lights(n=10, max_deg=60, seed=0):
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(5, max_deg, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def _cameras():
    return {"orthographic": Orthographic(0.04), "perspective": Perspective(np.array([[240.0, 0, 61.0], [0, 240.0, 57.0], [0, 0, 1]]))}


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1), -1, 1)))


def test_mirror_reflection_reference():
    """l = 2 (n.v) n - v against a numpy check at the sphere's apex and a rim-ward point (orthographic)."""
    fit = fit_sphere(circle_points(50, 40, 20), Orthographic())
    assert fit.center_px == pytest.approx((50, 40), abs=1e-9) and fit.radius_px == pytest.approx(20, abs=1e-9)
    assert np.allclose(mirror_directions(fit, [[50, 40]]), [[0, 0, 1]])
    # at u = 50 + 20 sin(a): n = (sin a, 0, cos a), l = (sin 2a, 0, cos 2a)
    a = np.radians(20)
    assert np.allclose(mirror_directions(fit, [[50 + 20 * np.sin(a), 40]]), [[np.sin(2 * a), 0, np.cos(2 * a)]], atol=1e-12)
    n, v, hit = sphere_normals(fit, [[50, 40 - 10]])  # above the centre: y up, n_y > 0
    assert hit[0] and n[0, 1] == pytest.approx(0.5) and np.allclose(v, [[0, 0, 1]])
    with pytest.raises(ValueError, match="outside"):
        mirror_directions(fit, [[0, 0]])


@pytest.mark.parametrize("cam", ["orthographic", "perspective"])
@pytest.mark.parametrize("bits", [8, 16])
def test_found_outline_and_directions(cam, bits):
    camera = _cameras()[cam]
    L = _lights()
    centre = (0.2, 0.1, -10.0)  # a sphere of ~50 px radius (the accuracy scales with it)
    imgs = render_spheres((SIZE, SIZE), camera, [{"center": centre, "radius": 2.0, "kind": "chrome"}], DirectionalLights(L))
    q = np.round(np.clip(imgs, 0, 1) * (2**bits - 1)) / (2**bits - 1)
    pts, _ = find_outline(q)
    fit = fit_sphere(pts, camera)
    if cam == "orthographic":
        assert fit.center_px == pytest.approx((59.5 + 0.2 / 0.04, 59.5 - 0.1 / 0.04), abs=0.1)
        assert fit.radius_px == pytest.approx(2.0 / 0.04, abs=0.1)
    else:
        c = np.array(centre) / np.linalg.norm(centre)
        assert _angles(fit.direction, c) < 0.02
        assert np.degrees(fit.half_angle) == pytest.approx(np.degrees(np.arcsin(2.0 / np.linalg.norm(centre))), abs=0.02)
    region = _disc_mask(fit, (SIZE, SIZE), 1.0)
    est = np.array([highlight_direction(fit, im, region)[0] for im in q])
    e = _angles(est, L)
    assert e.max() < 0.5, e


def test_matte_intensities_and_mask_outline():
    camera = _cameras()["perspective"]
    L = _lights(8, 50, seed=1)
    E = np.random.default_rng(2).uniform(0.5, 1.5, (8, 3))
    imgs = render_spheres((SIZE, SIZE), camera, [{"center": (0.2, -0.1, -10.0), "radius": 1.8, "kind": "matte"}], DirectionalLights(L, intensities=E))
    mask = render_spheres((SIZE, SIZE), camera, [{"center": (0.2, -0.1, -10.0), "radius": 1.8, "kind": "matte", "albedo": (1, 1, 1)}],
                          DirectionalLights(np.array([[0, 0, 1.0]]), intensities=np.full((1, 3), 1e6)), supersample=1)[0, ..., 0] > 0
    fit = fit_sphere(mask_outline(mask), camera)
    est, info = matte_intensities(np.clip(imgs, 0, 1), fit, L)
    s = (est * E).sum() / (est * est).sum()
    assert np.abs(est * s - E).max() / E.min() < 0.01
    assert abs(est.mean() - 1) < 1e-9


def test_two_spheres_give_near_light_positions():
    camera = Perspective(np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]]))
    spheres = [{"center": (-1.3, 0.0, -10.0), "radius": 0.9, "kind": "chrome"}, {"center": (1.3, 0.0, -10.0), "radius": 0.9, "kind": "chrome"}]
    P = np.array([[3.0, 4.0, -2.0], [-4.0, 2.0, -1.0], [0.5, -4.0, 0.0], [-2.0, -3.0, -3.0]])
    imgs = np.clip(render_spheres((120, 160), camera, spheres, PointLights(P), source_deg=2.0), 0, 1)
    fits, cents = [], []
    for sp in spheres:
        m = render_spheres((120, 160), camera, [{**sp, "kind": "matte", "albedo": (1, 1, 1)}], DirectionalLights(np.array([[0, 0, 1.0]]), intensities=np.full((1, 3), 1e6)), supersample=1)[0, ..., 0] > 0
        f = fit_sphere(mask_outline(m), camera, radius=0.9)
        region = _disc_mask(f, (120, 160), 1.0)
        cents.append(np.array([highlight_direction(f, im, region)[1]["centroid"] for im in imgs]))
        fits.append(f)
    pos, info = triangulate_lights(fits, cents, [0.9, 0.9])
    err = np.linalg.norm(pos - P, axis=1) / np.linalg.norm(P - np.array([0, 0, -10.0]), axis=1)
    assert err.max() < 0.05, (pos, err)
    assert min(info["ray_angle_deg"]) > 5
    with pytest.raises(ValueError, match="two or more"):
        triangulate_lights(fits[:1], cents[:1], [0.9])


def test_calibrate_lights_cli_then_reconstruct(tmp_path):
    """calibrate-lights on a mirror + matte sphere capture, then reconstruct --lights on an object under the same lights."""
    from gpps.cli import main
    from gpps.io import Dataset, save_png, save_txt, write_dataset
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import render

    camera = Perspective(np.array([[240.0, 0, 79.5], [0, 240.0, 79.5], [0, 0, 1]]))
    S = 160
    L = _lights(8, 55, seed=3)
    E = np.random.default_rng(4).uniform(0.7, 1.3, (8, 3))
    lights = DirectionalLights(L, intensities=E)
    cal = tmp_path / "cal"
    cal.mkdir()
    imgs = render_spheres((S, S), camera, [{"center": (-1.3, 0.5, -10.0), "radius": 1.9, "kind": "chrome"},
                                           {"center": (1.7, -0.9, -10.0), "radius": 1.2, "kind": "matte"}], lights)
    for k, im in enumerate(imgs):
        save_png(cal / f"{k + 1:03d}.png", np.clip(im, 0, 1), bits=16)
    save_txt(cal / "K.txt", camera.K)

    def circle(c, r):  # the circle a user would measure on the silhouette (an ellipse, off the axis)
        m = render_spheres((S, S), camera, [{"center": c, "radius": r, "kind": "matte", "albedo": (1, 1, 1)}],
                           DirectionalLights(np.array([[0, 0, 1.0]]), intensities=np.full((1, 3), 1e6)), supersample=1)[0, ..., 0] > 0
        f = fit_sphere(mask_outline(m), Orthographic())
        return [str(v) for v in (*f.center_px, f.radius_px)]

    out = tmp_path / "lights"
    assert main(["--device", "cpu", "calibrate-lights", str(cal), "--chrome", *circle((-1.3, 0.5, -10.0), 1.9),
                 "--matte", *circle((1.7, -0.9, -10.0), 1.2), "--out", str(out), "--quiet"]) == 0
    est = np.loadtxt(out / "light_directions.txt")
    assert _angles(est, L).max() < 0.6  # a given circle (the off-axis ellipse approximated)
    ei = np.loadtxt(out / "light_intensities.txt")
    s = (ei * E).sum() / (ei * ei).sum()
    assert np.abs(ei * s - E).max() / E.min() < 0.02
    rep = json.loads((out / "calibration.json").read_text())
    assert rep["intensities_from"] == "matte sphere" and len(rep["spheres"]) == 1
    assert (out / "filenames.txt").read_text().split() == [f"{k + 1:03d}.png" for k in range(8)]
    # an object under the same lights: reconstruct with the calibrated files
    sc = make_scene("sphere", 48, Perspective(np.array([[96.0, 0, 23.5], [0, 96.0, 23.5], [0, 0, 1]])))
    obj = render(sc, Material("lambertian"), lights, device="cpu")
    write_dataset(tmp_path / "obj", Dataset(images=np.clip(obj, 0, 1), mask=sc.mask, light_directions=L, light_intensities=E,
                                             K=np.asarray(sc.camera.K), normal_gt=sc.normals))
    r1, r2 = tmp_path / "r_true", tmp_path / "r_cal"
    assert main(["--device", "cpu", "reconstruct", str(tmp_path / "obj"), "--solver", "none", "--method", "ppn", "--out", str(r1), "--quiet"]) == 0
    assert main(["--device", "cpu", "reconstruct", str(tmp_path / "obj"), "--lights", str(out), "--solver", "none", "--method", "ppn",
                 "--out", str(r2), "--quiet"]) == 0
    m1 = json.loads((r1 / "report.json").read_text())["maen_deg"]
    m2 = json.loads((r2 / "report.json").read_text())["maen_deg"]
    assert abs(m2 - m1) < 0.3, (m1, m2)


def test_calibrate_lights_cli_errors(tmp_path, capsys):
    from gpps.cli import main
    from gpps.io import save_png

    for k in range(3):
        save_png(tmp_path / f"{k}.png", np.zeros((20, 20)), bits=8)
    assert main(["calibrate-lights", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "outline" in capsys.readouterr().err
    assert main(["calibrate-lights", str(tmp_path), "--chrome", "10", "10", "5", "--out", str(tmp_path / "o")]) == 2
    assert "no highlight" in capsys.readouterr().err


def test_calibrate_lights_checks_its_outlines(tmp_path):
    """Circles, the card and the radii are checked by name before any sphere is fitted; one circle may be given
    as (cx, cy, r) and one radius as a number (both crashed: 'cannot unpack non-iterable int object', "'float'
    object is not iterable")."""
    import gpps
    from gpps.io import save_png

    for k in range(3):
        save_png(tmp_path / f"{k}.png", np.zeros((20, 20)), bits=8)
    cases = [(dict(chrome=(10, 10, -3)), ValueError, r"chrome: expected a radius r > 0"),
             (dict(chrome=(100, 100, 5)), ValueError, r"chrome: expected a circle on the 20 x 20 image"),
             (dict(chrome=[(10, 10, 5), (4, 5)]), ValueError, r"chrome\[1\]: expected \(cx, cy, r\)"),
             (dict(chrome=(np.nan, 1, 2)), ValueError, "chrome: expected finite numbers"),
             (dict(chrome=[]), ValueError, "chrome: expected at least one circle"),
             (dict(chrome="abc"), TypeError, "chrome: expected a circle"),
             (dict(matte=(10, 10)), ValueError, r"matte: expected \(cx, cy, r\)"),
             (dict(card=(1, 2, 3)), ValueError, r"card: expected \(x0, y0, x1, y1\)"),
             (dict(card=(50, 50, 60, 60)), ValueError, "card: expected a rectangle on the 20 x 20 image"),
             (dict(chrome=(10, 10, 5), sphere_radius="x"), TypeError, "sphere_radius: expected a radius"),
             (dict(chrome=(10, 10, 5), sphere_radius=-1.0), ValueError, "sphere_radius: expected one radius > 0")]
    for kw, err, match in cases:
        with pytest.raises(err, match=match):
            gpps.calibrate_lights(tmp_path, **kw)
    for kw in (dict(chrome=(10, 10, 5)), dict(chrome=[(10, 10, 5)], sphere_radius=0.5)):  # accepted: no highlight
        with pytest.raises(ValueError, match="no highlight on the mirror sphere"):
            gpps.calibrate_lights(tmp_path, **kw)


def test_card_intensities_formula():
    from gpps.host.calibrate import card_intensities

    L = _lights(6, 50, seed=5)
    E = np.random.default_rng(6).uniform(0.5, 1.5, (6, 3))
    nc = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    region = np.zeros((10, 12), bool)
    region[2:7, 3:9] = True
    imgs = np.zeros((6, 10, 12, 3))
    imgs[:, region] = (0.6 * E * (L @ nc)[:, None])[:, None, :]
    est, _ = card_intensities(imgs, region, L, nc)
    assert np.allclose(est, E / E.mean(), rtol=1e-12)
    with pytest.raises(ValueError, match="faces away"):
        card_intensities(imgs, region, L, (0.0, 0.0, -1.0))


def test_calibrate_lights_cli_two_spheres_positions(tmp_path):
    """Two mirror spheres in a mask with two blobs, their radius given: light_positions.txt by triangulation."""
    from gpps.cli import main
    from gpps.io import save_png, save_txt

    camera = Perspective(np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]]))
    spheres = [{"center": (-1.3, 0.0, -10.0), "radius": 0.9, "kind": "chrome"}, {"center": (1.3, 0.0, -10.0), "radius": 0.9, "kind": "chrome"}]
    P = np.array([[3.0, 4.0, -2.0], [-4.0, 2.0, -1.0], [0.5, -4.0, 0.0], [-2.0, -3.0, -3.0]])
    imgs = np.clip(render_spheres((120, 160), camera, spheres, PointLights(P), source_deg=2.0), 0, 1)
    for k, im in enumerate(imgs):
        save_png(tmp_path / f"{k}.png", im, bits=16)
    m = render_spheres((120, 160), camera, [{**s, "kind": "matte", "albedo": (1, 1, 1)} for s in spheres],
                       DirectionalLights(np.array([[0, 0, 1.0]]), intensities=np.full((1, 3), 1e6)), supersample=1)[0, ..., 0] > 0
    save_png(tmp_path / "chrome_mask.png", m.astype(np.uint8) * 255)
    save_txt(tmp_path / "K.txt", camera.K)
    out = tmp_path / "lights"
    assert main(["--device", "cpu", "--quiet", "calibrate-lights", str(tmp_path), "--sphere-radius", "0.9", "--out", str(out)]) == 0
    pos = np.loadtxt(out / "light_positions.txt")
    err = np.linalg.norm(pos - P, axis=1) / np.linalg.norm(P - np.array([0, 0, -10.0]), axis=1)
    assert err.max() < 0.05, (pos, err)
    rep = json.loads((out / "calibration.json").read_text())
    assert len(rep["spheres"]) == 2 and rep["spheres"][0]["outline"].startswith("mask")
    d = np.loadtxt(out / "light_directions.txt")
    assert d.shape == (4, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)


def test_calibrate_lights_follows_the_output_rules(tmp_path, capsys):
    """--out is checked before computing (issue 18's rules): not the input folder, not a foreign non-empty folder."""
    from gpps.cli import main
    from gpps.io import MARKER

    for k in range(3):
        (tmp_path / f"{k}.png").write_bytes(b"")
    assert main(["calibrate-lights", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "input" in capsys.readouterr().err
    foreign = tmp_path.parent / (tmp_path.name + "_foreign")
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["calibrate-lights", str(tmp_path), "--out", str(foreign)]) == 2
    assert "did not write" in capsys.readouterr().err and (foreign / "notes.txt").read_text() == "mine"
    assert not (foreign / MARKER).exists()
