"""Verification of pose hypotheses by rendering, and a training-free RGB refinement.

Template retrieval (:mod:`~cosy_cli.singleview.training_free.templates`) ranks views by sparse shape gradients
only; in a cluttered, occluded real image its best template is often a wrong rotation while a
right one is among its top few dozen. This module renders hypotheses with the mesh's own colours
(vertex colours or texture; flat grey for bare meshes) into the detection's crop camera and
scores them against the image, and can refine the best by a local search on the same score
(``rgb_refine: search``; the default RGB refinement is the contour alignment of
:mod:`~cosy_cli.singleview.training_free.contour`, which uses this score as its accept test).

Per detection (:class:`CropObservation`, computed once): a square window around the detection
box, grown by ``margin`` x its larger side on each side, resampled to ``crop`` x ``crop`` px; its
crop intrinsics (:func:`~cosy_cli.geometry.camera.crop_intrinsics`); the image's colour edges
(Canny on the crop, the largest channel response) and their distance transform; a colour model
of the background (the crop's pixels outside the detection box).

Per hypothesis (:meth:`Verifier.score`, batched: one atlas render for all hypotheses of an
image), each term in [0, 1]:

- ``edge``: the rendered silhouette's outline and the render's own colour edges against the
  image's edges: mean of max(0, 1 - d / ``edge_tol``) over the rendered edge pixels, d the
  distance (crop px) to the nearest image edge. Occluded outline pixels find no edge: a partly
  hidden object loses a part of this term, not its rank (every hypothesis of that detection loses
  the same occluded part).
- ``colour``: inside the rendered silhouette, agreement of the image colour with the rendered
  colour after one brightness gain per hypothesis (least squares): mean of max(0, 1 - |I - g R| /
  ``colour_tol``). Shape-only meshes (no colours) give this term no weight.
- ``region``: how well the silhouette separates object from background pixels within the box:
  with p(x) the probability that pixel x is not background (its colour is rare outside the box),
  the mean of p inside the silhouette (within the box) minus its mean outside, mapped to [0, 1].
- ``box``: the rendered silhouette's box against the detection box: the fraction of the detection
  box covered by the silhouette's box (a visible box lies inside the whole object's), times
  min(1, area(detection box) / area(silhouette box)) ^ ``box_excess`` (an occluded object's
  silhouette box may be larger than its visible box: a soft penalty only).

- ``mask`` (only for detections that come with a segmentation, e.g. BOP's default detections):
  the IoU of the rendered silhouette with the segmentation in the crop. Weight ``w_mask`` 2,
  chosen with GT visible masks on the odd LM-O scenes and YCB-V frames 1-5 (1 and 2 alike on LM-O,
  2 better on YCB-V; replacing the region term's colour model by the mask instead did as well on
  LM-O and lost 0.19 BOP19 AR on YCB-V; restricting ICP to the depth inside the mask lost 0.14 on
  YCB-V, +0.001 on the proxy RGB-D LM-O: ICP keeps the box).

score = sum of the weighted terms / sum of the weights used.

Cost (2-core CPU, llvmpipe). Rendering dominates: llvmpipe's triangle setup grows with the faces
drawn, so every render uses a decimated copy, lit per vertex (``shading``, see
:class:`~cosy_cli.rendering.SceneRenderer`), read back as one RGBA attachment (the mask is its
alpha). The terms are computed only at the rendered edge and silhouette pixels, gathered by flat
index (colours as (3, P) rows, the silhouette's box from its sorted pixel list).
:meth:`Verifier.rank` scores all hypotheses with a coarse copy (``rank_faces``, 600) and re-scores
only each detection's best ``rank_keep`` (8) with the ``max_faces`` (3000) copy; these stay ahead
in the ranking. On the odd LM-O dev scenes the cascade (then 1000 faces), 48 instead of 64
hypotheses and 3 x 16 instead of 4 x 24 search samples together cost 0.006 AR (MSSD, MSPD)
(0.317 -> 0.311) for 0.54x the time; the 600-face first pass then kept the AR (odd 0.312, even
0.304 with the search, 0.365 with the contour alignment). With the rendering and scoring
speed-ups the chain takes ~0.65x the time of the same settings before them (side by side:
benchmarks/bench_stage1_speed.py; each setting's cost: benchmarks/bench_realdata_singleview.py
--sweep).

Refinement (:meth:`Verifier.refine`): a local random search in the crop's camera. Each round
perturbs the current best pose of every detection ``samples`` times: rotation by a random axis x
an angle ~ N(0, sigma_rot), image-plane shift of the object origin ~ N(0, sigma_px) crop px and a
relative depth change ~ N(0, sigma_depth) (default 0: in a 64 px crop the depth barely changes the
score, and searching it let the pose drift along the ray on a synthetic test); scores all of
them in one render and keeps a sample only when it beats the current best. The spreads shrink
by ``shrink`` per round. The score never decreases, and the pose cannot leave the neighbourhood
of the input by more than the sum of the spreads (it does not wander). With depth (ICP) the
cascade runs too (since 2026-12-02; before, every hypothesis was scored with the full copies): on
the proxy RGB-D LM-O odd scenes 3 of 282 picks changed (BOP19 AR 0.720 -> 0.718; YCB-V frames 1-5
0.554 -> 0.558, synthetic dev scenes 0.937 -> 0.939) for 0.53x the verification time, 0.84x the
chain's (``bench_stage1_speed.py --data lmo-depth --variants new-nocascade,new``): the ICP and the
depth pick, not the verification order, decide there. Held out: proxy even scenes 0.722 -> 0.719,
YCB-V frames 6-10 0.460 -> 0.438 (the mug in one frame), synthetic held-out scenes unchanged.

Lengths in mm; T_cam_obj 4x4 (OpenCV camera); K (3, 3) px; boxes x1, y1, x2, y2 px (pixel edges).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ...geometry.camera import crop_affine, crop_intrinsics
from ...geometry.rotations import axis_angle_to_matrix
from ...lifetime import Closing


@dataclass
class VerifyConf:
    """Settings of verification and RGB refinement (chosen on the odd LM-O dev scenes, see
    benchmarks/bench_realdata_singleview.py)."""

    crop: int = 64                 # crop side, px
    margin: float = 0.2            # window = detection box grown by this x its larger side on each side
    max_faces: int = 3000          # rendering uses a decimated copy of at most this many faces
    rank_faces: int = 600          # > 0: rank() first scores all hypotheses with a coarser copy (this many faces) ...
    rank_keep: int = 8             # ... and re-scores only each detection's best this many with max_faces
    edge_tol: float = 2.5          # crop px: an edge pixel this far from an image edge scores 0
    colour_tol: float = 0.25       # RGB distance (0..1 per channel) at which a pixel scores 0
    w_edge: float = 0.0            # chamfer to Canny edges (0: the oriented term alone was better)
    w_colour: float = 1.0
    w_region: float = 2.0
    w_box: float = 0.5
    w_prior: float = 1.0           # the hypothesis' own score (template matching), when given
    box_excess: float = 1.0
    canny: tuple = (40, 100)       # Canny thresholds (grey levels)
    min_gradient: float = 40.0     # Sobel magnitude (grey levels) of an image gradient in the oriented term
    w_orient: float = 1.0
    w_mask: float = 2.0            # the silhouette's IoU with the detection's segmentation, where it has one
    scorer_scope: str = "rank"     # with a learned scorer: "rank": it orders only rank()'s best scorer_keep per
                                   # detection, the rest stays training-free; "all": its prediction is every score
    scorer_keep: int = 16          # scope "rank": hypotheses per detection the scorer orders (best by the first pass)
    # refinement
    rounds: int = 3
    samples: int = 16
    sigma_rot_deg: float = 10.0
    sigma_px: float = 2.0          # crop px
    sigma_depth: float = 0.0       # relative; 0: the depth stays the box's (barely observable in a small crop)
    shrink: float = 0.6
    refine_faces: int = 0          # > 0: the search renders copies of at most this many faces (0: max_faces; 1500:
                                   # ~0.6x the search's time, rotations within 15 deg -0.007 on LM-O odd and even)
    seed: int = 0
    shading: str = "vertex"        # renders lit per vertex ("pixel": per fragment; the same colours to 1 grey level)


def _split_flat(i: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(i // size, i % size) of non-negative int64 indices (shifts when size is a power of two)."""
    if size & (size - 1) == 0:
        k = size.bit_length() - 1
        return i >> k, i & (size - 1)
    q = i // size
    return q, i - q * size


