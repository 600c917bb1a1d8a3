"""Ray-cast ground truth with depth discontinuities, written independently of gpps.

Each scene is a few analytic surfaces (tilted planes, possibly clipped to an
image-space region, and spheres) in the gpps frame (x right, y up, z toward
the camera, scene at z < 0, depth d = -z).  Every pixel's ray meets the
surfaces; the nearest hit gives the pixel's depth, its exact normal and its
surface label (z-buffer), so occlusion boundaries are depth discontinuities
with no blending.  Pixel centres are at integer (column j, row i).

* perspective: ray ``r = ((j - cx) / f, -(i - cy) / f, -1)``, point ``d r``;
* orthographic (pixel size ``s``): point ``((j - cx) s, -(i - cy) s, -d)``.

Scenes (``SCENES``):

* ``steps``: a staircase of three tilted planar treads over a tilted back plane;
* ``overlap``: two spheres, one partly in front of the other, before a plane;
* ``figure``: one sphere (occluding rim all round) in front of a tilted plane;
* ``gaps``: two tilted slabs in front of a plane, separated by a gap 2 pixels
  wide and a 1-pixel slit, the plane seen through both;
* ``rims``: a sphere cut by a plane slab in front of it (occluding rims, and
  a surface split by an occluder into two pieces).

The scene scale is chosen so that the depth range is about a quarter of the
working distance (perspective) and the slopes are moderate away from rims.
"""

from __future__ import annotations

import numpy as np

F_PX = 1.2  # perspective focal length in image widths
Z0 = 10.0  # working distance (scene units)


def _rays(h, w, camera, s):
    ii, jj = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    cx, cy = (w - 1) / 2, (h - 1) / 2
    if camera == "perspective":
        f = F_PX * w
        d = np.stack([(jj - cx) / f, -(ii - cy) / f, -np.ones_like(jj)], -1)
        return None, d, f
    o = np.stack([(jj - cx) * s, -(ii - cy) * s, np.zeros_like(jj)], -1)
    return o, np.array([0.0, 0.0, -1.0]), None


