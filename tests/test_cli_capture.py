"""The command line on users' folders: help and defaults, --version, --quiet, progress, uncalibrated reconstruct, JPEGs without a mask."""

import io
import json
import subprocess
import sys

import numpy as np
import pytest

from gpps.cli import build_parser, main


def _subparsers():
    p = build_parser()
    sub = next(a for a in p._actions if a.__class__.__name__ == "_SubParsersAction")
    return p, sub.choices


def test_every_option_has_help_and_shows_its_default():
    import argparse

    parser, subs = _subparsers()
    assert {"render", "reconstruct", "calibrate-lights", "integrate", "stream", "demo", "single"} <= set(subs)
    for name, p in [("gpps", parser), *subs.items()]:
        text = p.format_help()
        for a in p._actions:
            if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction, argparse._VersionAction)):
                continue
            assert a.help, f"{name} {a.option_strings or a.dest}: no help text"
            if a.option_strings and a.default not in (None, False, argparse.SUPPRESS) and "default" not in a.help.lower():
                flat = " ".join(text.split())
                assert f"(default: {a.default})" in flat, f"{name} {a.option_strings}: default {a.default!r} not shown"


def test_version_and_quiet(capsys):
    from gpps import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and __version__ in capsys.readouterr().out


def test_progress_lines_off_a_terminal_and_bar_on_one():
    from gpps.cli import _progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    lines = _progress.Lines("x", io.StringIO(), interval=0.0)
    for k in range(101):
        lines(k, 100, "step")
    out = lines.stream.getvalue()
    assert "\r" not in out and 2 <= out.count("\n") <= 12 and out.rstrip().endswith("100.0%" + out.rstrip().split("100.0%")[-1])
    old = sys.stderr
    try:
        sys.stderr = Tty()
        assert isinstance(_progress.bar("y"), _progress.Bar)
        sys.stderr = io.StringIO()
        assert isinstance(_progress.bar("y"), _progress.Lines)
        _progress.configure(quiet=True)
        assert _progress.bar("y") is _progress._silent
    finally:
        _progress.configure(quiet=False)
        sys.stderr = old


def test_no_cuda_driver_warning_on_import(tmp_path):
    code = "from gpps._runtime import warp; warp()"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0 and "CUDA driver" not in p.stderr + p.stdout


def _raw_folder(tmp_path, n=8, size=48, fmt="png"):
    """A rendered capture as a user has it: images only (and K for perspective)."""
    from gpps.io import save_png
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene("bumps", size, "orthographic", albedo="texture")
    lights = default_lights("directional", n, layout="spiral", slant_deg=40)
    imgs = np.clip(render(sc, Material("lambertian"), lights, device="cpu"), 0, 1)
    raw = tmp_path / "raw"
    raw.mkdir()
    for k, im in enumerate(imgs):
        save_png(raw / f"shot_{k + 1}.{fmt}", im, bits=16)
    np.save(raw / "normal_gt.npy", sc.normals)
    return raw, sc, lights


