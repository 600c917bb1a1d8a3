"""Light calibration from images of spheres: directions (and intensities, positions) of the lights.

:func:`calibrate_lights` is what ``gpps calibrate-lights`` runs.  The folder holds one image per
light (any format :func:`gpps.io.capture.read_capture` reads, same order rules) of a mirror (chrome)
sphere, optionally with a matte (Lambertian) sphere or a grey card in view, and optionally ``K.txt``.

* The mirror sphere's outline: given circles, a mask image (``chrome_mask.*``, one blob per sphere)
  or found in the images (:func:`gpps.host.calibrate.find_outline`); each image's highlight gives a
  direction (:func:`gpps.host.calibrate.highlight_direction`), averaged over the spheres.
* Two mirror spheres of known radius and a perspective camera: near-light positions by triangulation
  (:func:`gpps.host.calibrate.triangulate_lights`), unless the reflected rays are nearly parallel.
* A matte sphere (circle or ``matte_mask.*``) or a grey card (rectangle or ``card_mask.*``): relative
  RGB intensities (mean 1); else ones.

:meth:`LightCalibration.write` writes ``light_directions.txt``, ``light_intensities.txt``,
``light_positions.txt`` (with positions), ``filenames.txt`` and ``calibration.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy import ndimage

from gpps._check import as_array, as_path, check_choice, check_number
from gpps.camera import Orthographic, Perspective, camera_from_K
from gpps.host.calibrate import (SphereFit, card_intensities, circle_points, disc_mask, find_outline, fit_sphere,
                                 highlight_direction, mask_outline, matte_intensities, triangulate_lights)
from gpps.io import read_K, save_json, save_txt
from gpps.io.capture import find_side_file, read_capture
from gpps.io.formats import Transfer, read_image_file

__all__ = ["LightCalibration", "calibrate_lights"]

Progress = Callable[[float, float, str], None]


@dataclass
class LightCalibration:
    """What :func:`calibrate_lights` found.

    Attributes:
        directions: (N, 3) unit directions toward the lights, gpps frame (x right, y up, z toward the
            camera), the mean over the mirror spheres.
        intensities: (N, 3) relative RGB intensities (mean 1); ones without a matte sphere or card.
        positions: (N, 3) light positions (scene units, gpps frame) from two spheres of known radius
            and a perspective camera; else None.
        filenames: the calibration images, in light order.
        spheres: the mirror spheres' fits (:class:`gpps.host.calibrate.SphereFit`).
        outlines: where each mirror sphere's outline came from ("given circle", "mask ...", "found in the images").
        intensities_from: what gave the intensities ("matte sphere", "grey card" or "none (ones): ...").
        camera: the camera (perspective from K, else orthographic).
        report: the ``calibration.json`` entries (``warnings`` added by :meth:`write`).
    """

    directions: np.ndarray
    intensities: np.ndarray
    positions: np.ndarray | None
    filenames: list[str]
    spheres: list[SphereFit]
    outlines: list[str]
    intensities_from: str
    camera: Orthographic | Perspective
    report: dict = field(default_factory=dict)

    def write(self, folder, *, warnings: list[str] | None = None) -> dict:
        """Write the light files and ``calibration.json`` into ``folder``.

        ``folder`` is written as is: give it a temporary folder of :func:`gpps.io.atomic_dir` so that
        the result appears complete or not at all.

        Args:
            folder: an existing folder.
            warnings: the warning messages to record in ``calibration.json`` (``"warnings"``).

        Returns:
            The report as written.
        """
        folder = Path(folder)
        self.report["warnings"] = list(warnings or [])
        save_txt(folder / "light_directions.txt", self.directions)
        save_txt(folder / "light_intensities.txt", self.intensities)
        if self.positions is not None:
            save_txt(folder / "light_positions.txt", self.positions)
        (folder / "filenames.txt").write_text("\n".join(self.filenames) + "\n")
        save_json(folder / "calibration.json", self.report)
        return self.report


def _mask_file(root: Path, stem: str, given) -> Path | None:
    """The mask image of ``stem``: ``given`` (must exist), else ``<stem>.*`` in ``root``, else None."""
    if given:
        p = Path(given)
        if not p.is_file():
            raise FileNotFoundError(f"{stem}: file not found: {p}")
        return p
    return find_side_file(root, stem)


def _read_mask(path, shape) -> np.ndarray:
    """(H, W) bool mask image (any channel > 0.5 of full scale), checked against ``shape``."""
    m, _ = read_image_file(path, transfer="linear")
    m = np.any(m > 0.5, axis=-1)
    if m.shape != shape:
        raise ValueError(f"{path}: expected a mask of shape {shape}, got {m.shape}")
    return m


def _numbers(name: str, value, k: int, form: str) -> np.ndarray:
    """``value`` as ``k`` finite floats; anything else is an error naming ``name`` and the ``form`` expected
    (what is not an array of real numbers: :func:`gpps._check.as_array`'s TypeError)."""
    a = as_array(name, value, dtype=np.float64, finite=False)
    if a.shape != (k,):
        raise ValueError(f"{name}: expected {form} ({k} numbers), got {value!r}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite numbers {form}, got {value!r}")
    return a


def _circle(name: str, value, shape) -> tuple[float, float, float]:
    """One outline ``(cx, cy, r)`` (pixels), checked: ``r > 0`` and the disc overlaps the (H, W) image."""
    cx, cy, r = (float(v) for v in _numbers(name, value, 3, "(cx, cy, r)"))
    if r <= 0:
        raise ValueError(f"{name}: expected a radius r > 0 (pixels), got {r:g}")
    h, w = shape
    if cx + r < 0 or cx - r > w - 1 or cy + r < 0 or cy - r > h - 1:
        raise ValueError(f"{name}: expected a circle on the {w} x {h} image, got ({cx:g}, {cy:g}, {r:g})")
    return cx, cy, r


def _circles(name: str, value, shape) -> list[tuple[float, float, float]] | None:
    """None, one circle ``(cx, cy, r)`` or a sequence of them, as a list of checked circles."""
    if value is None:
        return None
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{name}: expected a circle (cx, cy, r) or a sequence of them, got {value!r}")
    try:
        one = np.ndim(value) == 1 and len(value) == 3 and all(np.ndim(v) == 0 for v in value)
    except ValueError:  # (a ragged sequence: numpy cannot size it)
        one = False
    if one:
        return [_circle(name, value, shape)]
    try:
        items = list(value)
    except TypeError:
        raise TypeError(f"{name}: expected a circle (cx, cy, r) or a sequence of them, got {value!r}") from None
    if not items:
        raise ValueError(f"{name}: expected at least one circle (cx, cy, r), got an empty sequence")
    return [_circle(f"{name}[{i}]", c, shape) for i, c in enumerate(items)]


def _mirror_spheres(root: Path, images, camera, chrome, chrome_mask) -> tuple[list[SphereFit], list[str]]:
    """The mirror spheres' fits and where their outlines came from: given circles, a mask (one blob each,
    blobs under 20 % of the largest ignored), else found in the images."""
    h, w = images.shape[1:3]
    fits, sources = [], []
    mask_file = _mask_file(root, "chrome_mask", chrome_mask) if not chrome else None
    if chrome:
        for cx, cy, r in chrome:
            fits.append(fit_sphere(circle_points(cx, cy, r), camera))
            sources.append("given circle")
    elif mask_file is not None:
        lab, k = ndimage.label(_read_mask(mask_file, (h, w)))
        if k == 0:
            raise ValueError(f"{mask_file}: the mask is empty")
        sizes = np.bincount(lab.ravel())[1:]
        for idx in np.argsort(sizes)[::-1]:
            if sizes[idx] < 0.2 * sizes.max():
                break
            fits.append(fit_sphere(mask_outline(lab == idx + 1), camera))
            sources.append(f"mask {mask_file.name}")
    else:
        pts, _ = find_outline(images)
        fits.append(fit_sphere(pts, camera))
        sources.append("found in the images")
    return fits, sources


def _highlights(fits, images, filenames, min_contrast, progress) -> tuple[np.ndarray, np.ndarray, list[list[dict]]]:
    """Each sphere's highlight in each image: directions (S, N, 3) and centroids (S, N, 2) (NaN where
    none was found) and the per-image report rows."""
    n, h, w = images.shape[:3]
    dirs = np.full((len(fits), n, 3), np.nan)
    cents = np.full((len(fits), n, 2), np.nan)
    rows_per_sphere = []
    for s, f in enumerate(fits):
        region = disc_mask(f, (h, w), shrink=1.0)
        rows = []
        for k in range(n):
            l, info = highlight_direction(f, images[k], region, min_contrast=min_contrast)
            if l is not None:
                dirs[s, k] = l
                cents[s, k] = info["centroid"]
            rows.append({"file": filenames[k], **{kk: vv for kk, vv in info.items()}})
            if progress is not None:
                progress(s * n + k + 1, len(fits) * n, f"sphere {s + 1}: {filenames[k]}")
        rows_per_sphere.append(rows)
    return dirs, cents, rows_per_sphere


def _positions(fits, cents, radii, camera, report: dict) -> np.ndarray | None:
    """Near-light positions (N, 3) by triangulation from two spheres of known radius; None when that is not
    possible (the reason in ``report["triangulation"]``)."""
    if len(fits) < 2 or radii is None:
        return None
    if not camera.is_perspective:
        report["triangulation"] = {"note": "positions need a perspective camera (K.txt)"}
        return None
    positions, tri = triangulate_lights(fits, list(cents), radii)
    report["triangulation"] = tri
    ang = np.asarray(tri["ray_angle_deg"])
    if np.any(~np.isfinite(ang)) or np.median(ang) < 1.0:
        report["triangulation"]["note"] = ("the reflected rays are nearly parallel (median angle "
                                           f"{np.nanmedian(ang):.2f} deg): the lights are too far for positions; only directions written")
        return None
    return positions


def _intensities(root: Path, images, camera, directions, matte, card, card_normal, report: dict) -> tuple[np.ndarray, str]:
    """Relative RGB intensities (N, 3) from a matte sphere (circle or matte_mask.*) or a grey card (rectangle
    or card_mask.*), else ones; and what gave them."""
    n, h, w = images.shape[:3]
    matte_mask = _mask_file(root, "matte_mask", None) if matte is None else None
    card_mask = _mask_file(root, "card_mask", None) if card is None else None
    if matte is not None or matte_mask is not None:
        if matte is not None:
            mf = fit_sphere(circle_points(*matte), camera)
        else:
            mf = fit_sphere(mask_outline(_read_mask(matte_mask, (h, w))), camera)
        intens, info = matte_intensities(images, mf, directions)
        report["matte_sphere"] = {**mf.to_dict(), **info}
        return intens, "matte sphere"
    if card is not None or card_mask is not None:
        if card is not None:
            x0, y0, x1, y1 = card
            region = np.zeros((h, w), bool)
            region[min(y0, y1):max(y0, y1) + 1, min(x0, x1):max(x0, x1) + 1] = True
        else:
            region = _read_mask(card_mask, (h, w))
        intens, info = card_intensities(images, region, directions, card_normal)
        report["grey_card"] = {"normal": list(card_normal), **info}
        return intens, "grey card"
    return np.ones((n, 3)), "none (ones): no matte sphere or grey card"


def calibrate_lights(folder, *, chrome=None, chrome_mask=None, sphere_radius=None, matte=None, card=None,
                     card_normal=(0.0, 0.0, 1.0), K=None, transfer: Transfer = "auto", ambient: str | None = "auto",
                     min_contrast: float = 3.0, progress: Progress | None = None,
                     read_progress: Progress | None = None) -> LightCalibration:
    """Light directions (and intensities, positions) from a folder of images of spheres.

    Args:
        folder: one image per light of a mirror sphere (same order rules as :func:`gpps.io.read_capture`);
            optional ``K.txt``, ``chrome_mask.*``, ``matte_mask.*``, ``card_mask.*``.
        chrome: mirror sphere outlines as circles ``[(cx, cy, r), ...]`` or one ``(cx, cy, r)`` (pixels);
            None: ``chrome_mask``.
        chrome_mask: mask image of the mirror sphere(s), one blob each; None: ``chrome_mask.*`` in
            ``folder`` if present, else the outline is found in the images.
        sphere_radius: the mirror spheres' radii (scene units): one (a number or a 1-sequence) for all or
            one per sphere; with
            two spheres and a perspective camera, the lights' positions.
        matte: a matte sphere's outline ``(cx, cy, r)`` (pixels) for intensities; None: ``matte_mask.*``.
        card: a grey card rectangle ``(x0, y0, x1, y1)`` (pixels: columns x0..x1, rows y0..y1) for
            intensities; None: ``card_mask.*``.
        card_normal: the card's normal, gpps frame.
        K: (3, 3) intrinsics (pixels) or a text file of them; None: the folder's K.txt, else orthographic.
        transfer: the images' transfer curve (``"auto"``: sRGB decoded for JPEG only).
        ambient: ``"auto"`` (an image named ``*ambient*``), ``"none"`` or None (never), or a file: subtracted.
        min_contrast: a highlight's peak must exceed the sphere's median by this factor.
        progress: optional ``progress(done, total, message)`` over the highlights.
        read_progress: optional ``progress(done, total, message)`` while the images are read.

    Returns:
        :class:`LightCalibration`; :meth:`LightCalibration.write` writes it.

    Raises:
        FileNotFoundError: no folder, or a named file is missing.
        ValueError: no outline found, an empty mask, a wrong number of radii, an image without a highlight.
    """
    transfer = check_choice("transfer", transfer, Transfer)
    min_contrast = check_number("min_contrast", min_contrast, lo=0.0, lo_open=True)
    root = as_path("folder", folder)
    # no object here: read with the mask "none" (no mask file, no automatic mask)
    cap = read_capture(root, transfer=transfer, ambient=None if ambient == "none" else ambient,
                       mask="none", normalise=False, progress=read_progress)
    ds = cap.dataset
    images = ds.images
    n, h, w = images.shape[:3]
    if K is not None:
        K = read_K(K) if isinstance(K, (str, Path)) else np.asarray(K, np.float64)
    else:
        K = ds.K
    camera = camera_from_K(K) if K is not None else Orthographic()
    chrome = _circles("chrome", chrome, (h, w))
    if matte is not None:
        matte = _circle("matte", matte, (h, w))
    if card is not None:
        x0, y0, x1, y1 = (int(round(v)) for v in _numbers("card", card, 4, "(x0, y0, x1, y1)"))
        if max(x0, x1) < 0 or min(x0, x1) > w - 1 or max(y0, y1) < 0 or min(y0, y1) > h - 1:
            raise ValueError(f"card: expected a rectangle on the {w} x {h} image, got {tuple(card)}")
        card = (max(min(x0, x1), 0), max(min(y0, y1), 0), min(max(x0, x1), w - 1), min(max(y0, y1), h - 1))
    given_radius = sphere_radius
    if sphere_radius is not None and (isinstance(sphere_radius, (str, bytes)) or np.ndim(sphere_radius) == 0):
        sphere_radius = [sphere_radius]  # (one radius for every sphere)
    report = {"dir": str(folder), "images": n, "shape": [h, w], "camera": camera.kind, "filenames": ds.filenames,
              "formats": cap.formats, "ambient_subtracted": cap.ambient}
    fits, sources = _mirror_spheres(root, images, camera, chrome, chrome_mask)
    radii = None
    if sphere_radius is not None:
        try:
            radii = [float(r) for r in sphere_radius]
        except (TypeError, ValueError):
            raise TypeError(f"sphere_radius: expected a radius or one per sphere (scene units), got "
                            f"{given_radius!r}") from None
        radii = radii * (len(fits) if len(radii) == 1 else 1)
        if len(radii) != len(fits) or not all(np.isfinite(radii)) or min(radii) <= 0:
            raise ValueError(f"sphere_radius: expected one radius > 0 or one per sphere ({len(fits)}), got {sphere_radius}")
        for f, r in zip(fits, radii):
            f.radius = float(r)
    dirs, cents, rows = _highlights(fits, images, ds.filenames, min_contrast, progress)
    report["spheres"] = [{"outline": sources[s], **f.to_dict(), "highlights": rows[s]} for s, f in enumerate(fits)]
    found = np.all(np.isfinite(dirs), -1)
    missing = [ds.filenames[k] for k in range(n) if not found[:, k].any()]
    if missing:
        raise ValueError(f"images: no highlight on the mirror sphere in {', '.join(missing)} (light behind the sphere, off, or too weak: see min_contrast)")
    mean_dir = np.nanmean(dirs, 0)
    mean_dir /= np.linalg.norm(mean_dir, axis=1, keepdims=True)
    if len(fits) > 1:
        spread = [float(np.degrees(np.arccos(np.clip(dirs[0, k] @ dirs[1, k], -1, 1)))) for k in range(n)]
        report["direction_difference_between_spheres_deg"] = spread
    positions = _positions(fits, cents, radii, camera, report)
    intens, intens_src = _intensities(root, images, camera, mean_dir, matte, card, card_normal, report)
    report["intensities_from"] = intens_src
    report["light_directions"] = mean_dir
    report["light_intensities"] = intens
    if positions is not None:
        report["light_positions"] = positions
    return LightCalibration(directions=mean_dir, intensities=intens, positions=positions, filenames=list(ds.filenames),
                            spheres=fits, outlines=sources, intensities_from=intens_src, camera=camera, report=report)
