"""Train the single-image normal / depth network (issues 8 and 24) on scenes gpps renders itself and, with
``--mitsuba``, the same generator's scenes rendered by Mitsuba's path tracer (:mod:`mitsuba_random`).

Runs on the GPU machine (PyTorch + the Warp kit; ``training/device_train.sh`` carries the Mitsuba shards and
runs this in its own process session)::

    python3 training/train_single.py --out DIR --minutes 15 --batch 64 --mitsuba SHARDS --mitsuba-val VAL

Data recipe v2 (:mod:`shapes`, issue 24): ``--train`` random scenes of seeds ``0..train-1`` (height
fields, surfaces of revolution, smooth-union blobs, composed solids occluding each other, objects on a
support, reliefs; uniform / noise / cell / stripe / mixed RGB albedo, grey a third of the time, objects
apart from their support; the five reflectance models and the dielectric plastic with random parameters;
directional or point lights with cast shadows; orthographic or perspective camera; an indirect fill term,
exposure with clipping, noise, 8-bit quantisation), each
rendered under ``--lights`` random lights by gpps's Warp renderer; validation scenes use seeds
``TRAIN_SEED_LIMIT - 1 - k`` (never trained on).  Augmentation: flips and 90-degree rotations
(normals rotated with the image) and a gamma in [0.8, 1.25] on the normalised input.

``--mitsuba``: a share (``--mitsuba-frac``) of each batch from the Mitsuba shards (normal loss only: they hold no
height target).  ``--fusion max``: each step draws K in 1..``--max-images`` and gives the network K images of each
scene (distinct lights), fused inside it (:meth:`gpps.nn.model.SingleNet.forward`).  ``--init``: start from a
weights file (its widths).

Losses (seed 6.10, 6.11): ``L_n = -(1/m) sum_i N_i . N*_i`` over the m mask pixels, and
``L_d = (1/m) sum D_i^2 - (1/(2 m^2)) (sum D_i)^2 + (1/m) sum (grad_x D_i^2 + grad_y D_i^2)`` with
``D = Z - Z*`` the relative height error (units of half the image width) and the gradients as
differences over pixel pairs inside the mask divided by the pixel spacing 2/S.  Total
``L = L_n + w_d L_d``.

Writes ``single_net.npz`` (numpy weights + meta JSON, what :mod:`gpps.nn.model` loads) and
``single_training.json`` (recipe, steps, losses, validation MAEN against the flat-plane baseline).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # a script run from a checkout, not an installed package
    sys.path.insert(0, str(ROOT))

from gpps.nn.model import arch, layers, prepare_input  # noqa: E402
from shapes import TRAIN_SEED_LIMIT, SceneRenderer, random_scene, render_random_sample  # noqa: E402


def _scene(args):
    size, seed = args
    return random_scene(size, seed)


def build_dataset(seeds, size, n_lights, device, pool, log=None):
    """Inputs (N, L, 4, S, S) f16, normals (N, 3, S, S) f16, height (N, 1, S, S) f16, mask (N, 1, S, S) u8."""
    n = len(seeds)
    X = np.zeros((n, n_lights, 4, size, size), np.float16)
    N = np.zeros((n, 3, size, size), np.float16)
    Z = np.zeros((n, 1, size, size), np.float16)
    M = np.zeros((n, 1, size, size), np.uint8)
    rend = SceneRenderer(device)
    stats = {"family": {}, "brdf": {}, "albedo": {}, "camera": {}, "lights": {}, "shadows": {}}
    t0 = time.time()
    for k, sc in enumerate(pool.imap(_scene, [(size, int(s)) for s in seeds], chunksize=16)):
        sc, nrm, imgs, lights = render_random_sample(size, int(seeds[k]), rend, n_lights=n_lights, scene=sc)
        for li in range(n_lights):
            X[k, li] = prepare_input(imgs[li], sc.mask)
        N[k] = nrm.transpose(2, 0, 1)
        Z[k, 0] = sc.relative_height()
        M[k, 0] = sc.mask
        for key, val in (("family", sc.family), ("brdf", sc.material.brdf), ("albedo", sc.info["albedo"]),
                         ("camera", sc.camera_kind), ("lights", lights.kind), ("shadows", str(sc.info["shadows"]))):
            stats[key][val] = stats[key].get(val, 0) + 1
        if log and (k + 1) % 1000 == 0:
            log(f"data {k + 1}/{n} {time.time() - t0:.1f}s")
    return X, N, Z, M, stats


def _fake(n, size, n_lights):
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, (n, n_lights, 4, size, size)).astype(np.float16)
    X[:, :, 3] = 1
    nr = rng.normal(0, 1, (n, 3, size, size))
    nr[:, 2] = np.abs(nr[:, 2])
    nr /= np.linalg.norm(nr, axis=1, keepdims=True)
    Z = rng.normal(0, 0.1, (n, 1, size, size)).astype(np.float16)
    return X, nr.astype(np.float16), Z, np.ones((n, 1, size, size), np.uint8), {}


def load_mitsuba(folder, size, log=None):
    """The Mitsuba-rendered scenes of ``folder``'s shards (:mod:`mitsuba_random`): inputs (N, L, 4, S, S) f16 (L
    lights a scene, one per shard folder), normals (N, 3, S, S) f16, height (N, 1, S, S) f16 (zero: these scenes train the normals only), mask
    (N, 1, S, S) u8 and the per-scene info records."""
    from mitsuba_random import decode_shard

    shards = sorted(Path(folder).glob("mts_*.npz"))
    if not shards:
        raise FileNotFoundError(f"--mitsuba: no mts_*.npz shards in {folder}")
    Xs, Ns, Ms, info = [], [], [], []
    for f in shards:
        d = decode_shard(f)
        ims = d["images"] if d["images"].ndim == 5 else d["images"][:, None]  # (n, L, S, S, 3)
        if ims.shape[2] != size or (Xs and ims.shape[1] != Xs[0].shape[1]):
            raise ValueError(f"{f}: expected {size}^2 scenes of one light count, got {ims.shape[1:4]}")
        Xs.append(np.stack([[prepare_input(im, m) for im in sc] for sc, m in zip(ims, d["mask"])]).astype(np.float16))
        Ns.append(d["normals"].transpose(0, 3, 1, 2).astype(np.float16))
        Ms.append(d["mask"][:, None].astype(np.uint8))
        info += d["info"]
    X, N, M = np.concatenate(Xs), np.concatenate(Ns), np.concatenate(Ms)
    if log:
        log(f"mitsuba: {len(X)} scenes from {len(shards)} shards in {folder}")
    return X, N, np.zeros(M.shape, np.float16), M, info


def make_model(torch, widths):
    nn = torch.nn
    ENC, DEC, GLOBAL, HEAD = layers(widths)

    class Block(nn.Module):
        def __init__(self, cin, cout):
            super().__init__()
            self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
            self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)

        def forward(self, x):
            return torch.relu(self.conv2(torch.relu(self.conv1(x))))

    class Glob(nn.Module):
        def __init__(self):
            super().__init__()
            (_, a, b), (_, c, d) = GLOBAL
            self.fc1 = nn.Linear(a, b)
            self.fc2 = nn.Linear(c, d)

        def forward(self, x):
            g = x.mean(dim=(2, 3))
            return self.fc2(torch.relu(self.fc1(g)))

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            for name, cin, cout in ENC + DEC:
                self.add_module(name, Block(cin, cout))
            self.glob = Glob()
            self.head = nn.Conv2d(HEAD[1], HEAD[2], 3, padding=1)

        def forward(self, x):
            # x (B, 4, S, S), or (B, K, 4, S, S): K images of one scene, encoded one by one and fused by the
            # elementwise maximum at every scale (gpps.nn.model.SingleNet.forward)
            b, k_img = x.shape[0], (x.shape[1] if x.dim() == 5 else 1)
            x = x.reshape((b * k_img,) + tuple(x.shape[-3:]))
            skips = []
            for k, (name, _, _) in enumerate(ENC):
                if k:
                    x = torch.nn.functional.avg_pool2d(x, 2)
                x = getattr(self, name)(x)
                skips.append(x if k_img == 1 else x.reshape((b, k_img) + tuple(x.shape[1:])).amax(1))
            x = skips[-1]
            x = torch.relu(x + self.glob(x)[:, :, None, None])
            for (name, _, _), skip in zip(DEC, skips[-2::-1]):
                x = getattr(self, name)(torch.cat([torch.nn.functional.interpolate(x, scale_factor=2, mode="nearest"), skip], 1))
            return self.head(x)

    return Net()


def losses(torch, out, n_gt, z_gt, m, size):
    """(L_n (6.10), L_d (6.11), MAEN deg per image) for a batch (each per image: the caller weights them)."""
    out = out.float()
    n = torch.nn.functional.normalize(out[:, :3], dim=1, eps=1e-6)
    mf = m.float()
    cnt = mf.sum(dim=(1, 2, 3)).clamp_min(1.0)
    dot = (n * n_gt).sum(1, keepdim=True)
    l_n = -((dot * mf).sum(dim=(1, 2, 3)) / cnt)
    d = (out[:, 3:4] - z_gt) * mf
    s1 = d.sum(dim=(1, 2, 3))
    s2 = (d * d).sum(dim=(1, 2, 3))
    inv_h = size / 2.0  # 1 / pixel spacing in normalised units
    mx = mf[..., :, 1:] * mf[..., :, :-1]
    my = mf[..., 1:, :] * mf[..., :-1, :]
    gx = (d[..., :, 1:] - d[..., :, :-1]) * inv_h * mx
    gy = (d[..., 1:, :] - d[..., :-1, :]) * inv_h * my
    l_d = s2 / cnt - 0.5 * (s1 / cnt) ** 2 + ((gx * gx).sum(dim=(1, 2, 3)) + (gy * gy).sum(dim=(1, 2, 3))) / cnt
    with torch.no_grad():
        ang = torch.rad2deg(torch.acos(dot.clamp(-1.0, 1.0)))
        maen = (ang * mf).sum(dim=(1, 2, 3)) / cnt
    return l_n, l_d, maen


def si_error(torch, out, z_gt, m):
    """Scale-(offset-)invariant RMS height error sqrt(mean D^2 - mean(D)^2) per image."""
    mf = m.float()
    cnt = mf.sum(dim=(1, 2, 3)).clamp_min(1.0)
    d = (out[:, 3:4].float() - z_gt) * mf
    mean = d.sum(dim=(1, 2, 3)) / cnt
    return torch.sqrt(((d * d).sum(dim=(1, 2, 3)) / cnt - mean**2).clamp_min(0.0))


def augment(torch, x, n, z, m):
    """Random flips / 90-degree rotations (normals rotated with the image) and a gamma on the input; ``x``
    (B, 4, S, S) or (B, K, 4, S, S) (a scene's K images transformed alike, each its own gamma)."""
    if torch.rand(()) < 0.5:  # horizontal flip: columns reversed, n_x -> -n_x
        x, n, z, m = (t.flip(-1) for t in (x, n, z, m))
        n = torch.cat([-n[:, :1], n[:, 1:]], 1)
    if torch.rand(()) < 0.5:  # vertical flip: rows reversed, n_y -> -n_y
        x, n, z, m = (t.flip(-2) for t in (x, n, z, m))
        n = torch.cat([n[:, :1], -n[:, 1:2], n[:, 2:]], 1)
    if torch.rand(()) < 0.5:  # transpose (rows <-> columns): x right <-> y down, so (nx, ny) -> (-ny, -nx)
        x, n, z, m = (t.transpose(-1, -2) for t in (x, n, z, m))
        n = torch.cat([-n[:, 1:2], -n[:, :1], n[:, 2:]], 1)
    g = torch.exp(torch.empty(x.shape[:-3] + (1, 1, 1), device=x.device).uniform_(math.log(0.8), math.log(1.25)))
    x = torch.cat([x[..., :3, :, :].clamp_min(0.0) ** g, x[..., 3:, :, :]], -3)
    return x, n, z, m


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--train", type=int, default=4000, help="training scenes")
    ap.add_argument("--val", type=int, default=200, help="validation scenes")
    ap.add_argument("--lights", type=int, default=2, help="renders (lights) per training scene")
    ap.add_argument("--minutes", type=float, default=5.0, help="training wall-clock budget")
    ap.add_argument("--max-steps", type=int, default=100000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--wd", type=float, default=1.0, help="weight of the depth loss (6.11)")
    ap.add_argument("--workers", type=int, default=min(12, os.cpu_count() or 1))
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smoke", action="store_true", help="random tensors instead of renders (tests the torch code only)")
    ap.add_argument("--init", default=None, help="start from these weights (a single_net.npz): fine-tuning")
    ap.add_argument("--warmup", type=int, default=300, help="learning-rate warm-up steps")
    ap.add_argument("--widths", default="24,48,96,144,192", help="encoder channel widths, one per scale")
    ap.add_argument("--mitsuba", default=None, help="folder of Mitsuba-rendered shards (training/mitsuba_random.py)")
    ap.add_argument("--mitsuba-val", default=None, help="folder of Mitsuba-rendered validation shards")
    ap.add_argument("--mitsuba-frac", type=float, default=0.5, help="share of each batch drawn from --mitsuba")
    ap.add_argument("--fusion", choices=["none", "max"], default="none",
                    help="max: train on 1 to --max-images images of a scene at once, fused by their maximum (--lights, and "
                         "the Mitsuba shards' lights, at least that many)")
    ap.add_argument("--max-images", type=int, default=3, help="with --fusion max: the most images of one sample")
    args = ap.parse_args(argv)

    import torch

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    log_lines = []

    def log(msg):
        line = f"[{time.time() - t_start:7.1f}s] {msg}"
        print(line, flush=True)
        log_lines.append(line)

    torch.manual_seed(args.seed)
    dev = torch.device(args.device)
    warp_device = args.device if args.device.startswith("cuda") else "cpu"
    tr_seeds = np.arange(args.train)
    va_seeds = TRAIN_SEED_LIMIT - 1 - np.arange(args.val)
    if args.smoke:
        Xtr, Ntr, Ztr, Mtr, stats = _fake(args.train, args.size, args.lights)
        Xva, Nva, Zva, Mva, _ = _fake(args.val, args.size, 1)
    else:
        with Pool(args.workers) as pool:  # numpy workers forked before Warp / CUDA start
            Xtr, Ntr, Ztr, Mtr, stats = build_dataset(tr_seeds, args.size, args.lights, warp_device, pool, log)
            Xva, Nva, Zva, Mva, _ = build_dataset(va_seeds, args.size, 1, warp_device, pool)
    t_data = time.time() - t_start
    log(f"data: {args.train} train x {args.lights} lights, {args.val} val scenes at {args.size}^2 in {t_data:.1f}s")
    widths = tuple(int(x) for x in args.widths.split(","))
    frac = float(args.mitsuba_frac) if args.mitsuba else 0.0
    if not 0.0 <= frac <= 1.0:
        raise SystemExit(f"--mitsuba-frac: expected a share in [0, 1], got {frac}")
    mts_info = []
    if args.mitsuba:
        Xmt, Nmt, Zmt, Mmt, mts_info = load_mitsuba(args.mitsuba, args.size, log)
    vals = {"gpps": (Xva[:, 0], Nva, Zva, Mva)}
    if args.mitsuba_val:
        Xmv, Nmv, Zmv, Mmv, _ = load_mitsuba(args.mitsuba_val, args.size, log)
        vals["mitsuba"] = (Xmv[:, 0], Nmv, Zmv, Mmv)
        if args.fusion == "max" and Xmv.shape[1] > 1:  # the same scenes, all their images fused
            vals[f"mitsuba_k{Xmv.shape[1]}"] = (Xmv, Nmv, Zmv, Mmv)
    kmax = 1
    if args.fusion == "max":
        kmax = min(args.max_images, args.lights, Xmt.shape[1] if args.mitsuba else args.lights)
        if kmax < 2:
            raise SystemExit(f"--fusion max: expected --lights and the Mitsuba shards' lights >= 2, got {args.lights} "
                             f"and {Xmt.shape[1] if args.mitsuba else '-'}")

    to = lambda a, dt: torch.from_numpy(a).to(dev, dt)  # noqa: E731
    Xtr_t, Ntr_t, Ztr_t, Mtr_t = to(Xtr, torch.float16), to(Ntr, torch.float32), to(Ztr, torch.float32), to(Mtr, torch.bool)
    if args.mitsuba:
        Xmt_t, Nmt_t, Mmt_t = to(Xmt, torch.float16), to(Nmt, torch.float32), to(Mmt, torch.bool)
        Zmt_t = torch.zeros(Mmt_t.shape, device=dev, dtype=torch.float32)
    vals_t = {k: (to(x, torch.float32), to(n, torch.float32), to(z, torch.float32), to(m, torch.bool)) for k, (x, n, z, m) in vals.items()}

    if args.init:
        from gpps.nn.model import load_weights

        init_params, init_meta = load_weights(args.init)
        widths = tuple(int(x) for x in init_meta.get("widths", widths))  # the initial network's widths
    model = make_model(torch, widths)
    if args.init:
        model.load_state_dict({k: torch.from_numpy(v) for k, v in init_params.items()})
        log(f"initialised from {args.init} (trained {init_meta.get('steps')} steps, val MAEN {init_meta.get('val_maen_deg')})")
    model = model.to(dev).to(memory_format=torch.channels_last)
    n_params = sum(p.numel() for p in model.parameters())
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    use_amp = dev.type == "cuda"

    def evaluate(name):
        Xv, Nv, Zv, Mv = vals_t[name]
        model.eval()
        maens, sis, lns, lds = [], [], [], []
        with torch.no_grad():
            for s in range(0, Xv.shape[0], 64):
                xb = Xv[s : s + 64]
                xb = xb.contiguous(memory_format=torch.channels_last) if xb.dim() == 4 else xb.contiguous()
                with torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
                    o = model(xb)
                ln, ld, maen = losses(torch, o, Nv[s : s + 64], Zv[s : s + 64], Mv[s : s + 64], args.size)
                maens.append(maen)
                sis.append(si_error(torch, o, Zv[s : s + 64], Mv[s : s + 64]))
                lns.append(ln)
                lds.append(ld)
        model.train()
        cat = lambda v: float(torch.cat(v).mean())  # noqa: E731
        return {"maen_deg": cat(maens), "si_height": cat(sis), "loss_normal": cat(lns), "loss_depth": cat(lds)}

    # flat-plane baseline on each validation set: n = (0, 0, 1), height 0
    flat_maen, flat_si = {}, {}
    for name, (Xv, Nv, Zv, Mv) in vals_t.items():
        flat = torch.zeros((Xv.shape[0], 4) + tuple(Xv.shape[-2:]), device=dev)
        flat[:, 2] = 1.0
        flat_maen[name] = float(losses(torch, flat, Nv, Zv, Mv, args.size)[2].mean())
        flat_si[name] = float(si_error(torch, flat, Zv, Mv).mean())
    log(f"model: widths {widths}, {n_params} parameters; flat-plane val MAEN "
        + ", ".join(f"{k} {v:.2f} deg" for k, v in flat_maen.items()))

    budget = args.minutes * 60.0
    t_train = time.time()
    step = 0
    history = []
    ema = None
    ntr = Xtr_t.shape[0]
    n_mts = int(round(args.batch * frac))
    while step < args.max_steps:
        tfrac = (time.time() - t_train) / budget
        if tfrac >= 1.0:
            break
        lr = args.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(tfrac, 1.0)))) * min(1.0, (step + 1) / max(args.warmup, 1))
        for g in opt.param_groups:
            g["lr"] = lr
        nb_g = args.batch - n_mts
        k_img = int(torch.randint(1, kmax + 1, ()))  # images of each sample this step (1 without fusion)
        idx = torch.randint(0, ntr, (nb_g,), device=dev)
        li = torch.rand(nb_g, args.lights, device=dev).argsort(1)[:, :k_img]  # k distinct lights of each scene
        xb, nb, zb, mb = Xtr_t[idx[:, None], li].float(), Ntr_t[idx], Ztr_t[idx], Mtr_t[idx]
        wd = torch.full((nb_g,), args.wd, device=dev)
        if n_mts:
            j = torch.randint(0, Xmt_t.shape[0], (n_mts,), device=dev)
            lj = torch.rand(n_mts, Xmt_t.shape[1], device=dev).argsort(1)[:, :k_img]
            xb = torch.cat([xb, Xmt_t[j[:, None], lj].float()])
            nb, zb, mb = torch.cat([nb, Nmt_t[j]]), torch.cat([zb, Zmt_t[j]]), torch.cat([mb, Mmt_t[j]])
            wd = torch.cat([wd, torch.zeros(n_mts, device=dev)])  # no height target for the Mitsuba scenes
        if k_img == 1:
            xb = xb[:, 0]
        xb, nb, zb, mb = augment(torch, xb, nb, zb, mb)
        xb = xb.contiguous(memory_format=torch.channels_last) if xb.dim() == 4 else xb.contiguous()
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
            o = model(xb)
        ln, ld, maen = losses(torch, o, nb, zb, mb, args.size)
        loss = ln.mean() + (wd * ld).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        step += 1
        cur = np.array([float(ln.mean()), float(ld[:nb_g].mean()) if nb_g else 0.0, float(maen.mean())]) if step % 50 == 0 else None
        if cur is not None:
            ema = cur if ema is None else 0.9 * ema + 0.1 * cur
        if step % 1000 == 0:
            v = {name: evaluate(name) for name in vals_t}
            rec = {"step": step, "time_s": round(time.time() - t_train, 1), "lr": lr,
                   "train_loss_normal": float(ema[0]), "train_loss_depth": float(ema[1]), "train_maen_deg": float(ema[2]),
                   **{f"val_{name}_{k}": val for name, r in v.items() for k, val in r.items()}}
            history.append(rec)
            log(f"step {step} lr {lr:.2e} train L_n {ema[0]:.4f} L_d {ema[1]:.4f} MAEN {ema[2]:.2f} | val MAEN "
                + ", ".join(f"{name} {r['maen_deg']:.2f}" for name, r in v.items()))
    t_train = time.time() - t_train
    finals = {name: evaluate(name) for name in vals_t}
    final = finals["gpps"]
    log(f"done: {step} steps in {t_train:.1f}s; val MAEN " + ", ".join(
        f"{name} {r['maen_deg']:.2f} deg (flat {flat_maen[name]:.2f})" for name, r in finals.items()))

    params = {k: v.detach().float().cpu().numpy() for k, v in model.state_dict().items()}
    shapes = arch(widths)
    for k, shape in shapes.items():
        assert params[k].shape == shape, (k, params[k].shape, shape)
    extra = set(params) - set(shapes)
    assert not extra, extra
    # a numpy check of the exported weights on one validation image
    from gpps.nn.model import SingleNet

    # val_maen_deg is what the flow takes as the network's expected error (the highlight fit's prior): the
    # physically based validation set's when there is one, the closer of the two to images from the wild
    expected = finals.get("mitsuba", final)["maen_deg"]
    meta = {"size": args.size, "widths": list(widths), "fusion": args.fusion, "max_images": kmax, "steps": step,
            "init": args.init, "train_seconds": round(t_train, 1),
            "val_maen_deg": expected, "val_maen_deg_by_set": {k: r["maen_deg"] for k, r in finals.items()},
            "trained_with": f"torch {torch.__version__}", "parameters": n_params}
    net = SingleNet(params, meta)
    o_np = net.forward(Xva[0, 0].astype(np.float32))
    with torch.no_grad():
        o_t = model.float()(vals_t["gpps"][0][:1].contiguous(memory_format=torch.channels_last))[0].cpu().numpy()
    meta["numpy_vs_torch_max_abs"] = float(np.max(np.abs(o_np - o_t)))
    fused = [k for k in vals_t if k.startswith("mitsuba_k")]
    if fused:  # the fusion too: one validation scene's images at once
        xk = vals_t[fused[0]][0][:1]
        o_np = net.forward(xk[0].cpu().numpy())
        with torch.no_grad():
            o_t = model(xk.contiguous())[0].cpu().numpy()
        meta["numpy_vs_torch_fused_max_abs"] = float(np.max(np.abs(o_np - o_t)))
    np.savez(out / "single_net.npz", meta=np.array(json.dumps(meta)), **{k: v.astype(np.float32) for k, v in params.items()})
    report = {
        "recipe": {
            "generator": "shapes.render_random_sample, recipe v2 (gpps Warp Renderer + CastShadows, device %s)" % warp_device,
            "size": args.size, "train_scenes": args.train, "renders_per_train_scene": args.lights,
            "train_seeds": [0, int(args.train) - 1], "val_seeds": [int(va_seeds[-1]), int(va_seeds[0])],
            "val_scenes": args.val, "counts": stats,
            "augmentation": "flips, transpose (normals rotated with the image), input gamma in [0.8, 1.25]",
            "data_seconds": round(t_data, 1),
            "mitsuba": None if not args.mitsuba else {
                "generator": "mitsuba_random.render_random (recipe v2's shapes as a 2.5D shell, Mitsuba 3 path tracer)",
                "scenes": len(mts_info), "batch_share": frac, "folder": str(args.mitsuba),
                "counts": {key: {v: sum(1 for r in mts_info if str(r[key]) == v) for v in sorted({str(r[key]) for r in mts_info})}
                           for key in ("family", "bsdf_objects", "bsdf_support", "light", "bits")}},
        },
        "model": {"parameters": n_params, "widths": list(widths), "architecture": "gpps.nn.model docstring"},
        "training": {"optimizer": "AdamW wd 1e-4", "lr": args.lr, "init": args.init,
                     "schedule": f"{args.warmup}-step warm-up, cosine to 2% over the time budget",
                     "batch": args.batch, "steps": step, "seconds": round(t_train, 1), "depth_loss_weight": args.wd,
                     "mixed_precision": "bf16 autocast" if use_amp else "none", "device": str(dev)},
        "losses": {"normal": "6.10: -(1/m) sum N.N*", "depth": "6.11 with lambda 1/2 and gradient terms (spacing 2/S)"},
        "validation": {**final, "flat_plane_maen_deg": flat_maen["gpps"], "flat_plane_si_height": flat_si["gpps"],
                       "by_set": {k: {**r, "flat_plane_maen_deg": flat_maen[k]} for k, r in finals.items()}},
        "numpy_vs_torch_max_abs": meta["numpy_vs_torch_max_abs"],
        "history": history,
        "log": log_lines,
    }
    (out / "single_training.json").write_text(json.dumps(report, indent=2) + "\n")
    log(f"wrote {out / 'single_net.npz'} and single_training.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