def _hit_plane(o, d, n, c, region):
    """Depth of the plane ``n . X = c`` (n unit, n_z > 0) along the rays, inf outside ``region``."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    if o is None:  # perspective: X = t d, depth t
        t = c / (d @ n)
    else:  # orthographic: X = o + t (0, 0, -1)
        t = (o @ n - c) / n[2]
    t = np.where(region & (t > 0), t, np.inf)
    return t, np.broadcast_to(n, t.shape + (3,))


def _hit_sphere(o, d, C, R):
    """Nearest depth of the sphere |X - C| = R along the rays (inf where missed) and its normals."""
    C = np.asarray(C, float)
    if o is None:
        dd = np.broadcast_to(d, d.shape)
        a = np.sum(dd * dd, -1)
        b = -2 * dd @ C
        c = C @ C - R * R
        disc = b * b - 4 * a * c
        t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        X = t[..., None] * dd
    else:
        q = o - C
        # |q + t (0,0,-1)|^2 = R^2: t^2 - 2 t q_z + |q|^2 - R^2 = 0
        disc = q[..., 2] ** 2 - (np.sum(q * q, -1) - R * R)
        t = q[..., 2] - np.sqrt(np.maximum(disc, 0))
        X = o + t[..., None] * np.array([0.0, 0.0, -1.0])
    ok = (disc > 0) & (t > 0)
    nrm = (X - C) / R
    return np.where(ok, t, np.inf), nrm


def render_scene(name: str, size: int = 96, camera: str = "orthographic"):
    """Ray-cast one scene.

    Args:
        name: one of ``SCENES``.
        size: image height and width (pixels).
        camera: ``"orthographic"`` or ``"perspective"``.

    Returns:
        dict with ``depth`` (H, W) float64 (inf nowhere: every pixel hits the
        back plane), ``normals`` (H, W, 3) unit, ``labels`` (H, W) int (surface
        index), ``mask`` (H, W) bool (all True), ``K`` (3x3, perspective) or
        ``pixel_size`` (orthographic).
    """
    h = w = size
    # the field of view covers about [-L, L] x [-L, L] at the working distance
    L = Z0 / (2 * F_PX)
    s = 2 * L / w
    o, d, f = _rays(h, w, camera, s)
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    u, v = (jj + 0.5) / w, (ii + 0.5) / h  # image-space coordinates in (0, 1) for regions
    every = np.ones((h, w), bool)
    hits = []

    def plane(n, depth_at_centre, region=every):
        n = np.asarray(n, float) / np.linalg.norm(n)
        c = n @ np.array([0.0, 0.0, -depth_at_centre])
        hits.append(_hit_plane(o, d, n, c, region))

    def sphere(cx, cy, depth_c, R):
        hits.append(_hit_sphere(o, d, (cx * L, cy * L, -depth_c), R * L))

    back = Z0 + 0.35 * L
    if name == "steps":
        plane((0.15, 0.1, 1), back)
        for k in range(3):
            plane((-0.2 + 0.15 * k, 0.25, 1), back - 0.3 * L * (k + 1), (u > 0.2 + 0.22 * k) & (v > 0.15) & (v < 0.85))
    elif name == "overlap":
        plane((-0.1, 0.2, 1), back)
        sphere(-0.25, 0.1, Z0 - 0.1 * L, 0.45)
        sphere(0.3, -0.15, Z0 - 0.45 * L, 0.4)
    elif name == "figure":
        plane((0.2, -0.15, 1), back)
        sphere(0.05, 0.0, Z0 - 0.2 * L, 0.6)
    elif name == "gaps":
        plane((0.1, 0.1, 1), back)
        g = 2.0 / w  # a gap of 2 pixels, and a slit of 1
        plane((0.25, 0.1, 1), back - 0.5 * L, (u > 0.1) & (u < 0.5 - g / 2) & (v > 0.1) & (v < 0.9))
        plane((-0.2, 0.15, 1), back - 0.35 * L, (u > 0.5 + g / 2) & (u < 0.9) & (v > 0.1) & (v < 0.9)
              & ~((v > 0.5) & (v < 0.5 + 1.0 / h)))
    elif name == "rims":
        plane((0.0, 0.2, 1), back)
        sphere(0.0, 0.05, Z0 - 0.05 * L, 0.65)
        plane((0.1, 0.0, 1), Z0 - 0.9 * L, (u > 0.42) & (u < 0.58) & (v > 0.05) & (v < 0.95))
    else:
        raise ValueError(f"name: expected one of {SCENES}, got {name!r}")
    depth = np.full((h, w), np.inf)
    normals = np.zeros((h, w, 3))
    labels = -np.ones((h, w), int)
    for k, (t, nrm) in enumerate(hits):
        closer = t < depth
        depth = np.where(closer, t, depth)
        normals = np.where(closer[..., None], nrm, normals)
        labels = np.where(closer, k, labels)
    return _scene_dict(depth, normals, labels, camera, f, s, h, w)


SCENES = ("steps", "overlap", "figure", "gaps", "rims")


def _scene_dict(depth, normals, labels, camera, f, s, h, w):
    """The scene dict of the renders: unit normals, the mask of the hit pixels, the camera's ``K`` or pixel size."""
    out = dict(depth=depth, normals=normals / np.linalg.norm(normals, axis=-1, keepdims=True), labels=labels,
               mask=np.isfinite(depth))
    if camera == "perspective":
        out["K"] = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    else:
        out["pixel_size"] = s
    return out


def _hit_polytope(o, d, planes):
    """Entry depth of the convex polytope ``{X : n_k . X <= c_k}`` along the rays (inf where missed) and the
    outward normal of the face the ray enters through."""
    shape = d.shape[:-1] if o is None else o.shape[:-1]
    t_in = np.zeros(shape)
    t_out = np.full(shape, np.inf)
    face = -np.ones(shape, int)
    for k, (n, c) in enumerate(planes):
        nd = d @ n
        no = np.zeros(shape) if o is None else o @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - no) / nd
        enter = nd < 0
        face = np.where(enter & (t > t_in), k, face)
        t_in = np.where(enter, np.maximum(t_in, t), t_in)
        t_out = np.where(nd > 0, np.minimum(t_out, t), t_out)
        t_out = np.where((nd == 0) & (no > c), -np.inf, t_out)
    hit = (t_in <= t_out) & (face >= 0)
    normals = np.stack([planes[k][0] for k in range(len(planes))])[np.maximum(face, 0)]
    return np.where(hit, t_in, np.inf), normals, np.where(hit, face, -1)


