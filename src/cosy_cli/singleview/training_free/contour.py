"""Contour alignment: a training-free RGB refinement that aligns the rendered outline with the image.

After verification (:mod:`~cosy_cli.singleview.training_free.verify`) each detection has hypotheses whose
renderings roughly cover the object; the outline of the best is typically a few pixels off and its
depth along the viewing ray off by a few percent. This step aligns the rendered outline with the
image, as edge-based trackers (RAPID and its successors) and sparse region-based trackers do:

1. render every pose into a square window around its detection box (``crop`` x ``crop`` px, the
   box grown by ``margin`` x its larger side on each side), with depth;
2. take up to ``points`` pixels of each silhouette's outline, their outward normals (the gradient
   of the smoothed silhouette), where the outline itself lies (sub-pixel: where the smoothed
   silhouette crosses 0.5) and their 3-D points on the model (back-projected rendered depth, kept
   in the object frame);
3. per outline point a 1-D search along its normal, ``search_px`` either side in 1 px steps
   (bilinear), with ``match``:

   - ``region``: colour histograms (``bins`` per channel) of the window inside the current
     silhouette and in a band (3 to ``band_px`` px) around it give each pixel a probability of
     being the object's colour; the boundary along the line that best splits it into object colour
     inside and background outside (a 1-D segmentation, plus a Gaussian prior of ``sigma_px`` on
     its offset) is the match. A point whose inside is not clearly more object-like than its
     outside (``min_contrast``: an occluded or low-contrast stretch) is dropped;
   - ``edge``: the strongest local maximum of the colour gradient along the normal (x the
     Gaussian prior) above ``min_edge`` grey levels per px; points without one are dropped;
   - ``both`` (default): the region match, moved to the strongest edge within ``snap_px`` when
     there is one (region for robustness, the edge for precision);
4. a few Levenberg-Marquardt steps (each taken only where it lowers that detection's cost) on the
   pose increment (rotation about the object origin in camera axes, translation in mm)
   minimising the robust (Cauchy, scale ``robust_px``) point-to-line distances of the projected
   model points to their matches; a pose with fewer than ``min_points`` matches is left as it is;
5. repeat ``iterations`` times, re-rendering, with the search range shrunk by ``shrink``.

:func:`refine_contour` aligns several hypotheses per detection (``cosy estimate`` aligns the best
two, ``CONTOUR_TOP``: the runner-up often is the right rotation) and applies the accept test:
every iterate is scored with the verification score (the same observation, prior and renderer as
the ranking); a detection's pose is replaced only by an iterate of strictly higher score than the
pose given (the best of them by score + ``w_fit`` x its fit: the fraction of outline points
within ``robust_px`` of their match). So the score never decreases, and a pose moves only where
the image says so.

Measured (benchmarks/bench_realdata_singleview.py --scenes all, visible GT boxes, one run side by
side on 2 cores shared with other jobs), local search -> this step instead: LM-O dev odd scenes
(settings chosen there) AR (MSSD, MSPD) 0.313 -> 0.376, rotations within 15 deg 0.280 -> 0.344,
median translation error 41 -> 32 mm; held-out even scenes 0.307 -> 0.372, 0.274 -> 0.336,
45 -> 33 mm; the step costs ~195 ms per image of 7.4 detections (~26 ms per detection, two
hypotheses each; the search ~280 ms). Multi-view (benchmarks/bench_realdata_multiview.py) on
these candidates: odd 0.325 -> 0.391, even 0.320 -> 0.365. Synthetic held-out scenes
(benchmarks/bench_estimate.py, RGB only): recall of ADD-S < 0.1 d 0.826 -> 0.917.

All per-point work is batched numpy over the poses of an image (no loop over points; small
per-detection image operations: warp, blur, distance transform); the renders are one call per
round. Lengths in mm; T_cam_obj 4x4 (OpenCV camera); K (3, 3) px; boxes x1, y1, x2, y2 px (pixel
edges); crop pixels have their centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...errors import CosyError
from ...geometry.camera import crop_affine, crop_intrinsics
from ...geometry.rotations import axis_angle_to_matrix
from ...lifetime import Closing
from .verify import window_crop


@dataclass
class ContourConf:
    """Settings of the contour alignment (chosen on the odd LM-O dev scenes, see
    benchmarks/bench_realdata_singleview.py)."""

    crop: int = 128              # window side, px
    margin: float = 0.2          # window = box grown by this x its larger side on each side
    max_faces: int = 3000        # rendered copies of at most this many faces
    iterations: int = 4          # render -> match -> Levenberg-Marquardt rounds
    gn_steps: int = 3            # Levenberg-Marquardt steps per round (matches fixed)
    points: int = 128            # outline points per detection (at most)
    search_px: float = 8.0       # crop px either side of the outline, first round
    shrink: float = 0.75         # search range factor per round
    sigma_px: float = 6.0        # Gaussian prior on the match offset, crop px
    min_edge: float = 12.0       # edge / both: grey levels per px: weaker image gradients are no (snap) match
    ambiguity: float = 0.0       # edge, > 0: drop points whose second-best maximum reaches this x the best
    robust_px: float = 2.0       # Cauchy scale of the residuals, crop px
    min_points: int = 12         # fewer matches: the detection is not moved
    damping: float = 1e-2        # Levenberg-Marquardt: initial lambda (x diag(H))
    max_rot_deg: float = 10.0    # step limits per Levenberg-Marquardt step
    max_shift_rel: float = 0.1   # translation step <= this x the object's distance
    blur: float = 1.0            # Gaussian blur (crop px) before the image gradient
    match: str = "both"          # region | edge | both: how the 1-D search finds the outline (docstring)
    bins: int = 16               # colour histogram bins per channel (region)
    band_px: float = 16.0        # region: background histogram from this far outside the silhouette
    min_contrast: float = 0.2    # region: inside mean p_fg - outside mean p_fg below this: no match
    snap_px: float = 2.0         # both: the region match snaps to the strongest edge within this
    accept_rounds: int = 2       # accept test: the iterates of this many last rounds are candidates (0: all)
    w_fit: float = 0.1           # accept test: among iterates that raise the score, pick by score + this x fit
    seed: int = 0


@dataclass
class ContourResult:
    """T (m, 4, 4) refined poses (mm), score (m,) their verification scores (>= the input's),
    moved (m,) bool whether the pose changed, matches (m,) outline points matched in the last
    round, times: seconds per part."""

    T: np.ndarray
    score: np.ndarray
    moved: np.ndarray
    matches: np.ndarray
    times: dict = field(default_factory=dict)


def windows(boxes: np.ndarray, margin: float) -> np.ndarray:
    """Square windows (m, 4) x1, y1, x2, y2 px around boxes (m, 4), grown by ``margin`` x the larger
    side on each side."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    side = np.maximum(np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]), 2.0) * (1.0 + 2.0 * margin)
    c = (b[:, :2] + b[:, 2:]) / 2
    return np.concatenate([c - side[:, None] / 2, c + side[:, None] / 2], 1)


def observe_windows(rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray, conf: ContourConf):
    """Per detection its window's crop intrinsics (m, 3, 3), the crop (m, S, S, 3) uint8 and its
    colour gradients gx, gy (m, S, S, 3) float32 grey levels per crop px (Sobel / 8 after a
    Gaussian blur of ``blur`` px)."""
    import cv2

    S = conf.crop
    win = windows(boxes, conf.margin)
    A = crop_affine(win, (S, S))
    Kc = crop_intrinsics(K, win, (S, S))
    src = np.asarray(rgb)
    crops = np.zeros((len(win), S, S, 3), np.uint8)
    gx = np.zeros((len(win), S, S, 3), np.float32)
    gy = np.zeros_like(gx)
    for i in range(len(win)):  # one warp per detection, of its window only (4K images)
        crops[i] = window_crop(src, win[i], A[i], S)
        crop = crops[i].astype(np.float32)
        if conf.blur > 0:
            crop = cv2.GaussianBlur(crop, (0, 0), conf.blur)
        gx[i] = cv2.Sobel(crop, cv2.CV_32F, 1, 0, ksize=3) * np.float32(0.125)
        gy[i] = cv2.Sobel(crop, cv2.CV_32F, 0, 1, ksize=3) * np.float32(0.125)
    return Kc, crops, gx, gy


def colour_posteriors(crops: np.ndarray, mask: np.ndarray, conf: ContourConf) -> np.ndarray:
    """Per pixel the probability (m, S, S, 1) float32 that its colour is the object's rather than the
    background's: colour histograms (``bins`` per channel) of the crop inside the rendered silhouette
    (2 px in from its outline) and in a band around it (3 to ``band_px`` px out), equal priors."""
    import cv2

    m, S = mask.shape[:2]
    nb = conf.bins ** 3
    q = (crops.astype(np.int64) * conf.bins) >> 8
    code = (q[..., 0] * conf.bins + q[..., 1]) * conf.bins + q[..., 2] + (np.arange(m) * nb)[:, None, None]
    fg = np.zeros((m, S, S), bool)
    bg = np.zeros((m, S, S), bool)
    for i in range(m):  # two distance transforms per detection
        mk = mask[i].astype(np.uint8)
        din = cv2.distanceTransform(mk, cv2.DIST_L2, 3)
        dout = cv2.distanceTransform(1 - mk, cv2.DIST_L2, 3)
        fg[i] = din > 2
        bg[i] = (dout > 3) & (dout <= conf.band_px)
    hf = np.bincount(code[fg], minlength=m * nb).reshape(m, nb).astype(np.float64)
    hb = np.bincount(code[bg], minlength=m * nb).reshape(m, nb).astype(np.float64)
    pf = (hf + 0.5) / (hf.sum(1, keepdims=True) + 0.5 * nb)
    pb = (hb + 0.5) / (hb.sum(1, keepdims=True) + 0.5 * nb)
    post = (pf / (pf + pb)).reshape(-1)
    return post[code].astype(np.float32)[..., None]


def _bilinear(img: np.ndarray, b: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Values of img (m, S, S, C) at image b (...) and float pixel x, y (...) (clamped), (..., C)."""
    S = img.shape[1]
    x = np.clip(x, 0, S - 1.001)
    y = np.clip(y, 0, S - 1.001)
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    fx = (x - x0)[..., None].astype(np.float32)
    fy = (y - y0)[..., None].astype(np.float32)
    flat = img.reshape(-1, img.shape[-1])
    i00 = (b * S + y0) * S + x0
    v00, v01 = flat[i00], flat[i00 + 1]
    v10, v11 = flat[i00 + S], flat[i00 + S + 1]
    return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy


def outline_points(mask: np.ndarray, depth: np.ndarray, Kc: np.ndarray, T: np.ndarray, n_points: int,
                   rng: np.random.Generator):
    """Outline pixels of the rendered silhouettes mask (m, S, S): up to ``n_points`` per image,
    spread evenly at random. Returns det (P,), pixel u (P, 2) (crop px, centres at integers),
    outward unit normals (P, 2), the model points X_obj (P, 3) mm under them and the offsets (P,)
    crop px along the normal from u to the outline (where the smoothed silhouette crosses 0.5)."""
    import cv2

    m, S = mask.shape[:2]
    pad = np.pad(mask, ((0, 0), (1, 1), (1, 1)))
    inner = pad[:, :-2, 1:-1] & pad[:, 2:, 1:-1] & pad[:, 1:-1, :-2] & pad[:, 1:-1, 2:]
    edge = mask & ~inner
    edge[:, [0, -1], :] = False  # the window's border is no outline
    edge[:, :, [0, -1]] = False
    f = np.flatnonzero(edge)
    b, rem = np.divmod(f, S * S)
    y, x = np.divmod(rem, S)
    # an even random subset per image: rank within its image after a random shuffle
    key = rng.random(len(f))
    order = np.lexsort((key, b))
    f, b, y, x = f[order], b[order], y[order], x[order]
    first = np.searchsorted(b, np.arange(m))
    rank = np.arange(len(f)) - first[b]
    keep = rank < n_points
    f, b, y, x = f[keep], b[keep], y[keep], x[keep]
    sm = mask.astype(np.float32)
    for i in range(m):  # one small blur per detection
        sm[i] = cv2.GaussianBlur(sm[i], (0, 0), 1.5, borderType=cv2.BORDER_CONSTANT)
    gxm = np.zeros_like(sm)
    gym = np.zeros_like(sm)
    gxm[:, :, 1:-1] = sm[:, :, 2:] - sm[:, :, :-2]
    gym[:, 1:-1] = sm[:, 2:] - sm[:, :-2]
    nrm = -np.stack([gxm.reshape(-1)[f], gym.reshape(-1)[f]], 1)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-6
    b, x, y, f, nrm, ln = b[ok], x[ok], y[ok], f[ok], nrm[ok], ln[ok]
    nrm = nrm / ln[:, None]
    # the outline itself lies outside the pixel's centre: where the smoothed mask crosses 0.5
    edge = np.clip((sm.reshape(-1)[f] - 0.5) / (0.5 * ln), 0.0, 1.5)
    z = depth.reshape(-1)[f].astype(np.float64)
    u = np.stack([x, y], 1).astype(np.float64)
    Kb = Kc[b]
    Xc = np.stack([(u[:, 0] - Kb[:, 0, 2]) / Kb[:, 0, 0] * z, (u[:, 1] - Kb[:, 1, 2]) / Kb[:, 1, 1] * z, z], 1)
    R, t = T[b, :3, :3], T[b, :3, 3]
    Xo = np.einsum("pji,pj->pi", R, Xc - t)  # R^T (X_cam - t)
    return b, u, nrm, Xo, edge


def match_along_normals(gx: np.ndarray, gy: np.ndarray, b: np.ndarray, u: np.ndarray, nrm: np.ndarray,
                        radius: float, conf: ContourConf):
    """1-D search per outline point along its normal: returns the signed offset (P,) crop px of
    its match and ok (P,) whether it has one (see the module docstring)."""
    L = int(np.ceil(radius))
    s = np.arange(-L, L + 1, dtype=np.float64)
    px = u[:, None, 0] + s[None] * nrm[:, None, 0]
    py = u[:, None, 1] + s[None] * nrm[:, None, 1]
    bb = np.broadcast_to(b[:, None], px.shape)
    gxs = _bilinear(gx, bb, px, py)  # (P, 2L+1, 3)
    gys = _bilinear(gy, bb, px, py)
    d = gxs * nrm[:, None, None, 0].astype(np.float32) + gys * nrm[:, None, None, 1].astype(np.float32)
    r = np.sqrt((d * d).sum(-1))  # (P, 2L+1) colour gradient along the normal
    S = gx.shape[1]
    inside = (px >= 0) & (px <= S - 1) & (py >= 0) & (py <= S - 1)
    r = np.where(inside, r, 0.0)
    rp = np.pad(r, ((0, 0), (1, 1)))
    peak = (r >= rp[:, :-2]) & (r > rp[:, 2:]) & (r >= conf.min_edge)
    w = np.where(peak, r * np.exp(-0.5 * (s / conf.sigma_px) ** 2)[None], 0.0)
    j = w.argmax(1)
    P = len(u)
    ok = w[np.arange(P), j] > 0
    if conf.ambiguity > 0:
        w2 = w.copy()
        w2[np.arange(P), j] = 0
        ok &= w2.max(1) < conf.ambiguity * w[np.arange(P), j]
    jm, jp = np.clip(j - 1, 0, 2 * L), np.clip(j + 1, 0, 2 * L)
    a, c0, c = r[np.arange(P), jm], r[np.arange(P), j], r[np.arange(P), jp]
    den = a - 2 * c0 + c
    sub = np.where((np.abs(den) > 1e-9) & (j > 0) & (j < 2 * L), 0.5 * (a - c) / np.where(den == 0, 1, den), 0.0)
    off = s[j] + np.clip(sub, -0.5, 0.5)
    return off, ok


def match_regions(post: np.ndarray, gx: np.ndarray, gy: np.ndarray, b: np.ndarray, u: np.ndarray,
                  nrm: np.ndarray, radius: float, conf: ContourConf):
    """1-D segmentation per outline point along its normal: the boundary position that best splits
    the samples into object colour (inside) and background colour (outside), with the Gaussian
    prior on its offset; with ``match`` "both" snapped to the strongest edge within ``snap_px``.
    Returns the signed offset (P,) crop px and ok (P,) (see the module docstring)."""
    L = int(np.ceil(radius))
    s = np.arange(-L, L + 1, dtype=np.float64)
    n = len(s)
    px = u[:, None, 0] + s[None] * nrm[:, None, 0]
    py = u[:, None, 1] + s[None] * nrm[:, None, 1]
    bb = np.broadcast_to(b[:, None], px.shape)
    p = np.clip(_bilinear(post, bb, px, py)[..., 0].astype(np.float64), 0.02, 0.98)  # (P, n)
    lf, lb = -np.log(p), -np.log1p(-p)
    cf = np.concatenate([np.zeros((len(u), 1)), np.cumsum(lf, 1)], 1)  # cf[:, k] = sum_{j<k} lf_j
    cb = np.concatenate([np.zeros((len(u), 1)), np.cumsum(lb, 1)], 1)
    k = np.arange(1, n)  # boundary between sample k-1 (inside) and k (outside)
    sb = (s[k - 1] + s[k]) / 2
    cost = cf[:, k] + (cb[:, n:n + 1] - cb[:, k]) + 0.5 * (sb / conf.sigma_px) ** 2
    j = cost.argmin(1)
    P = len(u)
    kk = k[j]
    n_in = kk.astype(np.float64)
    s_in = np.cumsum(p, 1)[np.arange(P), kk - 1]
    mean_in = s_in / n_in
    mean_out = (p.sum(1) - s_in) / (n - n_in)
    ok = (mean_in - mean_out) >= conf.min_contrast
    # sub-sample position: parabola through the costs around the minimum
    jm, jp = np.clip(j - 1, 0, n - 2), np.clip(j + 1, 0, n - 2)
    a, c0, c = cost[np.arange(P), jm], cost[np.arange(P), j], cost[np.arange(P), jp]
    den = a - 2 * c0 + c
    sub = np.where((den > 1e-9) & (j > 0) & (j < n - 2), 0.5 * (a - c) / np.where(den > 1e-9, den, 1.0), 0.0)
    off = sb[j] + np.clip(sub, -0.5, 0.5)
    if conf.match == "both":
        ns = 2 * int(np.ceil(conf.snap_px)) + 1
        so = np.round(off)[:, None] + np.arange(ns)[None] - (ns - 1) // 2
        qx = u[:, None, 0] + so * nrm[:, None, 0]
        qy = u[:, None, 1] + so * nrm[:, None, 1]
        bq = np.broadcast_to(b[:, None], qx.shape)
        d = _bilinear(gx, bq, qx, qy) * nrm[:, None, None, 0].astype(np.float32) \
            + _bilinear(gy, bq, qx, qy) * nrm[:, None, None, 1].astype(np.float32)
        r = np.sqrt((d * d).sum(-1))
        i = r.argmax(1)
        strong = r[np.arange(P), i] >= conf.min_edge
        # the first sample of largest response, no sub-pixel step (a parabola fit, half a pixel
        # outwards at a step edge, lost 0.013 AR on the odd LM-O scenes)
        off = np.where(strong, so[np.arange(P), i], off)
    return off, ok


def _residuals(T: np.ndarray, Kc: np.ndarray, b: np.ndarray, Xo: np.ndarray, target: np.ndarray, nrm: np.ndarray):
    """Point-to-line residuals (P,) crop px, the camera points X (P, 3) and X - t (P, 3)."""
    R, t = T[b, :3, :3], T[b, :3, 3]
    D = np.einsum("pij,pj->pi", R, Xo)
    X = D + t
    Z = np.maximum(X[:, 2], 1e-6)
    pu = np.stack([Kc[b, 0, 0] * X[:, 0] / Z + Kc[b, 0, 2], Kc[b, 1, 1] * X[:, 1] / Z + Kc[b, 1, 2]], 1)
    return np.einsum("pi,pi->p", nrm, pu - target), X, D


def gauss_newton(T: np.ndarray, Kc: np.ndarray, b: np.ndarray, Xo: np.ndarray, target: np.ndarray,
                 nrm: np.ndarray, conf: ContourConf) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt steps on the poses T (m, 4, 4) minimising the robust (Cauchy) sum of the
    point-to-line distances n . (project(T X_obj) - target) (crop px) of the points of each
    detection b (P,). A step is taken only where it lowers that detection's cost (else its damping
    grows); steps are bounded by ``max_rot_deg`` and ``max_shift_rel`` x the distance. Returns the
    new poses, the number of points (m,) used and how many of them end within ``robust_px``
    (0 for detections left as they were: fewer than ``min_points``)."""
    m = len(T)
    T = T.copy()
    npts = np.bincount(b, minlength=m)
    active = npts >= conf.min_points
    if not active.any():
        return T, npts, np.zeros(m, int)
    fx, fy = Kc[b, 0, 0], Kc[b, 1, 1]
    max_rot = np.radians(conf.max_rot_deg)
    c2 = conf.robust_px ** 2
    lam = np.full(m, conf.damping)
    onehot = (b[None] == np.arange(m)[:, None]).astype(np.float64)  # (m, P): sums per detection as a product

    def cost(res):
        return np.bincount(b, np.log1p(res * res / c2), minlength=m)

    res, X, D = _residuals(T, Kc, b, Xo, target, nrm)
    cur = cost(res)
    for _ in range(conf.gn_steps):
        Z = np.maximum(X[:, 2], 1e-6)
        # d res / dX = n^T d(pu)/dX
        Jn = np.stack([nrm[:, 0] * fx / Z, nrm[:, 1] * fy / Z,
                       -(nrm[:, 0] * fx * X[:, 0] + nrm[:, 1] * fy * X[:, 1]) / Z ** 2], 1)
        # X' = dR D + t + v: dX/dw = -[D]x (rotation about the object origin), dX/dv = I
        Jw = np.cross(D, Jn)  # Jn . (w x D) = w . (D x Jn)
        J = np.concatenate([Jw, Jn], 1)  # (P, 6)
        w = 1.0 / (1.0 + res * res / c2)  # IRLS weights of the Cauchy loss
        H = (onehot @ ((w[:, None, None] * J[:, :, None]) * J[:, None, :]).reshape(-1, 36)).reshape(m, 6, 6)
        g = onehot @ ((w * res)[:, None] * J)
        dg = np.einsum("mii->mi", H)
        A = H + (lam[:, None] * dg + 1e-9)[:, :, None] * np.eye(6)
        A[~active] = np.eye(6)
        g[~active] = 0
        delta = -np.linalg.solve(A, g[..., None])[..., 0]
        dw, dv = delta[:, :3], delta[:, 3:]
        ang = np.linalg.norm(dw, axis=1)
        dw = dw * np.minimum(1.0, max_rot / np.maximum(ang, 1e-12))[:, None]
        lim = conf.max_shift_rel * np.abs(T[:, 2, 3])
        ln = np.linalg.norm(dv, axis=1)
        dv = dv * np.minimum(1.0, lim / np.maximum(ln, 1e-12))[:, None]
        Tn = T.copy()
        Tn[:, :3, :3] = axis_angle_to_matrix(dw) @ T[:, :3, :3]
        Tn[:, :3, 3] = T[:, :3, 3] + dv
        res_n, X_n, D_n = _residuals(Tn, Kc, b, Xo, target, nrm)
        new = cost(res_n)
        ok = active & (new < cur)
        T[ok] = Tn[ok]
        cur = np.where(ok, new, cur)
        lam = np.where(ok, lam / 3.0, lam * 4.0)
        okp = ok[b]
        res = np.where(okp, res_n, res)
        X = np.where(okp[:, None], X_n, X)
        D = np.where(okp[:, None], D_n, D)
    inliers = np.bincount(b, np.abs(res) < conf.robust_px, minlength=m).astype(int)
    return T, npts, np.where(active, inliers, 0)


class ContourRefiner(Closing):
    """Contour alignment of poses (see the module docstring); one headless renderer of the
    objects' decimated copies at ``conf.crop`` px. Use as a context manager or call close().

    db: ObjectDatabase; conf: ContourConf."""

    def __init__(self, db, conf: ContourConf | None = None):
        self.db = db
        self.conf = conf or ContourConf()
        self._renderer = None

    @property
    def renderer(self):
        if self._renderer is None:
            from ...rendering import SceneRenderer, render_copy

            meshes = {o.obj_id: render_copy(o.mesh, self.conf.max_faces) for o in self.db}
            S = self.conf.crop
            self._renderer = SceneRenderer(meshes, S, S, znear=1.0, zfar=100_000.0, max_faces=None)
        return self._renderer

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def align(self, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray, obj_ids: np.ndarray, T: np.ndarray,
              det: np.ndarray | None = None):
        """The contour alignment's iterates, without an accept test: poses (iterations, n, 4, 4) after
        each round, the matches (iterations, n) of each round and its fit (iterations, n): the fraction
        of the outline points sampled that end within ``robust_px`` of their match. rgb (H, W, 3) uint8, K (3, 3),
        boxes (m, 4) px and obj_ids (m,) of m detections, T (n, 4, 4) mm poses, det (n,) the
        detection of each pose (default: n = m, one each)."""
        c = self.conf
        T = np.array(T, dtype=np.float64).reshape(-1, 4, 4)
        obj_ids = np.asarray(obj_ids).reshape(-1)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        det = np.arange(len(boxes)) if det is None else np.asarray(det, dtype=np.intp).reshape(-1)
        _check(rgb, K, boxes, obj_ids, T, self.db, det)
        if c.match not in ("region", "edge", "both"):
            raise CosyError(f"contour alignment: match must be region, edge or both, got {c.match!r}")
        n = len(T)
        if n == 0 or c.iterations <= 0:
            return np.zeros((0, n, 4, 4)), np.zeros((0, n), int), np.zeros((0, n))
        Kc, crops, gx, gy = observe_windows(rgb, K, boxes, c)
        if not np.array_equal(det, np.arange(len(boxes))):
            Kc, crops, gx, gy = Kc[det], crops[det], gx[det], gy[det]
        ids = [int(o) for o in obj_ids[det]]
        rng = np.random.default_rng(c.seed)
        S = c.crop
        out_T, out_n, out_f = [], [], []
        radius = c.search_px
        for _ in range(c.iterations):
            r = self.renderer.render_crops(Kc, ids, T, (S, S), with_rgb=False)
            mask = r.instance >= 0
            b, u, nrm, Xo, edge = outline_points(mask, r.depth, Kc, T, c.points, rng)
            n_outline = np.bincount(b, minlength=n)
            if c.match == "edge":
                off, ok = match_along_normals(gx, gy, b, u, nrm, radius, c)
            else:
                post = colour_posteriors(crops, mask, c)
                off, ok = match_regions(post, gx, gy, b, u, nrm, radius, c)
            b, u, nrm, Xo, off = b[ok], u[ok], nrm[ok], Xo[ok], (off - edge)[ok]
            target = u + off[:, None] * nrm  # where the model point u should go
            T, npts, inl = gauss_newton(T, Kc, b, Xo, target, nrm, c)
            out_T.append(T.copy())
            out_n.append(npts)
            out_f.append(inl / np.maximum(n_outline, 1))
            radius = max(2.0, radius * c.shrink)
        return np.stack(out_T), np.stack(out_n), np.stack(out_f)


def _check(rgb, K, boxes, obj_ids, T, db, det) -> None:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise CosyError(f"contour alignment: expected an RGB image (H, W, 3), got shape {rgb.shape}")
    if np.asarray(K).shape != (3, 3):
        raise CosyError(f"contour alignment: expected K of shape (3, 3), got {np.asarray(K).shape}")
    if len(boxes) != len(obj_ids) or len(det) != len(T):
        raise CosyError(f"contour alignment: {len(boxes)} boxes, {len(obj_ids)} object ids, {len(T)} poses and "
                        f"{len(det)} detection indices (expected a box and an id per detection, an index per pose)")
    if len(det) and (det.min() < 0 or det.max() >= len(boxes)):
        raise CosyError(f"contour alignment: detection indices must be in 0..{len(boxes) - 1}")
    if len(T) and not np.all(np.isfinite(T)):
        raise CosyError("contour alignment: poses must be finite")
    if len(T) and np.any(T[:, 2, 3] <= 0):
        raise CosyError("contour alignment: every object must be in front of the camera (t_z > 0 mm)")
    unknown = sorted(set(int(o) for o in obj_ids) - set(int(o) for o in db.obj_ids))
    if unknown:
        raise CosyError(f"contour alignment: obj_id {unknown[0]} is not in the models "
                        f"(known: {', '.join(map(str, db.obj_ids))})")


def refine_contour(refiner: ContourRefiner, verifier, obs: list, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray,
                   obj_ids: np.ndarray, T: np.ndarray, prior: np.ndarray | None = None,
                   init_score: np.ndarray | None = None) -> ContourResult:
    """Contour alignment with the accept test. T: (m, 4, 4) one pose per detection, or (m, k, 4, 4)
    k hypotheses per detection, best first (e.g. :meth:`~cosy_cli.singleview.training_free.verify.Verifier.rank`'s),
    all aligned. Each detection keeps the pose of best verification score among its first
    hypothesis as given and all the iterates (``verifier``: a
    :class:`~cosy_cli.singleview.training_free.verify.Verifier`; obs (m,) its crop observations; prior (m,) or
    (m, k) the hypotheses' template scores and init_score (m,) the first hypothesis' score, as in
    :meth:`~cosy_cli.singleview.training_free.verify.Verifier.refine`)."""
    import time

    T = np.array(T, dtype=np.float64)
    if T.ndim == 3:
        T = T[:, None]
    if T.ndim != 4 or T.shape[-2:] != (4, 4):
        raise CosyError(f"contour alignment: expected poses (m, 4, 4) or (m, k, 4, 4), got shape {T.shape}")
    m, k = T.shape[:2]
    obj_ids = np.asarray(obj_ids).reshape(-1)
    if len(obs) != m or len(obj_ids) != m:
        raise CosyError(f"contour alignment: {len(obs)} observations and {len(obj_ids)} object ids for {m} detections")
    if m == 0:
        return ContourResult(T[:, 0], np.zeros(0), np.zeros(0, bool), np.zeros(0, int))
    pr = None
    if prior is not None:
        pr = np.asarray(prior, dtype=np.float64).reshape(m, -1)
        pr = np.broadcast_to(pr[:, :1], (m, k)) if pr.shape[1] == 1 else pr[:, :k]
    det = np.arange(m)
    ok_h = np.all(np.isfinite(T.reshape(m, k, -1)), -1) & (T[..., 2, 3] > 0)
    ok_h[:, 0] = True  # the first is checked (must be a pose)
    if pr is not None:
        ok_h &= np.isfinite(pr) | (np.arange(k) == 0)[None]
    hd, hk = np.nonzero(ok_h)
    t0 = time.perf_counter()
    iters, nmatch, fit = refiner.align(rgb, K, boxes, obj_ids, T[hd, hk], det=hd)
    t1 = time.perf_counter()
    T0 = T[:, 0]
    if init_score is None:
        s0 = verifier.score(obs, det, obj_ids, T0, None if pr is None else pr[:, 0])
    else:
        s0 = np.asarray(init_score, dtype=np.float64).reshape(-1)
    nm_last = nmatch[-1] if len(nmatch) else np.zeros(len(hd), int)
    if refiner.conf.accept_rounds > 0:  # only the last rounds' iterates are candidates
        iters, fit = iters[-refiner.conf.accept_rounds:], fit[-refiner.conf.accept_rounds:]
    it = len(iters)
    Tout, sout, moved, last = T0.copy(), s0.copy(), np.zeros(m, bool), np.zeros(m, int)
    if it:
        cand = iters.reshape(-1, 4, 4)  # (it * n): round-major
        cd = np.tile(hd, it)
        sc = verifier.score(obs, cd, obj_ids[cd], cand, None if pr is None else np.tile(pr[hd, hk], it))
        # per detection the best of the iterates that beat the input's score (by score + w_fit x fit)
        key = np.where(sc > s0[cd], sc + refiner.conf.w_fit * fit.reshape(-1), -np.inf)
        order = np.lexsort((-key, cd))
        first = order[np.searchsorted(cd[order], det)]
        better = np.isfinite(key[first])
        Tout[better] = cand[first[better]]
        sout[better] = sc[first[better]]
        moved = better
        last = np.zeros(m, int)
        np.maximum.at(last, hd, nm_last)
    return ContourResult(Tout, sout, moved, last, {"align": t1 - t0, "accept": time.perf_counter() - t1})
