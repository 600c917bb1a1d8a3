"""`gpps demo` end to end (small size): writes its outputs and beats least squares."""

import json

from gpps.cli import main


def test_demo_cli(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "64"]) == 0
    rep = json.loads((out / "report.json").read_text())
    s = rep["summary"]
    assert s["MAEN, gpps (deg)"] < 1.0 < 3 < s["MAEN, least squares (deg)"]
    assert s["depth error (of range)"] < 0.02
    assert abs(s["estimated roughness (true 0.2)"] - 0.2) < 0.02
    for f in ["normals.npy", "depth.npy", "normals.png", "albedo.png", "mesh.ply", "view.png", "capture/001.png",
              "capture/mask.png"]:
        assert (out / f).is_file(), f
    from gpps.io.outputs import OUTPUT_FILES

    for f in OUTPUT_FILES:  # the output set every command writes
        assert (out / f).is_file(), f
    assert rep["depth"]["scale"] == "metric" and "working distance" in rep["depth"]["source"]
