"""``gpps integrate``: integrate a normal map into depth, a mesh and a view.

Default: bilateral normal integration (BiNI), which keeps depth discontinuities
(occluding rims, overlapping objects); ``--method poisson`` (or any of
``--solver``, ``--tol``, ``--robust``) is the plain least-squares solve.

Writes the output set of :mod:`gpps.io.outputs` (``depth.npy``, ``depth.tiff``,
``depth.exr``, ``mesh.ply``, ``mesh.obj``, ``view.png``, ``normals.npy``,
``normals.png``, ``mask.png``) and ``report.json`` (timings, iterations,
residual, the depth convention) into ``--out``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import gpps
from gpps import Orthographic, Perspective
from gpps.cli._output import add_output_args, as_options, prepare_out, warning_messages
from gpps.cli._progress import bar
from gpps.io import (apply_depth_convention, atomic_dir, depth_convention, read_image, read_K, read_mask, read_npy,
                     save_json, write_outputs)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "integrate",
        help="normal map (.npy or BiNI-coded .png) to depth, mesh and view",
        description=__doc__.splitlines()[0],
    )
    p.add_argument("normals", help="NORMALS.npy (H, W, 3, gpps frame) or normal_map.png ((n+1)/2, 8/16 bit)")
    p.add_argument("--mask", required=True, help="mask image (non-zero = integrate)")
    p.add_argument("--K", dest="K", default=None, help="3x3 intrinsics text file: perspective camera")
    p.add_argument("--pixel-size", type=float, default=1.0, help="orthographic pixel size (scene units; default 1)")
    p.add_argument("--method", choices=["bini", "poisson"], default=None,
                   help="'bini' (default): bilateral normal integration (Cao et al. 2022), discontinuity-preserving, "
                        "BiNI's parameters (k=2, energy tolerance 1e-4, inner CG tolerance 1e-3): the mode for "
                        "measured normal maps; 'poisson': one least-squares solve, for smooth surfaces (implied by "
                        "--solver, --tol or --robust)")
    p.add_argument("--k", type=float, default=2.0, help="BiNI's sigmoid sharpness (default 2, the paper's)")
    p.add_argument("--bilateral", action="store_true", help="the same as --method bini")
    p.add_argument("--solver", choices=["multigrid", "jacobi", "direct"], default=None,
                   help="Poisson solver (default multigrid)")
    p.add_argument("--tol", type=float, default=None, help="Poisson: relative residual to reach (default 1e-5)")
    p.add_argument("--robust", nargs="?", const="curl", default=None, choices=["none", "curl", "cauchy"],
                   help="Poisson: down-weight wrong normals: 'curl' (bare --robust; edges weighted by the "
                        "integrability of their loops) or 'cauchy' (IRLS on the edge residuals)")
    p.add_argument("--reference-depth", type=float, default=None, help="mean depth per component (scene units): a metric depth; "
                                                                      "default: relative (perspective: mean 1; orthographic: pixels, mean 0)")
    add_output_args(p, "output folder (the output set of gpps.io.outputs and report.json)")
    p.set_defaults(func=run)


def _read_normals(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"normals: file not found: {path}")
    if path.suffix.lower() == ".npy":
        n = read_npy(path, name="normals")
    else:
        img = read_image(path, dtype=np.float64)  # RGB order, in [0, 1]
        if img.shape[-1] != 3:
            raise ValueError(f"normals: expected an RGB normal map, got {img.shape[-1]} channel(s) in {path}")
        n = img * 2.0 - 1.0  # BiNI coding: RGB = (n + 1) / 2, gpps axes
    n = np.asarray(n, dtype=np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals: expected (H, W, 3), got {n.shape} in {path}")
    return n


def run(args) -> int:
    inputs = [args.normals, args.mask, args.K]
    out = prepare_out(args, inputs=inputs)
    normals = _read_normals(Path(args.normals))
    mask = read_mask(args.mask)
    if mask.shape != normals.shape[:2]:
        raise ValueError(f"mask: expected shape {normals.shape[:2]} matching the normals, got {mask.shape}")
    with as_options("pixel_size"):
        camera = Perspective(read_K(args.K)) if args.K else Orthographic(args.pixel_size)
    poisson_opts = [f"--{k}" for k in ("solver", "tol", "robust") if getattr(args, k) is not None]
    method = args.method or ("bini" if args.bilateral or not poisson_opts else "poisson")
    if method == "bini" and poisson_opts:
        raise ValueError(f"--method: {', '.join(poisson_opts)} set(s) the Poisson solve; expected --method poisson "
                         f"with them, got --method bini")
    if args.bilateral and method != "bini":
        raise ValueError("--bilateral: expected no --method poisson with it")
    with as_options("reference_depth", "tol", "solver", "robust", bilateral_k="--k"):
        if method == "bini":
            res = gpps.integrate_normals(normals, mask, camera=camera, bilateral=True, bilateral_k=float(args.k),
                                         reference_depth=args.reference_depth, device=args.device,
                                         progress=bar("integrate"))
        else:
            res = gpps.integrate_normals(
                normals, mask, camera=camera, solver=args.solver or "multigrid",
                tol=1e-5 if args.tol is None else args.tol, robust=args.robust or "none",
                reference_depth=args.reference_depth, device=args.device, progress=bar("integrate"),
            )
    with atomic_dir(out, overwrite=args.overwrite, inputs=inputs, name="--out") as tmp:
        _write(tmp, res, camera, args, method, normals, mask)
    print(f"integrate ({method}): {int(res.mask.sum())} pixels, {res.outer_iterations} outer / {res.iterations} "
          f"iterations, residual {res.residual:.2e}, {res.timings.get('total', 0):.2f} s -> {args.out}")
    return 0


def _write(out, res, camera, args, method, normals, mask) -> None:
    """The output set (:mod:`gpps.io.outputs`, depth in its convention) and report.json into the temporary folder ``out``."""
    conv = depth_convention(camera, known_scale="--reference-depth" if args.reference_depth is not None else None)
    depth = apply_depth_convention(res.depth, res.mask, conv)
    nn = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    written = write_outputs(out, normals=nn, albedo=None, mask=mask, depth=depth, depth_mask=res.mask,
                            camera=camera, depth_info=conv)
    report = {
        "solver": res.solver, "iterations": res.iterations, "outer_iterations": res.outer_iterations,
        "residual": res.residual, "solver_residual": res.solver_residual, "converged": res.converged,
        "n_pixels": int(res.mask.sum()), "n_invalid": res.n_invalid, "n_components": res.n_components,
        "timings_s": res.timings, "camera": "perspective" if camera.is_perspective else "orthographic",
        "method": method, "robust": args.robust or "none", "device": args.device, "view": written.get("view"),
        "depth": conv, "outputs": written["files"],
    }
    if "view_fallback_reason" in written:
        report["view_fallback_reason"] = written["view_fallback_reason"]
    if method == "bini":
        report.update(k=float(args.k), energy=res.energy)
    report["warnings"] = warning_messages(args)
    save_json(out / "report.json", report)
