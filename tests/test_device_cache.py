"""perf/device_cache.py: the modules it would compile for the GPU machine (listing only: NVRTC is not needed)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("device_cache", ROOT / "perf" / "device_cache.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["device_cache"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_lists_kernel_modules_and_solver_specialisations(tmp_path, capsys):
    tool = _tool()
    names = [m.name for m in tool.gpps_modules(["lm"], ["cook-torrance"], ["none"])]
    for want in ("gpps.kernels.dgmc", "gpps.kernels.front", "gpps.kernels.material_search",
                 "gpps.kernels.solve.none_lambertian_none", "gpps.kernels.solve.lm_cook_torrance_none",
                 "gpps.kernels.solve.lm_cook_torrance_none_split",
                 "gpps.kernels.solve.lm_cook_torrance_none_split_under",
                 "gpps.kernels.solve_batched.lm_cook_torrance_none_starts"):
        assert want in names, want
    assert all(n.startswith("gpps.") for n in names)
    # a module directory in OUT counts as compiled only with a cubin of the architecture asked for
    ident = next(m for m in tool.gpps_modules(["lm"], ["cook-torrance"], ["none"]) if m.name == "gpps.kernels.dgmc")
    ident = ident.get_module_identifier(block_dim=ident.options["block_dim"])
    import warp as wp

    d = tmp_path / wp.config.version / ident
    d.mkdir(parents=True)
    (d / f"{ident}.sm90.cubin").write_bytes(b"x")
    assert tool.main(["--out", str(tmp_path), "--brdfs", "cook-torrance", "--robust", "none", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f"have  {ident}" in lines
    assert any(ln.startswith("need  wp_gpps.kernels.front_") for ln in lines)
