"""The single-image normal / depth network: architecture, weights file and numpy inference.

A compact multi-scale encoder-decoder in the spirit of the seed's 6.2.4
(Eigen & Fergus's three scales): a coarse *global* scale (the deepest
features averaged over the whole image and passed through two fully
connected layers, then added back everywhere), a mid scale and a fine scale
(a U-Net decoder with skip connections) that predicts the x, y, z components
of the normal and a relative depth at every pixel::
    input (4, S, S): RGB / p99 inside the mask, and the mask
      enc0  conv3x3 4->16, 16->16                  S
      enc1  avgpool2, conv 16->32, 32->32          S/2
      enc2  avgpool2, conv 32->64, 64->64          S/4
      enc3  avgpool2, conv 64->96, 96->96          S/8
      enc4  avgpool2, conv 96->128, 128->128       S/16
      glob  mean over the image, fc 128->128, relu, fc 128->128; enc4 = relu(enc4 + glob)
      dec3  up2 (nearest), concat enc3, conv 224->96, 96->96
      dec2  up2, concat enc2, conv 160->64, 64->64
      dec1  up2, concat enc1, conv 96->32, 32->32
      dec0  up2, concat enc0, conv 48->16, 16->16
      head  conv3x3 16->4: normal = normalize(out[0:3]), depth = out[3]

The channel widths above are :data:`DEFAULT_WIDTHS` (the issue-8 network's); a weights file may name other
widths (its meta's ``"widths"``: the encoder's, one per scale), and :func:`layers` derives every layer from
them.  The shipped network (session 30, issue 24) has widths (24, 48, 96, 144, 192): 2.1 M parameters, trained
on recipe v2's scenes rendered by gpps and by Mitsuba's path tracer (``training/``).
Every conv is 3x3, zero padding 1, followed by ReLU (except the head).  The
training code (``training/``, PyTorch) builds the same layers with the same
names; the weights ship as ``gpps/nn/single_net.npz`` and are evaluated here
with numpy only (no PyTorch, no network access).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import cv2
import numpy as np

__all__ = ["ARCH", "DEFAULT_WIDTHS", "layers", "arch", "SingleNet", "load_weights", "prepare_input", "conv3x3", "WEIGHTS_PATH", "NET_SIZE"]

WEIGHTS_PATH = Path(__file__).with_name("single_net.npz")
NET_SIZE = 128  # the resolution the shipped network was trained at
TTAName = Literal["none", "flips", "dihedral"]  # test-time augmentation of SingleNet.predict
TTA_NAMES: tuple[str, ...] = get_args(TTAName)

#: the encoder's channel widths of the first shipped network (issue 8); a weights file names its own in its meta
DEFAULT_WIDTHS: tuple[int, ...] = (16, 32, 64, 96, 128)


def layers(widths=DEFAULT_WIDTHS) -> tuple[list, list, list, tuple]:
    """The conv / fc layer tables ``(enc, dec, glob, head)`` of the network with encoder ``widths``.

    ``enc``: ``(name, in, out)`` of each scale's block (``enc0`` at full resolution, then each after a 2x
    pooling), ``dec``: the decoder blocks from the coarsest skip up (input: the upsampled coarser features
    concatenated with the skip), ``glob``: the two fully connected layers of the global scale, ``head``: the
    3x3 output conv (4 channels).  The training code builds the same layers from the same tables.

    Raises:
        ValueError: ``widths`` is not a sequence of at least two positive integers.
    """
    try:
        w = tuple(int(x) for x in widths)
    except (TypeError, ValueError):
        raise ValueError(f"widths: expected a sequence of positive integers, got {widths!r}") from None
    if len(w) < 2 or min(w) < 1 or any(float(x) != int(x) for x in widths):
        raise ValueError(f"widths: expected at least two positive integers, got {widths!r}")
    enc = [(f"enc{k}", 4 if k == 0 else w[k - 1], w[k]) for k in range(len(w))]
    dec = [(f"dec{k}", w[k + 1] + w[k], w[k]) for k in reversed(range(len(w) - 1))]
    glob = [("glob.fc1", w[-1], w[-1]), ("glob.fc2", w[-1], w[-1])]
    return enc, dec, glob, ("head", w[0], 4)


# (name, in_channels, out_channels) of the default network's conv layers, in order
ENC, DEC, GLOBAL, HEAD = layers()


def arch(widths=DEFAULT_WIDTHS) -> dict:
    """Every parameter's name and shape (conv: (out, in, 3, 3), fc: (out, in), biases (out,)) for ``widths``."""
    enc, dec, glob, head = layers(widths)
    shapes = {}
    for name, cin, cout in enc + dec:
        shapes[f"{name}.conv1.weight"] = (cout, cin, 3, 3)
        shapes[f"{name}.conv1.bias"] = (cout,)
        shapes[f"{name}.conv2.weight"] = (cout, cout, 3, 3)
        shapes[f"{name}.conv2.bias"] = (cout,)
    for name, cin, cout in glob:
        shapes[f"{name}.weight"] = (cout, cin)
        shapes[f"{name}.bias"] = (cout,)
    name, cin, cout = head
    shapes[f"{name}.weight"] = (cout, cin, 3, 3)
    shapes[f"{name}.bias"] = (cout,)
    return shapes


