"""`gpps demo` end to end (small size): writes its outputs and beats least squares."""

import json

from gpps.cli import main


def test_demo_cli(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "64"]) == 0
    rep = json.loads((out / "report.json").read_text())
    s = rep["summary"]
    assert s["MAEN, gpps LM (deg)"] < 0.5 < 3 < s["MAEN, least squares (deg)"]
    assert s["depth error (of range)"] < 0.02
    for f in ["normals.npy", "depth.npy", "normals.png", "albedo.png", "capture/001.png", "capture/mask.png"]:
        assert (out / f).is_file(), f