def render_box(size: int = 96, camera: str = "orthographic"):
    """A tilted box standing on a tilted ground plane: creases that are continuous and creases that are steps.

    The box's top face (tilted) has two side faces that face the camera (left and lower in the image): they
    join the top to the ground by two folds each side (top-side, side-ground), and the two sides meet at a
    vertical edge, all continuous.  Its right and upper side faces turn away from the camera, so there the top
    face's edge partly occludes the ground behind it: a depth step of the box's height that coincides with the
    crease between the top's and the ground's normals.  The step's size is visible in the shading (the visible
    sides span it), so with one global offset / scale the whole map has one right answer; a stitch that forces
    continuity across the occluding edges, or one that also cuts the folds, misses it.

    Returns:
        as :func:`render_scene`; ``labels``: 0 ground, 1 top, 2 left side, 3 lower side (4, 5: the hidden sides,
        never seen).
    """
    h = w = size
    L = Z0 / (2 * F_PX)
    s = 2 * L / w
    o, d, f = _rays(h, w, camera, s)
    back = Z0 + 0.35 * L

    def unit(v):
        v = np.asarray(v, float)
        return v / np.linalg.norm(v)

    ng = unit((0.1, 0.1, 1.0))
    cg = ng @ np.array([0.0, 0.0, -back])
    nt = unit((-0.15, 0.2, 1.0))
    top_c = nt @ np.array([0.0, 0.0, -(back - 0.5 * L)])
    zt = -(back - 0.5 * L)
    planes = [
        (nt, top_c),                                             # 1: top
        (unit((-1.0, 0.0, 0.6)), unit((-1.0, 0.0, 0.6)) @ np.array([-0.45 * L, 0.0, zt])),  # 2: left, seen
        (unit((0.0, -1.0, 0.6)), unit((0.0, -1.0, 0.6)) @ np.array([0.0, -0.4 * L, zt])),   # 3: lower, seen
        (unit((1.0, 0.0, -0.25)), unit((1.0, 0.0, -0.25)) @ np.array([0.4 * L, 0.0, zt])),  # 4: right, hidden
        (unit((0.0, 1.0, -0.25)), unit((0.0, 1.0, -0.25)) @ np.array([0.0, 0.45 * L, zt])),  # 5: upper, hidden
        (-ng, -cg),                                              # the ground: the box stands on it
    ]
    tb, nb, fb = _hit_polytope(o, d, planes)
    tg, ngr = _hit_plane(o, d, ng, cg, np.ones((h, w), bool))
    closer = tb < tg
    depth = np.where(closer, tb, tg)
    normals = np.where(closer[..., None], nb, ngr)
    labels = np.where(closer, fb + 1, 0)
    return _scene_dict(depth, normals, labels, camera, f, s, h, w)


def surface_errors(est, gt, labels, mask, perspective: bool, margin: int = 0):
    """Per-surface-piece depth error after aligning each piece's one free parameter.

    A piece is a 4-connected region of one surface label.  Normals fix a piece's
    depth up to an offset (orthographic) or a scale (perspective) only when it is
    cut off from the rest by discontinuities, so each piece is aligned by its own
    median offset (``median(gt - est)``) or median scale (``median(gt / est)``).

    With ``margin > 0`` only pixels farther than ``margin`` pixels (chessboard
    distance) from another surface or the mask border are scored (the surface's
    interior), pieces with none left are skipped.

    Returns:
        list of dicts ``{label, pixels, mean, max}`` (mean and max absolute error,
        scene units) and the scene's depth range ``max - min`` of ``gt`` over ``mask``.
    """
    from scipy import ndimage

    rows = []
    for lab in np.unique(labels[mask]):
        comp, nc = ndimage.label((labels == lab) & mask)
        for c in range(1, nc + 1):
            m = comp == c
            if margin > 0:
                m = ndimage.binary_erosion(m, np.ones((3, 3), bool), iterations=margin)
                if not m.any():
                    continue
            e, g = est[m].astype(np.float64), gt[m]
            if perspective:
                a = e * np.median(g / e)
            else:
                a = e + np.median(g - e)
            err = np.abs(a - g)
            rows.append(dict(label=int(lab), pixels=int(m.sum()), mean=float(err.mean()), max=float(err.max())))
    rng = float(gt[mask].max() - gt[mask].min())
    return rows, rng