ARCH = arch()


def prepare_input(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The network's input (4, H, W) float32 from one image.

    Args:
        image: (H, W) grey or (H, W, 3) RGB, any positive scale (linear or 8-bit
            gamma images alike: only the 99th percentile inside the mask is used).
        mask: (H, W) bool object pixels; None: the whole frame.

    The image is divided by the 99th percentile of its brightest channel
    inside the mask, clipped to [0, 1.5], zeroed outside the mask; the fourth
    channel is the mask.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")
    h, w = img.shape[:2]
    m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (h, w):
        raise ValueError(f"mask: expected shape {(h, w)}, got {m.shape}")
    if not m.any():
        raise ValueError("mask: expected at least one object pixel, got none")
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    p = float(np.percentile(img[m].max(-1), 99.0))
    x = np.clip(img / max(p, 1e-8), 0.0, 1.5) * m[..., None]
    return np.concatenate([x.transpose(2, 0, 1), m[None].astype(np.float32)], 0).astype(np.float32)


# --------------------------------------------------------------------------- numpy layers


def conv3x3(x: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """3x3 convolution (cross-correlation as in PyTorch), zero padding 1: (Cin, H, W) -> (Cout, H, W)."""
    cin, h, w = x.shape
    cout = weight.shape[0]
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1)))
    out = np.empty((cout, h * w), np.float32)
    # accumulate the nine shifted products: memory stays O(Cin H W)
    wk = weight.reshape(cout, cin, 9)
    out[:] = bias[:, None]
    for k in range(9):
        di, dj = divmod(k, 3)
        out += wk[:, :, k] @ xp[:, di : di + h, dj : dj + w].reshape(cin, h * w)
    return out.reshape(cout, h, w)


def _relu(x):
    return np.maximum(x, 0.0, out=x)


