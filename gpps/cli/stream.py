"""``gpps stream``: reconstruct a stream of frame sets (e.g. triples) and report frames per second.

Sources:

* ``--synthetic``: a moving synthetic scene (the ``bumps`` height field drifting
  sideways under the chosen lights), rendered on the fly as uint16 frames.
* ``SOURCE`` folder: the calibration of a DiLiGenT-style capture
  (``light_directions.txt`` or ``light_positions.txt``, optional
  ``light_intensities.txt``, ``K.txt``, ``mask.png``) and the frames either as
  images ``<frame>_<k>.png`` (k = 0..N-1, one per light, sorted by frame), or as
  one video per light ``light<k>.<ext>`` (read with OpenCV).

Every ``--save-every``-th result is written to ``OUT/frame_<index>/``
(``normals.npy``, ``albedo.npy``, ``depth.npy``, ``normals.png``); a
``report.json`` ends the run (frames, errors with their indices, frames per second).
A frame the folder cannot give (a missing image, images of different sizes) is an error naming the
files; the stream goes on.  The exit status is 2 when every frame was rejected (the report stays).
The output folder is written as a temporary sibling and renamed when the stream
ends; Ctrl-C ends a live stream normally (``"interrupted": true`` in the report),
any other failure leaves nothing behind.
"""

from __future__ import annotations

import json
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np

import gpps
from gpps import BRDF_NAMES, DirectionalLights, Material, Orthographic, Perspective, PointLights
from gpps.cli._output import add_output_args, as_options, prepare_out, warning_messages
from gpps.cli._progress import quiet
from gpps.io import atomic_dir, read_K, read_mask, read_matrix, save_json, save_npy, save_png


def register(sub):
    p = sub.add_parser("stream", help="stream frame sets (e.g. triples) through the real-time pipeline")
    p.add_argument("source", nargs="?", help="folder with calibration files and frames (<frame>_<k>.png or light<k>.* videos)")
    p.add_argument("--synthetic", action="store_true", help="stream a moving synthetic scene instead of SOURCE")
    p.add_argument("--frames", type=int, default=100, help="synthetic frames")
    p.add_argument("--size", type=int, default=256, help="synthetic frame size")
    p.add_argument("--brdf", choices=BRDF_NAMES, default="blinn-phong", help="reflectance model of the solve")
    p.add_argument("--iterations", type=int, default=3, help="solver iterations per frame")
    p.add_argument("--integration-iterations", type=int, default=2, help="PCG iterations per frame")
    p.add_argument("--reference-depth", type=float, default=None, help="mean depth (scene units); needed for point lights")
    p.add_argument("--save-every", type=int, default=0, help="save every k-th result (0: none)")
    add_output_args(p, "output folder (report.json, frame_<index>/ with --save-every)")
    p.set_defaults(func=run)


