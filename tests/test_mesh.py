"""Depth to mesh, mesh files, off-screen view, and the ``gpps integrate`` CLI."""

import json

import numpy as np
import pytest

from gpps.camera import Orthographic, Perspective
from gpps.io.mesh import depth_to_mesh, render_view, save_mesh


def _plane(h=12, w=10):
    depth = 5.0 + 0.01 * np.arange(w)[None, :] + np.zeros((h, 1))
    mask = np.ones((h, w), bool)
    mask[0, 0] = False
    return depth, mask


def test_mesh_vertices_faces_and_orientation():
    depth, mask = _plane()
    K = np.array([[50.0, 0, 4.5], [0, 50.0, 5.5], [0, 0, 1]])
    cam = Perspective(K)
    mesh = depth_to_mesh(depth, mask, cam)
    assert mesh.n_points == mask.sum()
    assert mesh.n_cells == 2 * 11 * 9 - 1  # one corner pixel missing removes one triangle
    pts = np.asarray(mesh.points)
    assert np.allclose(pts, cam.backproject(depth)[mask])
    nrm = np.asarray(mesh.compute_normals(cell_normals=True, point_normals=False).cell_data["Normals"])
    assert np.all(nrm[:, 2] > 0)  # faces the camera (+z)


def test_save_mesh_roundtrip(tmp_path):
    import pyvista as pv

    depth, mask = _plane()
    mesh = depth_to_mesh(depth, mask, Orthographic(0.1))
    for ext in ("ply", "obj"):
        p = save_mesh(mesh, tmp_path / f"m.{ext}")
        back = pv.read(str(p))
        assert back.n_points == mesh.n_points
    with pytest.raises(ValueError, match="path: expected"):
        save_mesh(mesh, tmp_path / "m.xyz")
    with pytest.raises(ValueError, match="depth: expected"):
        depth_to_mesh(depth[0], None)


def test_render_view_never_crashes(tmp_path):
    depth, mask = _plane(40, 40)
    out = render_view(depth, mask, Orthographic(0.1), tmp_path / "v.png", size=(96, 96))
    assert out["method"] in ("egl", "numpy-shaded")
    assert out["image"].shape == (96, 96, 3) and out["image"].dtype == np.uint8
    assert (tmp_path / "v.png").is_file()


def _sphere_normals(n=48):
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x, y = (jj - (n - 1) / 2) / (n / 2), -(ii - (n - 1) / 2) / (n / 2)
    mask = x * x + y * y < 0.8
    z = np.sqrt(np.maximum(1.2 - x * x - y * y, 1e-9))
    nrm = np.stack([x / z, y / z, np.ones_like(z)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    return nrm, mask


@pytest.mark.parametrize("fmt", ["npy", "png"])
def test_cli_integrate(tmp_path, fmt):
    import cv2

    from gpps.cli import main

    nrm, mask = _sphere_normals()
    if fmt == "npy":
        src = tmp_path / "n.npy"
        np.save(src, nrm)
    else:  # BiNI coding: (n + 1) / 2 in 16 bits, BGR as OpenCV writes
        src = tmp_path / "normal_map.png"
        cv2.imwrite(str(src), np.round((nrm + 1) / 2 * 65535).astype(np.uint16)[..., ::-1])
    cv2.imwrite(str(tmp_path / "mask.png"), mask.astype(np.uint8) * 255)
    np.savetxt(tmp_path / "K.txt", np.array([[200.0, 0, 23.5], [0, 200.0, 23.5], [0, 0, 1]]))
    out = tmp_path / "out"
    rc = main(["--device", "cpu", "integrate", str(src), "--mask", str(tmp_path / "mask.png"), "--K",
               str(tmp_path / "K.txt"), "--solver", "direct", "--reference-depth", "10", "--out", str(out)])
    assert rc == 0
    for f in ("depth.npy", "depth.tiff", "mesh.ply", "view.png", "report.json"):
        assert (out / f).is_file(), f
    rep = json.loads((out / "report.json").read_text())
    assert rep["residual"] < 1e-6 and rep["n_pixels"] == mask.sum()
    d = np.load(out / "depth.npy")
    assert abs(d[mask].mean() - 10) < 1e-3 and np.all(np.isnan(d[~mask]))  # NaN outside the mask (gpps.io.outputs)


def test_cli_bad_input(tmp_path, capsys):
    from gpps.cli import main

    np.save(tmp_path / "n.npy", np.zeros((4, 4)))
    import cv2

    cv2.imwrite(str(tmp_path / "mask.png"), np.full((4, 4), 255, np.uint8))
    rc = main(["--device", "cpu", "integrate", str(tmp_path / "n.npy"), "--mask", str(tmp_path / "mask.png"),
               "--out", str(tmp_path / "o")])
    assert rc == 2 and "normals: expected" in capsys.readouterr().err


def test_cli_integrate_errors_name_the_options(tmp_path, capsys):
    """The library's checks of gpps integrate's values come back naming the command's options."""
    import cv2
    from gpps.cli import main
    from gpps.host.scenes import make_scene

    sc = make_scene("sphere", 16, "orthographic")
    np.save(tmp_path / "n.npy", sc.normals.astype(np.float32))
    cv2.imwrite(str(tmp_path / "mask.png"), sc.mask.astype(np.uint8) * 255)
    base = ["--device", "cpu", "integrate", str(tmp_path / "n.npy"), "--mask", str(tmp_path / "mask.png"),
            "--out", str(tmp_path / "o")]
    for extra, want in ((["--k", "-1"], "--k: expected"), (["--reference-depth", "-3"], "--reference-depth: expected"),
                        (["--method", "poisson", "--tol", "2"], "--tol: expected"),
                        (["--pixel-size", "-2"], "--pixel-size: expected")):
        assert main(base + extra) == 2
        assert f"error: {want}" in capsys.readouterr().err, extra
        assert not (tmp_path / "o").exists()


def test_cli_says_a_repeated_warning_once(tmp_path, capsys, monkeypatch):
    """A GppsWarning issued many times (a stage that checks the same lights at every step) is printed once with
    its count and listed once in report.json."""
    import json
    import warnings

    import cv2

    import gpps
    from gpps.cli import main
    from gpps.host.scenes import make_scene

    sc = make_scene("sphere", 16, "orthographic")
    np.save(tmp_path / "n.npy", sc.normals.astype(np.float32))
    cv2.imwrite(str(tmp_path / "mask.png"), sc.mask.astype(np.uint8) * 255)
    real = gpps.integrate_normals

    def noisy(*a, **k):
        for _ in range(3):
            warnings.warn("lights: the same thing again", gpps.GppsWarning)
        warnings.warn("another thing", gpps.GppsWarning)
        return real(*a, **k)

    monkeypatch.setattr(gpps, "integrate_normals", noisy)
    assert main(["--device", "cpu", "integrate", str(tmp_path / "n.npy"), "--mask", str(tmp_path / "mask.png"),
                 "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert err.count("warning: lights: the same thing again (3 times)") == 1
    assert err.count("warning: another thing") == 1 and "another thing (" not in err
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["warnings"] == ["lights: the same thing again", "another thing"]
