"""Forward-render time per frame (N lights, RGB) on a device: `python perf/render_speed.py [--device cuda:0]`.

Bytes counted per pixel: reads depth (4), normal (12), mask (1), albedo (12) and writes N x 12;
FLOPs are not counted here (the model kernels are measured in perf/bench.py).
"""

import argparse

from _common import timeit, write_results

from gpps._runtime import resolve_device, warp
from gpps.material import Material
from gpps.pipeline.render import Renderer
from gpps.host.scenes import make_scene
from gpps.flows.synthetic import default_lights


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="auto")
    ap.add_argument("--sizes", default="256,512,1024")
    ap.add_argument("--n-lights", type=int, default=3)
    args = ap.parse_args()
    device = resolve_device(args.device)
    wp = warp()
    rows = []
    for size in [int(s) for s in args.sizes.split(",")]:
        scene = make_scene("sphere", size, "perspective")
        for brdf in ["blinn-phong", "cook-torrance"]:
            r = Renderer(scene.shape, scene.camera, default_lights("point", args.n_lights), Material.default_for(brdf), device=device)
            r.run(scene.depth, scene.mask, scene.albedo, scene.normals)  # uploads + compile
            from gpps.kernels.render import render_kernel

            def launch():
                wp.launch(render_kernel, dim=r.shape, inputs=[r.depth, r.normals, r.mask, r.albedo, r.cam, r.lp, r.mp], outputs=[r.images], device=device)

            t = timeit(launch, lambda: wp.synchronize_device(device), repeat=10 if device == "cpu" else 100)
            nbytes = size * size * (4 + 12 + 1 + 12 + args.n_lights * 12)
            rows.append({"size": size, "brdf": brdf, "n_lights": args.n_lights, **t, "GB_per_s": nbytes / t["median_s"] / 1e9})
            print(f"{size:5d}^2 {brdf:14s} N={args.n_lights}: {1e3 * t['median_s']:9.3f} ms   {rows[-1]['GB_per_s']:8.2f} GB/s")
    print("wrote", write_results("render_speed", device, {"rows": rows}))


if __name__ == "__main__":
    main()