def _synthetic(args):
    sc = gpps.make_scene("bumps", args.size, "perspective")
    mat = Material.default_for(args.brdf)
    L = gpps.default_lights("directional", 3)

    drift = max(1, args.size // 16)
    # the scene slides sideways by up to `drift` pixels; the stream's (fixed) mask is where it always is
    stream_mask = sc.mask.copy()
    for s in range(drift):
        stream_mask &= np.roll(sc.mask, s, axis=1)

    def rolled(a, s):
        return np.roll(a, s, axis=1) if np.ndim(a) >= 2 else a

    def frames():
        for f in range(args.frames):
            s = (f // 2) % drift
            moved = type(sc)(**{k: rolled(v, s) if isinstance(v, np.ndarray) else v for k, v in sc.__dict__.items()})
            img = gpps.render(moved, mat, L, bits=16, device=args.device if args.device != "auto" else None)
            yield np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)

    return sc.mask.shape, sc.camera, L, mat, stream_mask, frames()


def _folder(args):
    root = Path(args.source)
    if not root.is_dir():
        raise FileNotFoundError(f"source folder not found: {root}")
    ld, lp = root / "light_directions.txt", root / "light_positions.txt"
    if ld.is_file():
        dirs = read_matrix(ld, name="light_directions.txt")
        n = dirs.shape[0]
    elif lp.is_file():
        pos = read_matrix(lp, name="light_positions.txt")
        n = pos.shape[0]
    else:
        raise ValueError(f"{root}: expected light_directions.txt or light_positions.txt")
    inten = read_matrix(root / "light_intensities.txt", shape=(n, 3)) if (root / "light_intensities.txt").is_file() else None
    L = DirectionalLights(dirs, inten) if ld.is_file() else PointLights(pos, inten)
    mat_file = root / "material.json"
    mat = Material.from_dict(json.loads(mat_file.read_text())) if mat_file.is_file() else Material.default_for(args.brdf)
    pat = re.compile(r"^(.*)_(\d+)\.png$")
    groups: dict = {}
    for p in sorted(root.glob("*_*.png")):
        m = pat.match(p.name)
        if m:
            groups.setdefault(m.group(1), {})[int(m.group(2))] = p
    videos = [next(iter(sorted(root.glob(f"light{k}.*"))), None) for k in range(n)]
    reasons: dict = {}  # frame index -> why the folder could not give it (missing or mismatched images)
    if groups:
        keys = sorted(groups)
        first = cv2.imread(str(groups[keys[0]][0]), cv2.IMREAD_UNCHANGED)

        def frames():
            for index, key in enumerate(keys):
                g = groups[key]
                ims = [cv2.imread(str(g[k]), cv2.IMREAD_UNCHANGED) if k in g else None for k in range(n)]
                missing = [f"{key}_{k}.png" for k in range(n) if ims[k] is None]
                if missing or len({im.shape for im in ims}) != 1:
                    # reported as a bad frame by the stream, with this reason
                    reasons[index] = (f"frame {key}: " + (f"missing or unreadable {', '.join(missing)}" if missing else
                                      f"images of different sizes {[im.shape[:2] for im in ims]}"))
                    yield np.zeros((0,), np.uint8)
                    continue
                arr = np.stack(ims)
                yield arr[..., ::-1].copy() if arr.ndim == 4 else arr  # BGR -> RGB
    elif all(v is not None for v in videos):
        caps = [cv2.VideoCapture(str(v)) for v in videos]
        ok, first = caps[0].read()
        caps[0].set(cv2.CAP_PROP_POS_FRAMES, 0)
        if not ok:
            raise ValueError(f"{videos[0]}: cannot read a frame")

        def frames():
            while True:
                ims = []
                for c in caps:
                    ok, im = c.read()
                    if not ok:
                        return
                    ims.append(im[..., ::-1])
                yield np.ascontiguousarray(np.stack(ims))
    else:
        raise ValueError(f"{root}: expected frames <frame>_<k>.png (k = 0..{n - 1}) or videos light0..light{n - 1}.*")
    h, w = first.shape[:2]
    cam = Perspective(read_K(root / "K.txt")) if (root / "K.txt").is_file() else Orthographic()
    mask = read_mask(root / "mask.png") if (root / "mask.png").is_file() else np.ones((h, w), bool)
    return (h, w), cam, L, mat, mask, frames(), reasons


def run(args) -> int:
    if args.synthetic == (args.source is not None):
        raise ValueError("source: expected either SOURCE or --synthetic")
    if args.save_every < 0:
        raise ValueError(f"--save-every: expected an integer >= 0, got {args.save_every}")
    inputs = [args.source]
    out = prepare_out(args, inputs=inputs)
    with as_options("size"):
        shape, cam, L, mat, mask, frames, reasons = (*_synthetic(args), {}) if args.synthetic else _folder(args)
    with as_options("iterations", "integration_iterations", "reference_depth"):
        cfg = gpps.StreamConfig(iterations=args.iterations, integration_iterations=args.integration_iterations,
                                reference_depth=args.reference_depth, output="numpy" if args.save_every else "device")
    st = gpps.Stream(shape, cam, L, mat, mask=mask, config=cfg, device=None if args.device == "auto" else args.device)
    errors, n, t0, last = [], 0, time.perf_counter(), time.perf_counter()
    interrupted = False
    tty = bool(getattr(sys.stderr, "isatty", lambda: False)())
    lead, tail = ("\r", "") if tty else ("", "\n")
    with atomic_dir(out, overwrite=args.overwrite, inputs=inputs, name="--out") as tmp:
        try:
            for r in st.iterate(frames):
                n += 1
                if not r.ok:
                    errors.append({"index": r.index, "error": reasons.get(r.index, r.error)})
                elif args.save_every and r.index % args.save_every == 0:
                    d = tmp / f"frame_{r.index:06d}"
                    save_npy(d / "normals.npy", r.normals)
                    save_npy(d / "albedo.npy", r.albedo)
                    if r.depth is not None:
                        save_npy(d / "depth.npy", r.depth)
                    save_png(d / "normals.png", np.where(mask[..., None], (r.normals + 1) / 2, 0), bits=8)
                now = time.perf_counter()
                if not quiet() and now - last > (0.5 if tty else 5.0):  # progress on stderr: redrawn on a terminal, lines in logs
                    sys.stderr.write(f"{lead}frame {n}  {n / (now - t0):7.1f} frames/s  errors {len(errors)}{tail}")
                    sys.stderr.flush()
                    last = now
        except KeyboardInterrupt:  # the normal end of a live stream: keep what was streamed
            interrupted = True
        dt = time.perf_counter() - t0
        if tty and not quiet() and n:
            sys.stderr.write("\n")
        print(f"frames {n}  {n / max(dt, 1e-9):.1f} frames/s (wall, including reading)  errors {len(errors)}"
              + ("  (interrupted)" if interrupted else ""))
        save_json(tmp / "report.json", {"frames": n, "seconds": dt, "frames_per_s": n / max(dt, 1e-9),
                                        "errors": errors, "interrupted": interrupted,
                                        "stream_seconds": st.stats["seconds"], "device": st.device,
                                        "warnings": warning_messages(args)})
    if n and len(errors) == n:  # (the report stays: it has every frame's reason)
        print(f"gpps stream: error: every frame ({n}) was rejected; the first: {errors[0]['error']} "
              f"(report in {out})", file=sys.stderr)
        return 2
    return 0