class _Segments:
    """Sums per hypothesis of values listed hypothesis by hypothesis (``counts`` (n,) values each, in
    order): one sequential float64 pass (np.add.reduceat) instead of a scattered bincount."""

    def __init__(self, counts: np.ndarray):
        counts = np.asarray(counts, dtype=np.int64)
        self.n = len(counts)
        self.nonempty = counts > 0
        end = np.cumsum(counts)
        self.first = (end - counts)[self.nonempty]
        self.last = end[self.nonempty] - 1

    def __call__(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros(self.n)
        if len(self.first):
            out[self.nonempty] = np.add.reduceat(values, self.first, dtype=np.float64)
        return out


_TAN_BIN_EDGES = np.tan((np.arange(4) + 0.5) * np.pi / 8).astype(np.float32)  # 11.25, 33.75, 56.25, 78.75 deg


def _orientation_bins_of(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """orientation_bins(arctan2(gy, gx)) (:func:`~cosy_cli.singleview.training_free.templates.orientation_bins`:
    bins 0..7 over 0..180 deg, bin b centred on b x 22.5 deg) by comparisons of |gy| with tan x |gx|
    instead of an arctangent (the same bins but at exact ties)."""
    a, b = np.abs(gx), np.abs(gy)
    k = (b > _TAN_BIN_EDGES[0] * a).astype(np.intp)  # bin of the angle folded into [0, 90] deg
    for t in _TAN_BIN_EDGES[1:]:
        k += b > t * a
    return np.where((gx < 0) != (gy < 0), (8 - k) & 7, k)  # opposite signs: 180 deg - the folded angle


@dataclass
class CropObservation:
    """What the scores need of one detection's image window (see the module docstring)."""

    K: np.ndarray          # (3, 3) crop intrinsics
    window: np.ndarray     # (4,) x1, y1, x2, y2 of the window in the image, px
    box_crop: np.ndarray   # (4,) the detection box in crop px (pixel edges)
    rgb: np.ndarray        # (S, S, 3) float32 0..1
    dist: np.ndarray       # (S, S) float32 distance (crop px) to the nearest image edge
    not_bg: np.ndarray     # (S, S) float32 in [0, 1]: 1 - how common the pixel's colour is outside the box
    in_box: np.ndarray     # (S, S) bool
    resp: np.ndarray       # (8, S, S) float32 orientation responses (LINEMOD-like, spread 3x3)
    grey: bool = False     # a grey image (three equal channels): colours are compared as grey levels
    seg: np.ndarray | None = None  # (S, S) float32 in [0, 1]: the detection's segmentation in the crop, if any
    # what it was made of (image, K, box, mask; references, not copies): a scorer trained on another crop
    # side observes the same detection again (Verifier.score)
    source: tuple | None = field(default=None, repr=False, compare=False)
    others: dict = field(default_factory=dict, repr=False, compare=False)  # crop side -> that observation


def window_crop(src: np.ndarray, win: np.ndarray, A: np.ndarray, S: int) -> np.ndarray:
    """The (S, S) crop of the square window ``win`` (x1, y1, x2, y2 px) of the image ``src`` by the
    affine map ``A`` (:func:`~cosy_cli.geometry.camera.crop_affine`), anti-aliased when the window
    shrinks (scale < 0.7: a Gaussian blur of 0.5 / scale px). Only the window and a margin beyond
    the blur's kernel are blurred and warped (no copy of the whole image per detection: a 4K frame
    is 25 MB): the same pixels as the whole image blurred, where the warp samples."""
    import cv2

    scale = S / (win[2] - win[0])
    if scale < 0.7:
        sigma = 0.5 / scale
        r = int(math.ceil(4 * sigma)) + 2
        H, W = src.shape[:2]
        X0, Y0 = max(int(math.floor(win[0])) - r, 0), max(int(math.floor(win[1])) - r, 0)
        X1, Y1 = min(int(math.ceil(win[2])) + r, W), min(int(math.ceil(win[3])) + r, H)
        if X1 > X0 and Y1 > Y0 and (X1 - X0 < W or Y1 - Y0 < H):
            src = cv2.GaussianBlur(np.ascontiguousarray(src[Y0:Y1, X0:X1]), (0, 0), sigma)
            A = A + np.array([[0.0, 0.0, A[0, 0] * X0 + A[0, 1] * Y0], [0.0, 0.0, A[1, 0] * X0 + A[1, 1] * Y0]])
        else:
            src = cv2.GaussianBlur(src, (0, 0), sigma)
    return cv2.warpAffine(src, A, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def observe(rgb: np.ndarray, K: np.ndarray, box: np.ndarray, conf: VerifyConf,
            mask: np.ndarray | None = None) -> CropObservation:
    """The crop observation of one detection (box x1, y1, x2, y2 px); with the detection's
    segmentation ``mask`` (H, W) bool, also that mask in the crop (``seg``, anti-aliased to [0, 1])
    for the ``mask`` term."""
    import cv2

    S = conf.crop
    x1, y1, x2, y2 = (float(v) for v in box)
    side = max(x2 - x1, y2 - y1, 2.0) * (1.0 + 2.0 * conf.margin)
    cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
    win = np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])
    A = crop_affine(win, (S, S))
    Kc = crop_intrinsics(K, win, (S, S))
    crop = window_crop(np.asarray(rgb), win, A, S)
    scale = S / side
    edges = np.zeros((S, S), np.uint8)
    for c in range(3):
        edges |= cv2.Canny(crop[..., c], *conf.canny, L2gradient=True)
    dist = cv2.distanceTransform(np.where(edges > 0, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
    bx = np.array([(x1 - win[0]) * scale, (y1 - win[1]) * scale, (x2 - win[0]) * scale, (y2 - win[1]) * scale])
    yy, xx = np.mgrid[0:S, 0:S] + 0.5
    in_box = (xx >= bx[0]) & (xx <= bx[2]) & (yy >= bx[1]) & (yy <= bx[3])
    # background colour model: 8x8x8 RGB histogram of the window outside the box
    q = (crop // 32).astype(np.int64)
    code = (q[..., 0] * 8 + q[..., 1]) * 8 + q[..., 2]
    hb = np.bincount(code[~in_box], minlength=512).astype(np.float64)
    hb = np.convolve(hb, [0.25, 0.5, 0.25], mode="same")  # a little smoothing (along blue)
    hf = np.bincount(code[in_box], minlength=512).astype(np.float64)
    pb = hb / max(hb.sum(), 1.0)
    pf = hf / max(hf.sum(), 1.0)
    not_bg = (pf / np.maximum(pf + pb, 1e-12))[code].astype(np.float32)
    seg = None
    if mask is not None:
        seg = np.clip(window_crop(np.asarray(mask, np.float32), win, A, S), 0.0, 1.0).astype(np.float32)
    # oriented responses: per pixel the colour channel of largest gradient, quantised, spread 3x3
    from .templates import _LUT, orientation_bins, sobel

    gx, gy = sobel(np.moveaxis(crop.astype(np.float32), -1, 0))
    mag2 = gx * gx + gy * gy
    ch = np.argmax(mag2, axis=0)[None]
    gx, gy = np.take_along_axis(gx, ch, 0)[0], np.take_along_axis(gy, ch, 0)[0]
    strong = np.take_along_axis(mag2, ch, 0)[0] >= conf.min_gradient ** 2
    bits = np.where(strong, np.left_shift(1, orientation_bins(np.arctan2(gy, gx))), 0).astype(np.uint8)
    p = np.pad(bits, 1)
    spread = np.zeros((S, S), np.uint8)
    for dy in range(3):
        for dx in range(3):
            spread |= p[dy:dy + S, dx:dx + S]
    resp = _LUT[:, spread].astype(np.float32) / 255.0
    grey = bool(np.array_equal(crop[..., 0], crop[..., 1]) and np.array_equal(crop[..., 1], crop[..., 2]))
    return CropObservation(Kc, win, bx, crop.astype(np.float32) / 255.0, dist.astype(np.float32), not_bg, in_box,
                           resp, grey, seg, source=(rgb, K, box, mask))


@dataclass
class RankedHypotheses:
    """Hypotheses of N detections re-ranked by :meth:`Verifier.rank`, best first: T_cam_obj
    (N, k, 4, 4) mm, score (N, k) verification scores (-1 for missing hypotheses; with the cascade
    (``rank_faces``), those after the first ``rank_keep`` are the coarse copies' scores), prior (N, k)
    their template scores, obs the N crop observations (for :meth:`Verifier.refine`)."""

    T_cam_obj: np.ndarray
    score: np.ndarray
    prior: np.ndarray
    obs: list



class Verifier(Closing):
    """Scores and refines hypotheses by rendering; one headless renderer over decimated meshes.

    db: ObjectDatabase; conf: VerifyConf. Use as a context manager or call close()."""

    def __init__(self, db, conf: VerifyConf | None = None, scorer=None):
        self.db = db
        self.conf = conf or VerifyConf()
        # a learned scorer (:class:`~cosy_cli.singleview.scorer.runtime.OnnxScorer`): its prediction
        # replaces the weighted sum of the terms (see :mod:`cosy_cli.singleview.scorer`)
        self.scorer = scorer
        if scorer is not None and scorer.margin != self.conf.margin:
            raise ValueError(f"the scorer was trained on crops with margin {scorer.margin}, verification uses "
                             f"margin {self.conf.margin}")
        # a scorer trained on another crop side scores through a verifier of its side (its own renders and
        # terms, the detections observed again at that side); the training-free scores stay at conf.crop
        self._learned = None
        if scorer is not None and scorer.crop != self.conf.crop:
            self._learned = Verifier(db, replace(self.conf, crop=int(scorer.crop)), scorer=scorer)
        self._renderers: dict[int, object] = {}
        self._coloured: dict[int, bool] = {}
        self._coarse: dict[int, bool] = {}  # obj_id -> rank() renders a coarser copy of it

    def _renderer_with(self, max_faces: int):
        if max_faces not in self._renderers:
            from ...rendering import SceneRenderer, render_copy

            meshes = {}
            for o in self.db:
                m = o.mesh
                self._coloured[o.obj_id] = bool(getattr(m.visual, "defined", False))
                # a copy less than half the size of the max_faces one saves little: the latter then
                coarser = len(m.faces) > 2 * max_faces and max_faces < self.conf.max_faces
                if max_faces == self.conf.rank_faces:
                    self._coarse[o.obj_id] = coarser
                meshes[o.obj_id] = render_copy(m, max_faces if coarser else self.conf.max_faces)
            S = self.conf.crop
            self._renderers[max_faces] = SceneRenderer(meshes, S, S, znear=1.0, zfar=100_000.0, max_faces=None,
                                                       shading=self.conf.shading)
        return self._renderers[max_faces]

    @property
    def renderer(self):
        """The renderer of the decimated copies with at most ``max_faces`` faces (made on first use)."""
        return self._renderer_with(self.conf.max_faces)

    def close(self):
        for r in self._renderers.values():
            r.close()
        self._renderers = {}
        if self._learned is not None:
            self._learned.close()

    def _observed_at(self, obs: list[CropObservation], S: int) -> list[CropObservation]:
        """The observations ``obs`` made again at crop side ``S`` (kept on each, made once)."""
        out = []
        for o in obs:
            if S not in o.others:
                if o.source is None:
                    raise ValueError(f"an observation without its source image cannot be observed at {S} px")
                rgb, K, box, mask = o.source
                o.others[S] = observe(rgb, K, box, replace(self.conf, crop=S), mask)
            out.append(o.others[S])
        return out

    # ------------------------------------------------------------------ scoring

    def score(self, obs: list[CropObservation], det: np.ndarray, obj_ids: np.ndarray, T: np.ndarray,
              prior: np.ndarray | None = None, terms: bool = False, max_faces: int | None = None,
              inputs: bool = False, learned: bool | None = None):
        """Scores (n,) of hypotheses T (n, 4, 4) of detections ``det`` (n,) indices into ``obs``,
        objects obj_ids (n,); ``prior`` (n,) in [0, 1]: the hypotheses' own scores (template
        matching), weighted by ``w_prior``. With ``terms``, also a dict of the per-term (n,) arrays.
        max_faces: render copies of at most this many faces (default ``conf.max_faces``).
        With a learned ``scorer``, the scores are its predictions (the terms still returned are
        the training-free ones, "total" their weighted sum) where ``learned`` says so (None: where
        ``conf.scorer_scope`` is "all"). ``inputs``: instead of the scores, a
        dict of the scorer's raw inputs (renders "rgba" (n, S, S, 4) uint8, "gain" (n,), "terms"
        (n, T), "ridx" (n,) the observation of each, "udet" the observations used, "total" the
        training-free scores), what training stores.

        One render of all n hypotheses; the terms are computed on the rendered pixels only (edge
        pixels, silhouette pixels), gathered as flat index arrays."""
        c = self.conf
        if learned is None:
            learned = c.scorer_scope == "all"
        if learned and self._learned is not None and not inputs:
            # only the obs that are used are observed again
            used = np.unique(np.asarray(det, np.int64))
            again = dict(zip(used.tolist(), self._observed_at([obs[d] for d in used], self._learned.conf.crop)))
            obs2 = [again.get(d) for d in range(len(obs))]
            return self._learned.score(obs2, det, obj_ids, T, prior, terms=terms, max_faces=max_faces, learned=True)
        S = c.crop
        SS = S * S
        n = len(T)
        if n == 0:
            return (np.zeros(0), {}) if terms else np.zeros(0)
        det = np.asarray(det)
        udet, ridx = np.unique(det, return_inverse=True)  # the observations used, and each hypothesis' row
        U = len(udet)
        Ks = np.stack([obs[d].K for d in udet])[ridx]
        ren = self.renderer if max_faces is None else self._renderer_with(int(max_faces))
        out = ren.render_crops(Ks, [int(i) for i in obj_ids], T, (S, S), with_depth=False, with_instance=False)
        # one 32-bit word per pixel (RGBA, alpha 255 on the object): 0 exactly off the silhouette
        px = out.rgba.reshape(n * SS, 4).view(np.uint32).reshape(-1)
        mask = px != 0
        fm = np.flatnonzero(mask)  # flat indices b * S * S + y * S + x of the silhouette pixels (sorted)
        mb, mpix = _split_flat(fm, SS)
        area = np.bincount(mb, minlength=n).astype(np.float64)
        has = area > 0
        sums = _Segments(area)  # per-hypothesis sums over the silhouette pixels (contiguous runs of fm)
        my, mx = _split_flat(mpix, S)
        rgba = out.rgba
        g = rgba[..., 0].astype(np.float32)
        g += rgba[..., 1]
        g += rgba[..., 2]
        g *= np.float32(1.0 / 765.0)  # grey level of the render, 0..1
        gf = g.reshape(-1)
        # edges of the render: the outline (a 4-neighbour off the silhouette or off the crop) and,
        # inside, colour edges (central differences of the grey level)
        inner = (mx > 0) & (mx < S - 1) & (my > 0) & (my < S - 1)
        ii = np.flatnonzero(inner)
        fi = fm.take(ii)
        inner[ii] = mask.take(fi - 1) & mask.take(fi + 1) & mask.take(fi - S) & mask.take(fi + S)
        ii = np.flatnonzero(inner)
        fi = fm.take(ii)
        gxi = gf.take(fi + 1) - gf.take(fi - 1)
        gyi = gf.take(fi + S) - gf.take(fi - S)
        is_edge = ~inner
        is_edge[ii] = gxi * gxi + gyi * gyi > np.float32(0.08 ** 2)
        ei = np.flatnonzero(is_edge)
        fe, eb, rem, ey, ex = fm.take(ei), mb.take(ei), mpix.take(ei), my.take(ei), mx.take(ei)
        ne = np.bincount(eb, minlength=n).astype(np.float64)
        esums = _Segments(ne)  # per-hypothesis sums over the edge pixels
        if c.w_edge > 0:
            dist = np.stack([obs[d].dist for d in udet])
            e_score = esums(np.maximum(0.0, 1.0 - dist.reshape(-1).take(ridx[eb] * SS + rem) / c.edge_tol)) \
                / np.maximum(ne, 1)
        else:
            e_score = np.zeros(n)
        # oriented: the render's gradient orientation at its edge pixels against the image's responses;
        # the outline against the black background counts even for dark objects (+0.25 on the silhouette)
        def gm(idx):  # grey level + 0.25 on the silhouette, at flat pixel indices
            return gf.take(idx) + np.float32(0.25) * mask.take(idx)

        zero = np.float32(0.0)
        inx, iny = (ex > 0) & (ex < S - 1), (ey > 0) & (ey < S - 1)
        gxm = np.where(inx, gm(np.where(inx, fe + 1, fe)) - gm(np.where(inx, fe - 1, fe)), zero)
        gym = np.where(iny, gm(np.where(iny, fe + S, fe)) - gm(np.where(iny, fe - S, fe)), zero)
        ob = _orientation_bins_of(gxm, gym)
        resp = np.stack([obs[d].resp for d in udet]).reshape(-1)  # (U, 8, S, S) flat
        o_score = esums(resp.take((ridx[eb] * 8 + ob) * SS + rem)) / np.maximum(ne, 1)
        # colour with one gain per hypothesis, on the silhouette pixels (channels as rows: (3, P))
        opix = ridx[mb] * SS + mpix  # the same pixel in the observation's crop
        I = np.stack([obs[d].rgb for d in udet]).reshape(U * SS, 3).T.take(opix, axis=1)  # (3, P) 0..1
        Rv = px.take(fm).view(np.uint8).reshape(-1, 4).T[:3].astype(np.float32, order="C")
        Rv *= np.float32(1.0 / 255.0)
        grey = np.array([obs[d].grey for d in udet])
        if grey.any():  # a grey sensor sees the render's luminance (ITU-R BT.601 weights), not its colours
            gp = grey[ridx].take(mb)
            Rv[:, gp] = (np.float32(0.299) * Rv[0, gp] + np.float32(0.587) * Rv[1, gp]
                         + np.float32(0.114) * Rv[2, gp])[None]
        num = sums(I[0] * Rv[0] + I[1] * Rv[1] + I[2] * Rv[2])
        den = sums(Rv[0] * Rv[0] + Rv[1] * Rv[1] + Rv[2] * Rv[2])
        gain_h = np.clip(num / np.maximum(den, 1e-9), 0.3, 3.0).astype(np.float32)
        Rv *= gain_h.take(mb)
        I -= Rv
        I *= I
        diff = np.sqrt(I[0] + I[1] + I[2])
        c_score = sums(np.maximum(np.float32(0.0), np.float32(1.0) - diff / np.float32(c.colour_tol))) \
            / np.maximum(area, 1)
        # region: object-like pixels inside vs outside the silhouette, within the box
        nb = np.stack([obs[d].not_bg for d in udet])
        inb = np.stack([obs[d].in_box for d in udet])
        nb_box = (nb * inb).sum((1, 2))[ridx]
        n_box = inb.sum((1, 2))[ridx].astype(np.float64)
        w_in = inb.reshape(-1).take(opix)
        n_in = sums(w_in.astype(np.float32))
        s_in = sums(np.where(w_in, nb.reshape(-1).take(opix), np.float32(0.0)))
        pin = s_in / np.maximum(n_in, 1)
        pout = (nb_box - s_in) / np.maximum(n_box - n_in, 1)
        r_score = np.clip(0.5 + 0.5 * (pin - pout), 0.0, 1.0)
        # box of the silhouette (pixel edges): rows come sorted per hypothesis, columns need a min/max
        x1, x2, y1, y2 = (np.zeros(n, np.int64) for _ in range(4))
        if len(fm):
            first, last = sums.first, sums.last
            y1[has], y2[has] = my[first], my[last] + 1
            x1[has] = np.minimum.reduceat(mx, first)
            x2[has] = np.maximum.reduceat(mx, first) + 1
        bx = np.stack([obs[d].box_crop for d in udet])[ridx]
        iw = np.clip(np.minimum(x2, bx[:, 2]) - np.maximum(x1, bx[:, 0]), 0, None)
        ih = np.clip(np.minimum(y2, bx[:, 3]) - np.maximum(y1, bx[:, 1]), 0, None)
        barea = (bx[:, 2] - bx[:, 0]) * (bx[:, 3] - bx[:, 1])
        marea = np.maximum((x2 - x1) * (y2 - y1), 1e-9)
        b_score = (iw * ih / np.maximum(barea, 1e-9)) * np.minimum(1.0, barea / marea) ** c.box_excess
        coloured = np.array([self._coloured.get(int(o), False) for o in obj_ids])
        wc = np.where(coloured, c.w_colour, 0.0)
        wp = 0.0 if prior is None else c.w_prior
        pr = 0.0 if prior is None else np.nan_to_num(np.asarray(prior, dtype=np.float64))
        # mask: the silhouette's IoU with the detection's segmentation (detections that have one)
        has_seg = np.array([obs[d].seg is not None for d in udet])
        m_score, wm = np.zeros(n), np.zeros(n)
        if has_seg.any() and c.w_mask > 0:
            segs = np.stack([obs[d].seg if obs[d].seg is not None else np.zeros((S, S), np.float32) for d in udet])
            inter = sums(segs.reshape(-1).take(opix))
            union = area + segs.reshape(U, -1).sum(1)[ridx] - inter
            m_score = np.where(union > 0, inter / np.maximum(union, 1e-9), 0.0)
            wm = np.where(has_seg[ridx], c.w_mask, 0.0)
        total = (c.w_edge * e_score + c.w_orient * o_score + wc * c_score + c.w_region * r_score
                 + c.w_box * b_score + wp * pr + wm * m_score) / (c.w_edge + c.w_orient + wc + c.w_region + c.w_box
                                                                  + wp + wm)
        total = np.where(has, total, 0.0)
        term_arrays = {"orient": o_score, "edge": e_score, "colour": c_score, "region": r_score, "box": b_score,
                       "mask": m_score}
        if (self.scorer is not None and learned) or inputs:
            from ..scorer.features import assemble, term_vector

            tv = term_vector(term_arrays, prior, coloured, total, area / np.maximum(barea, 1e-9))
            if inputs:
                return {"rgba": out.rgba, "gain": gain_h, "terms": tv, "ridx": ridx, "udet": udet, "total": total}
            image = assemble(np.stack([obs[d].rgb for d in udet]), inb, nb, ridx, out.rgba, gain_h)
            pred = np.where(has, self.scorer(image, tv, ridx), 0.0)
            if terms:
                return pred, dict(term_arrays, total=total)
            return pred
        if terms:
            return total, term_arrays
        return total

    def rank(self, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray, obj_ids: np.ndarray,
              T_hyp: np.ndarray, prior: np.ndarray | None = None, masks=None) -> RankedHypotheses:
        """Score the k hypotheses T_hyp (N, k, 4, 4) of N detections (boxes (N, 4) px, obj_ids (N,))
        in one render and sort each detection's by score. prior (N, k): template scores (NaN where a
        detection has fewer than k hypotheses: those rank last). With ``rank_faces`` 0 every
        hypothesis is scored with the ``max_faces`` copies (no coarse first pass). masks: None, or
        per detection an (H, W) bool segmentation or None (see :func:`observe`)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        obj_ids = np.asarray(obj_ids).reshape(-1)
        T_hyp = np.asarray(T_hyp, dtype=np.float64)
        N, k = T_hyp.shape[:2]
        pr = np.zeros((N, k)) if prior is None else np.asarray(prior, dtype=np.float64)
        masks = [None] * len(boxes) if masks is None else list(masks)
        if len(masks) != len(boxes):
            raise ValueError(f"{len(masks)} masks for {len(boxes)} detections")
        obs = [observe(rgb, K, b, self.conf, m) for b, m in zip(boxes, masks)]
        valid = np.isfinite(pr) & np.all(np.isfinite(T_hyp.reshape(N, k, -1)), -1) & (T_hyp[..., 2, 3] > 0)
        di, hi = np.nonzero(valid)
        sc = np.full((N, k), -1.0)  # verification scores are in [0, 1]: missing hypotheses rank last
        c = self.conf
        cascade = 0 < c.rank_faces < c.max_faces and c.rank_keep < k
        last = self.scorer is not None and c.scorer_scope == "rank"  # the scorer orders the best scorer_keep
        if cascade:
            self._renderer_with(c.rank_faces)
            coarse = np.array([self._coarse[int(o)] for o in obj_ids], bool)
            cascade = bool(coarse.any())
        if len(di):
            sc[di, hi] = self.score(obs, di, obj_ids[di], T_hyp[di, hi], None if prior is None else pr[di, hi],
                                    max_faces=c.rank_faces if cascade else None)
        ahead = np.zeros((N, k))
        if cascade or last:  # re-score each detection's best rank_keep (scorer_keep by the scorer) with the full
            # copies; they stay ahead
            top = np.argsort(-sc, axis=1, kind="stable")[:, :c.scorer_keep if last else c.rank_keep]
            di2 = np.repeat(np.arange(N), top.shape[1])
            hi2 = top.reshape(-1)
            keep = sc[di2, hi2] >= 0
            if not last:  # objects drawn from their max_faces copy: scored already
                keep &= coarse[di2]
            di2, hi2 = di2[keep], hi2[keep]
            if len(di2):
                sc[di2, hi2] = self.score(obs, di2, obj_ids[di2], T_hyp[di2, hi2],
                                          None if prior is None else pr[di2, hi2], learned=last or None)
                ahead[di2, hi2] = 2.0
        order = np.argsort(-(sc + ahead), axis=1, kind="stable")
        rows = np.arange(N)[:, None]
        return RankedHypotheses(T_hyp[rows, order], sc[rows, order], pr[rows, order], obs)


    # ------------------------------------------------------------------ refinement

    def refine(self, obs: list[CropObservation], obj_ids: np.ndarray, T: np.ndarray,
               prior: np.ndarray | None = None, init_score: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Local random search (see the module docstring) of poses T (m, 4, 4), one per observation
        ``obs[i]``. ``init_score`` (m,): the scores of T when known (e.g. from :meth:`rank`, with the
        same ``prior``), saving one render. Returns the refined poses and their scores (never below
        the input's)."""
        c = self.conf
        m = len(T)
        T = np.array(T, dtype=np.float64)
        det = np.arange(m)
        obj_ids = np.asarray(obj_ids).reshape(-1)
        faces = c.refine_faces if 0 < c.refine_faces != c.max_faces else None
        best = (self.score(obs, det, obj_ids, T, prior, max_faces=faces) if init_score is None or faces
                else np.array(init_score, dtype=np.float64))
        prior_n = None if prior is None else np.repeat(np.asarray(prior, dtype=np.float64), c.samples)
        rng = np.random.default_rng(c.seed)
        s_rot, s_px, s_z = math.radians(c.sigma_rot_deg), c.sigma_px, c.sigma_depth
        ns = c.samples
        for _ in range(c.rounds):
            w = rng.normal(size=(m * ns, 3)) * s_rot
            dR = axis_angle_to_matrix(w).reshape(m, ns, 3, 3)
            dz = np.exp(rng.normal(size=(m, ns)) * s_z)
            dpx = rng.normal(size=(m, ns, 2)) * s_px
            Tn = np.repeat(T[:, None], ns, 1)
            Tn[..., :3, :3] = dR @ T[:, None, :3, :3]  # rotate about the object origin, camera axes
            t = T[:, :3, 3]
            Ks = np.stack([o.K for o in obs])
            # image-plane shift at the object's depth, then depth scaled along the ray
            shift = np.zeros((m, ns, 3))
            shift[..., 0] = dpx[..., 0] * t[:, None, 2] / Ks[:, None, 0, 0]
            shift[..., 1] = dpx[..., 1] * t[:, None, 2] / Ks[:, None, 1, 1]
            Tn[..., :3, 3] = (t[:, None] + shift) * dz[..., None]
            sc = self.score(obs, np.repeat(det, ns), np.repeat(obj_ids, ns), Tn.reshape(-1, 4, 4),
                            prior_n, max_faces=faces).reshape(m, ns)
            j = sc.argmax(1)
            better = sc[det, j] > best
            T[better] = Tn[det[better], j[better]]
            best[better] = sc[det[better], j[better]]
            s_rot, s_px, s_z = s_rot * c.shrink, s_px * c.shrink, s_z * c.shrink
        return T, best