def test_reconstruct_uncalibrated_from_a_raw_folder(tmp_path, capsys):
    raw, sc, lights = _raw_folder(tmp_path)
    out = tmp_path / "out"
    assert main(["--device", "cpu", "reconstruct", str(raw), "--out", str(out), "--json"]) == 0
    cap = capsys.readouterr()
    rep = json.loads(cap.out)  # stdout is the JSON alone; progress went to stderr
    assert "reconstruct:" in cap.err and "100.0%" in cap.err
    assert rep["method"] == "uncalibrated" and rep["input"]["mask"] == "automatic"
    assert rep["convex_concave"]["surface"] == "convex" and rep["convex_concave"]["flip"] in ("ambiguous", "resolved")
    assert rep["depth"]["scale"] == "relative" and rep["depth"]["unit"] == "pixel"
    est = np.loadtxt(out / "lights_estimated.txt")
    used = (out / "filenames_used.txt").read_text().split()
    assert used == [f"shot_{k + 1}.png" for k in range(8)]
    e = np.degrees(np.arccos(np.clip(np.sum(est * lights.directions, 1), -1, 1)))
    assert e.mean() < 6.0, e  # the method's accuracy is tested in test_uncalibrated.py; here: the CLI is the API
    from gpps.io.capture import read_capture
    from gpps.flows.uncalibrated import solve_uncalibrated

    from gpps.host.automask import lit_pixels

    cap_ = read_capture(raw)
    ev = cap_.dataset.mask & lit_pixels(cap_.dataset.images)
    assert rep["light_evidence_pixels"] == ev.sum()
    res = solve_uncalibrated(cap_.dataset.images, ev, device="cpu")
    F = np.diag([-1.0, -1.0, 1.0]) if rep["convex_concave"].get("flipped") else np.eye(3)
    assert np.allclose(est, res.light_directions @ F, atol=1e-6)
    n_cli = np.load(out / "normals.npy")
    assert np.allclose(n_cli[ev], (res.normals @ F)[ev], atol=1e-5)
    inten = np.loadtxt(out / "light_intensities_estimated.txt")
    assert inten.shape == (8, 3) and abs(inten.mean() - 1) < 1e-6
    assert rep["maen_deg"] < 5.0
    for f in ("normals.npy", "albedo.npy", "depth.exr", "mesh.obj", "mask.png"):
        assert (out / f).is_file()
    # --quiet: no progress, no summary line
    assert main(["--device", "cpu", "--quiet", "reconstruct", str(raw), "--out", str(tmp_path / "q"), "--solver", "none"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and "reconstruct:" not in cap.err


def test_reconstruct_errors_name_the_argument(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "dir: folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["reconstruct", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "expected images" in capsys.readouterr().err
    raw, _, _ = _raw_folder(tmp_path, n=4, size=24)
    assert main(["reconstruct", str(raw), "--max-size", "2", "--out", str(tmp_path / "o")]) == 2
    assert "error: --max-size: expected" in capsys.readouterr().err
    # both light files: the point lights are used, and their missing distance says so
    (tmp_path / "both").mkdir()
    _, _, lights = _raw_folder(tmp_path / "both", n=4, size=24)
    np.savetxt(tmp_path / "both" / "raw" / "light_directions.txt", lights.directions)
    np.savetxt(tmp_path / "both" / "raw" / "light_positions.txt", 10 * lights.directions)
    assert main(["reconstruct", str(tmp_path / "both" / "raw"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "expected the object's distance for point lights" in err and "remove it for directional lights" in err
    assert not (tmp_path / "o").exists()


def test_diligent_jpegs_without_mask_match_pngs_with_mask(tmp_path, data_root):
    """DiLiGenT ball on a light subset (16 of 96): sRGB JPEGs, no mask.png, no filenames.txt, against the PNGs with
    the mask (least squares, the fast path; perf/diligent_jpeg.py runs the full pipeline on all 96)."""
    import shutil

    import cv2

    from gpps.io.formats import linear_to_srgb

    src = data_root / "diligent" / "ball"
    if not src.is_dir():
        pytest.skip("DiLiGenT ball not found")
    names = (src / "filenames.txt").read_text().split()
    idx = sorted(np.random.default_rng(0).choice(96, 16, replace=False).tolist())  # spread (every 8th is one column: coplanar)
    png, jpg = tmp_path / "png", tmp_path / "jpg"
    png.mkdir()
    jpg.mkdir()
    for j, k in enumerate(idx):
        shutil.copy(src / names[k], png / names[k])
        a = cv2.imread(str(src / names[k]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535
        cv2.imwrite(str(jpg / f"{j + 1:03d}.jpg"), np.round(linear_to_srgb(a) * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    (png / "filenames.txt").write_text("\n".join(names[k] for k in idx) + "\n")
    for f in ("light_directions.txt", "light_intensities.txt"):
        rows = np.loadtxt(src / f)[idx]
        np.savetxt(png / f, rows)
        np.savetxt(jpg / f, rows)
    for f in ("K.txt", "mask.png", "normal_gt.npy"):
        shutil.copy(src / f, png / f)
    shutil.copy(src / "K.txt", jpg / "K.txt")
    outs = {}
    for tag, folder in (("png", png), ("jpg", jpg)):
        out = tmp_path / f"out_{tag}"
        assert main(["--device", "cpu", "--quiet", "reconstruct", str(folder), "--solver", "none", "--no-integrate", "--out", str(out)]) == 0
        outs[tag] = (np.load(out / "normals.npy"), cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED) > 0)
    gt = np.load(src / "normal_gt.npy")
    gm = outs["png"][1]
    am = outs["jpg"][1]
    assert (am & gm).sum() / (am | gm).sum() > 0.95  # the automatic mask is the ball

    def maen(n, m):
        c = np.clip(np.sum(n[m] * gt[m], -1), -1, 1)
        return float(np.degrees(np.arccos(c)).mean())

    both = am & gm
    assert abs(maen(outs["jpg"][0], both) - maen(outs["png"][0], both)) < 0.5


def test_folder_arguments_must_be_paths():
    """A folder argument that is not a path: a TypeError naming it (os.fspath's own message named nothing)."""
    import gpps
    from gpps.io.capture import read_capture

    with pytest.raises(TypeError, match="folder: expected a path"):
        gpps.reconstruct_folder(np.zeros(3))
    with pytest.raises(TypeError, match="folder: expected a path"):
        gpps.calibrate_lights(np.zeros(3))
    with pytest.raises(TypeError, match="dir: expected a path"):
        read_capture(3)
    with pytest.raises(FileNotFoundError, match="dir: folder not found"):
        gpps.reconstruct_folder("/nonexistent/gpps/folder")