def _pool2(x):
    c, h, w = x.shape
    return x.reshape(c, h // 2, 2, w // 2, 2).mean(axis=(2, 4))


def _up2(x):
    return x.repeat(2, axis=1).repeat(2, axis=2)


def load_weights(path: str | Path | None = None) -> tuple[dict, dict]:
    """Read a weights file: ``(params, meta)``; params checked against :func:`arch` of the widths its meta
    names (``meta["widths"]``; files without it have :data:`DEFAULT_WIDTHS`).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a parameter is missing or has the wrong shape.
    """
    path = Path(path) if path is not None else WEIGHTS_PATH
    if not path.is_file():
        raise FileNotFoundError(f"weights: file not found: {path}")
    with np.load(path, allow_pickle=False) as z:
        params = {k: np.asarray(z[k], np.float32) for k in z.files if k != "meta"}
        meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
    shapes = arch(meta.get("widths", DEFAULT_WIDTHS))
    for k, shape in shapes.items():
        if k not in params:
            raise ValueError(f"weights: parameter {k!r} missing from {path}")
        if params[k].shape != shape:
            raise ValueError(f"weights: {k!r} expected shape {shape}, got {params[k].shape}")
    return params, meta


@dataclass
class SingleNet:
    """The network with its weights, evaluated with numpy.

    Example::
        net = SingleNet.load()                       # the shipped weights
        normals, rel_depth = net.predict(image, mask)
    """

    params: dict
    meta: dict

    @classmethod
    def load(cls, path: str | Path | None = None) -> "SingleNet":
        params, meta = load_weights(path)
        return cls(params, meta)

    @property
    def size(self) -> int:
        return int(self.meta.get("size", NET_SIZE))

    @property
    def widths(self) -> tuple[int, ...]:
        """The encoder's channel widths (the weights file's meta, else :data:`DEFAULT_WIDTHS`)."""
        return tuple(int(x) for x in self.meta.get("widths", DEFAULT_WIDTHS))

    @property
    def multiple(self) -> int:
        """Input sides must be multiples of this (one 2x pooling per scale below the first)."""
        return 2 ** (len(self.widths) - 1)

    def _block(self, name, x):
        p = self.params
        x = _relu(conv3x3(x, p[f"{name}.conv1.weight"], p[f"{name}.conv1.bias"]))
        return _relu(conv3x3(x, p[f"{name}.conv2.weight"], p[f"{name}.conv2.bias"]))

    @property
    def fusion(self) -> bool:
        """Whether the network was trained on several images of one object at once (``meta["fusion"] == "max"``):
        then :meth:`predict_many` fuses them; otherwise the flow averages its per-image predictions."""
        return self.meta.get("fusion") == "max"

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Raw output (4, H, W) for an input (4, H, W), or for K images of one object (K, 4, H, W), with H, W
        multiples of :attr:`multiple` (16 for five scales).

        K images go through the encoder one by one; at every scale their features are fused by the elementwise
        maximum over the images (PS-FCN's order-free fusion), and the global scale and the decoder see the fused
        features only.  One image is the same network without the fusion.
        """
        p = self.params
        x = np.asarray(x, np.float32)
        xs = x[None] if x.ndim == 3 else x
        q = self.multiple
        if xs.ndim != 4 or xs.shape[0] < 1 or xs.shape[1] != 4 or xs.shape[2] % q or xs.shape[3] % q:
            raise ValueError(f"x: expected (4, H, W) or (K, 4, H, W) with H, W multiples of {q}, got {x.shape}")
        enc, dec, _, _ = layers(self.widths)
        per = list(xs)
        skips = []
        for k, (name, _, _) in enumerate(enc):
            per = [self._block(name, _pool2(a) if k else a) for a in per]
            skips.append(per[0] if len(per) == 1 else np.max(np.stack(per), axis=0))
        x = skips[-1]
        g = x.mean(axis=(1, 2))
        g = np.maximum(p["glob.fc1.weight"] @ g + p["glob.fc1.bias"], 0.0)
        g = p["glob.fc2.weight"] @ g + p["glob.fc2.bias"]
        x = _relu(x + g[:, None, None])
        for (name, _, _), skip in zip(dec, skips[-2::-1]):
            x = self._block(name, np.concatenate([_up2(x), skip], 0))
        return conv3x3(x, p["head.weight"], p["head.bias"])

    def _forward_tta(self, x: np.ndarray, tta: str) -> np.ndarray:
        """:meth:`forward`, averaged over the transforms of ``tta`` (see :meth:`predict`); ``x`` (4, H, W) or
        (K, 4, H, W), every image transformed alike."""
        if tta not in TTA_NAMES:
            raise ValueError(f"tta: expected one of {list(TTA_NAMES)}, got {tta!r}")
        transposes = (False, True) if tta == "dihedral" else (False,)
        flips = ((False, False),) if tta == "none" else ((False, False), (True, False), (False, True), (True, True))
        acc = None
        for tr in transposes:
            for fj, fi in flips:
                y = np.swapaxes(x, -1, -2) if tr else x
                y = y[..., ::-1, :] if fi else y
                y = y[..., :, ::-1] if fj else y
                o = self.forward(np.ascontiguousarray(y))
                o = o[:, :, ::-1] if fj else o  # undo in reverse order, mapping the normal components back
                o = o[:, ::-1] if fi else o
                o = np.array(o, copy=True)
                if fj:
                    o[0] = -o[0]
                if fi:
                    o[1] = -o[1]
                if tr:
                    o = o.transpose(0, 2, 1).copy()
                    o[[0, 1]] = -o[[1, 0]]
                if acc is None:
                    acc = o
                else:
                    acc += o
        return acc / (len(transposes) * len(flips))

    def predict(self, image: np.ndarray, mask: np.ndarray | None = None, *, size: int | None = None,
                tta: TTAName = "none"):
        """Normals (H, W, 3) and relative depth (H, W) of one image.

        The image is resized so that its longer side is ``size`` (default: the
        training size), padded to a multiple of :attr:`multiple`, evaluated, and the outputs
        are resized back (normals renormalised).  The relative depth is in
        units of half the image's longer side, mean 0 over the mask; larger
        values are nearer the camera (it is a height).

        ``tta``: test-time augmentation, the mean of the outputs for transformed copies of the input,
        each mapped back (the training's own augmentations, so each copy is an image the network was
        trained on): ``"none"``; ``"flips"``: the 4 mirror images (horizontal, vertical, both;
        ``n_x``/``n_y`` negated back); ``"dihedral"``: those and their transposes (8; ``(n_x, n_y)`` ->
        ``(-n_y, -n_x)``).  Costs that many forward passes.

        Returns:
            (normals, height): float32, zero outside the mask.
        """
        return self._predict([np.asarray(image, np.float32)], mask, size, tta)

    def predict_many(self, images, mask: np.ndarray | None = None, *, size: int | None = None, tta: TTAName = "none"):
        """Normals (H, W, 3) and relative depth (H, W) from K images of one object under other lights, fused
        inside the network (:meth:`forward`; meaningful for a network trained so, :attr:`fusion`).

        Args:
            images: (K, H, W) or (K, H, W, 3), or a list of K such images of one size; any positive scale each.
            mask, size, tta: as :meth:`predict`.

        Raises:
            ValueError: no image, or images of different sizes.
        """
        ims = [np.asarray(im, np.float32) for im in images]
        if not ims or any(im.shape[:2] != ims[0].shape[:2] or im.ndim not in (2, 3) for im in ims):
            raise ValueError(f"images: expected K >= 1 images (H, W) or (H, W, 3) of one size, got {[im.shape for im in ims]}")
        return self._predict(ims, mask, size, tta)

    def _predict(self, ims: list, mask, size, tta):
        h, w = ims[0].shape[:2]
        m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
        s = int(size or self.size)
        scale = s / max(h, w)
        hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
        q = self.multiple
        H, W = -(-hs // q) * q, -(-ws // q) * q
        oy, ox = (H - hs) // 2, (W - ws) // 2
        xp = np.zeros((len(ims), 4, H, W), np.float32)
        for k, img in enumerate(ims):
            x = prepare_input(img, m)
            xs = np.stack([cv2.resize(ch, (ws, hs), interpolation=cv2.INTER_AREA) for ch in x])
            ms = xs[3] > 0.5
            xs[:3] *= ms
            xs[3] = ms
            xp[k, :, oy : oy + hs, ox : ox + ws] = xs
        out = self._forward_tta(xp[0] if len(ims) == 1 else xp, tta)[:, oy : oy + hs, ox : ox + ws]
        out = np.stack([cv2.resize(ch, (w, h), interpolation=cv2.INTER_LINEAR) for ch in out])
        n = out[:3].transpose(1, 2, 0)
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
        n[..., 2] = np.maximum(n[..., 2], 1e-3)  # visible normals face the camera
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        height = out[3]  # normalised image units: resolution-independent
        height = np.where(m, height - height[m].mean(), 0.0)
        n[~m] = 0.0
        return n.astype(np.float32), height.astype(np.float32)
