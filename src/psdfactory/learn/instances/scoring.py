"""A predicted instance mask against the true one: one-to-one matches at an IoU, precision /
recall / F1, and the size errors of matched grains (torch-free)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import PsdError
from .measure import check_mask, compact_ids

# ---------------------------------------------------------------------------------------------
# scoring a segmentation


def f1_score(n_matched: int, n_pred: int, n_true: int) -> float:
    """2 matched / (predicted + true): the F1 of a detection (NaN with neither)."""
    return 2 * n_matched / (n_pred + n_true) if n_pred + n_true else float("nan")


@dataclass(frozen=True)
class MatchResult:
    """One-to-one matches of predicted to true instances at IoU >= a threshold."""

    pred_ids: np.ndarray  # matched predicted ids
    true_ids: np.ndarray  # the true id each is matched to
    iou: np.ndarray  # their IoU
    n_pred: int
    n_true: int
    precision: float  # matched / predicted (NaN with no prediction)
    recall: float  # matched / true (NaN with no true instance)
    f1: float  # 2 matched / (predicted + true) (NaN with neither)

    @property
    def n_matched(self) -> int:
        return len(self.pred_ids)


def _overlaps(pred: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(pred ids, true ids, pair table [pred idx, true idx, pixels]) of the mask pair, index 0 = background."""
    pids, _, plut = compact_ids(pred)
    tids, _, tlut = compact_ids(true)
    pids, tids = np.concatenate([[0], pids]), np.concatenate([[0], tids])
    plut, tlut = plut + 1, tlut + 1  # background (lookup -1) -> 0
    kp, kt = len(pids), len(tids)
    code = plut[pred.ravel()] * kt + tlut[true.ravel()]
    if kp * kt <= 1 << 24:  # contingency table
        table = np.bincount(code, minlength=kp * kt)
        nz = np.flatnonzero(table)
        counts = table[nz]
    else:  # too many ids for a dense table: only the pairs that occur
        nz, counts = np.unique(code, return_counts=True)
    return pids, tids, nz // kt, nz % kt, counts


def match_instances(pred_mask: np.ndarray, true_mask: np.ndarray, iou: float = 0.5) -> MatchResult:
    """Match predicted to true instances one-to-one where IoU >= `iou` (greedy, best IoU first).

    Overlaps come from one contingency table of id pairs (np.bincount over pred * K + true);
    at `iou` > 0.5 a match is unique anyway, the greedy pass only settles ties below.
    """
    pred, true = check_mask(pred_mask, "predicted mask"), check_mask(true_mask, "true mask")
    if pred.shape != true.shape:
        raise PsdError(f"predicted mask {pred.shape} and true mask {true.shape} differ in shape")
    if not 0 < iou <= 1:
        raise PsdError(f"IoU threshold must be in (0, 1], got {iou}")
    pids, tids, pi, ti, inter = _overlaps(pred, true)
    area_p = np.bincount(pi, weights=inter, minlength=len(pids))
    area_t = np.bincount(ti, weights=inter, minlength=len(tids))
    fgpair = (pi > 0) & (ti > 0)
    pi, ti, inter = pi[fgpair], ti[fgpair], inter[fgpair]
    ious = inter / (area_p[pi] + area_t[ti] - inter)
    cand = np.flatnonzero(ious >= iou)
    cand = cand[np.argsort(-ious[cand], kind="stable")]
    used_p, used_t, chosen = set(), set(), []
    for j in cand:  # a handful of candidate pairs, not pixels
        if pi[j] not in used_p and ti[j] not in used_t:
            used_p.add(pi[j])
            used_t.add(ti[j])
            chosen.append(j)
    chosen = np.array(chosen, dtype=np.int64)
    n_pred, n_true, tp = len(pids) - 1, len(tids) - 1, len(chosen)
    return MatchResult(
        pred_ids=pids[pi[chosen]],
        true_ids=tids[ti[chosen]],
        iou=ious[chosen],
        n_pred=n_pred,
        n_true=n_true,
        precision=tp / n_pred if n_pred else float("nan"),
        recall=tp / n_true if n_true else float("nan"),
        f1=f1_score(tp, n_pred, n_true),
    )


def border_ids(mask: np.ndarray) -> np.ndarray:
    """The ids (>= 1) of the instances with a pixel on the image border, ascending."""
    m = check_mask(mask)
    if not m.size:
        return np.zeros(0, np.int64)
    edge = np.concatenate([m[0], m[-1], m[:, 0], m[:, -1]])
    return np.unique(edge[edge > 0])


@dataclass(frozen=True)
class BorderMatch:
    """Predicted vs reference grains when the reference leaves out the grains the image border
    cuts (a photo's: their size is unknown). Matches one-to-one at IoU >= a threshold, then:

    - a reference grain touching the border is left out (neither found nor missed), and so is a
      predicted grain matched to one;
    - a predicted grain touching the border counts only if it matches a reference grain (a TP);
      matching none it is left out, not a false positive;
    - every other predicted grain matching none is a false positive, every other reference grain
      unmatched a false negative."""

    pred_ids: np.ndarray  # the predicted grains of the true positives
    true_ids: np.ndarray  # the reference grain each is matched to
    iou: np.ndarray  # their IoU
    tp: int
    fp: int
    fn: int
    left_out_pred: int  # predicted grains neither TP nor FP
    left_out_true: int  # reference grains touching the border
    precision: float  # tp / (tp + fp) (NaN without either)
    recall: float  # tp / (tp + fn) (NaN without a scored reference grain)
    f1: float  # 2 tp / (2 tp + fp + fn) (NaN without any)
    fp_ids: np.ndarray  # the predicted grains counted as false positives
    fn_ids: np.ndarray  # the reference grains counted as false negatives


def match_off_border(pred_mask: np.ndarray, true_mask: np.ndarray, iou: float = 0.5,
                     pred_on_border: np.ndarray | None = None,
                     true_on_border: np.ndarray | None = None) -> BorderMatch:
    """`match_instances`, scored by the border rule of `BorderMatch`. `pred_on_border`: the ids of
    the predicted grains that touch the border where that was decided on another copy of the
    mask (the estimator's own, before a resize); default: those touching this mask's border.
    `true_on_border` likewise for the reference (the mask as drawn, where it was grown since)."""
    m = match_instances(pred_mask, true_mask, iou)
    pred_present = compact_ids(check_mask(pred_mask))[0]
    true_present = compact_ids(check_mask(true_mask))[0]
    pred_edge = border_ids(pred_mask) if pred_on_border is None else np.asarray(pred_on_border, np.int64)
    true_edge = border_ids(true_mask) if true_on_border is None else np.asarray(true_on_border, np.int64)
    scored = ~np.isin(m.true_ids, true_edge)  # matched to a reference grain that is not left out
    unmatched = pred_present[~np.isin(pred_present, m.pred_ids)]
    on_edge = np.isin(unmatched, pred_edge)
    tp, fp = int(scored.sum()), int((~on_edge).sum())
    n_true = len(true_present) - int(np.isin(true_present, true_edge).sum())
    nan = float("nan")
    fn_ids = true_present[~np.isin(true_present, true_edge) & ~np.isin(true_present, m.true_ids)]
    return BorderMatch(
        pred_ids=m.pred_ids[scored], true_ids=m.true_ids[scored], iou=m.iou[scored], tp=tp, fp=fp, fn=n_true - tp,
        left_out_pred=int(on_edge.sum()) + int((~scored).sum()), left_out_true=len(true_present) - n_true,
        precision=tp / (tp + fp) if tp + fp else nan, recall=tp / n_true if n_true else nan,
        f1=f1_score(tp, tp + fp, n_true), fp_ids=unmatched[~on_edge], fn_ids=fn_ids)


# What became of each grain a match missed. The share of a grain's pixels that decides, each way:
KIND_SHARE = 0.5
FN_KINDS = ("cut", "merged", "missed", "misfit")
FP_KINDS = ("merge", "background", "piece", "misfit")


@dataclass(frozen=True)
class ErrorKinds:
    """Why a segmentation's false negatives and false positives are what they are (`error_kinds`)."""

    fn: dict[str, int]  # per kind of FN_KINDS, the reference grains no found grain matches
    fp: dict[str, int]  # per kind of FP_KINDS, the found grains that match none


def error_kinds(pred_mask: np.ndarray, true_mask: np.ndarray, match: BorderMatch) -> ErrorKinds:
    """Each false negative and false positive of `match` (the two masks' `match_off_border`) sorted
    into one kind, the first that applies, "more than half" meaning a share above KIND_SHARE of a
    grain's pixels:

    - a reference grain no found grain matches is `cut` where two or more found grains lie more
      than half inside it; `merged` where the found grain overlapping it most holds more than half
      of it and of another reference grain too (one found grain over several); `missed` where the
      found grains together hold no more than half of it; else `misfit` (found whole and alone, but
      outlined too differently for the IoU);
    - a found grain that matches none is a `merge` where it holds more than half of each of two or
      more reference grains; `background` where more than half of it lies on the reference's
      background (gaps, sand, a scale card); a `piece` where more than half of it lies inside one
      reference grain and it is less than half that grain's size; else `misfit`.

    The counts add up to the match's fn and fp."""
    pids, tids, pi, ti, inter = _overlaps(check_mask(pred_mask), check_mask(true_mask))
    area_p = np.bincount(pi, weights=inter, minlength=len(pids))
    area_t = np.bincount(ti, weights=inter, minlength=len(tids))
    p_index = dict(zip(pids.tolist(), range(len(pids)), strict=True))
    t_index = dict(zip(tids.tolist(), range(len(tids)), strict=True))
    big = inter > KIND_SHARE * area_t[ti]  # the pair holds more than half of its reference grain
    fn = dict.fromkeys(FN_KINDS, 0)
    for t in (t_index[int(i)] for i in match.fn_ids):
        sel = (ti == t) & (pi > 0)
        ps, ov = pi[sel], inter[sel]
        if (ov > KIND_SHARE * area_p[ps]).sum() >= 2:
            kind = "cut"
        elif len(ps) and ov.max() > KIND_SHARE * area_t[t] and (big & (pi == ps[ov.argmax()]) & (ti != t)
                                                                  & (ti > 0)).any():
            kind = "merged"
        elif ov.sum() <= KIND_SHARE * area_t[t]:
            kind = "missed"
        else:
            kind = "misfit"
        fn[kind] += 1
    fp = dict.fromkeys(FP_KINDS, 0)
    for p in (p_index[int(i)] for i in match.fp_ids):
        sel = pi == p
        ts, ov = ti[sel], inter[sel]
        grains = ts > 0
        inside = ov > KIND_SHARE * area_p[p]
        if (big[sel] & grains).sum() >= 2:
            kind = "merge"
        elif (inside & ~grains).any():
            kind = "background"
        elif (inside & grains & (area_p[p] < KIND_SHARE * area_t[ts])).any():
            kind = "piece"
        else:
            kind = "misfit"
        fp[kind] += 1
    return ErrorKinds(fn=fn, fp=fp)


def fully_visible(true_mask: np.ndarray, z_by_id: np.ndarray) -> np.ndarray:
    """Boolean per mask id (index = id): the particle touches neither the image edge nor any
    particle whose centre lies higher (which could hide part of it)."""
    m = np.asarray(true_mask).astype(np.int64)
    n = len(z_by_id)
    ok = np.zeros(n, dtype=bool)
    present = np.unique(m[m > 0])
    ok[present[present < n]] = True
    border = np.concatenate([m[0], m[-1], m[:, 0], m[:, -1]])
    ok[border[(border > 0) & (border < n)]] = False
    for a, b in ((m[:, :-1], m[:, 1:]), (m[:-1, :], m[1:, :])):
        sel = (a != b) & (a > 0) & (b > 0) & (a < n) & (b < n)
        a, b = a[sel], b[sel]
        ok[a[z_by_id[b] > z_by_id[a]]] = False
        ok[b[z_by_id[a] > z_by_id[b]]] = False
    return ok


def size_errors(est_mm: np.ndarray, true_mm: np.ndarray) -> dict:
    """Median and 90th percentile of |est − true| / true, and the median signed ratio − 1."""
    est_mm, true_mm = np.asarray(est_mm, float), np.asarray(true_mm, float)
    if not len(est_mm):
        return {"n": 0, "median": None, "p90": None, "median_bias": None}
    rel = np.abs(est_mm - true_mm) / true_mm
    return {"n": int(len(rel)), "median": float(np.median(rel)), "p90": float(np.percentile(rel, 90)),
            "median_bias": float(np.median(est_mm / true_mm) - 1)}


# ---------------------------------------------------------------------------------------------
# reference masks that keep grains apart

OUTLINE_GAP_QUANTILE = 25  # percent of the meeting pairs' gaps: the band, not the wider gaps of grains that barely meet
MEETING_GAP = 0.5  # a pair meets (would touch but for an outline band) when its gap is under this x its smaller ECD
MIN_MEETING_PAIRS = 3  # fewer meeting pairs than this: no band can be read off the mask


def neighbour_gaps(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pair of neighbouring instances (n x 2 ids, ascending) and the smallest gap (px) between
    them: 0 where they touch, the background's width between them where they do not. Neighbours
    are instances whose nearest-instance regions meet (the background's Voronoi partition); the gap
    across the ridge between them is the sum of the two sides' distances to their instance (exact
    along a row or column, a little over the Euclidean gap on a slant)."""
    from scipy import ndimage as ndi

    m = check_mask(mask)
    none = (np.zeros((0, 2), np.int64), np.zeros(0))
    if not (m > 0).any():
        return none
    dist, (iy, ix) = ndi.distance_transform_edt(m == 0, return_indices=True)
    near = m[iy, ix]
    n = int(m.max()) + 1
    keys, widths = [], []
    for a, b, da, db in ((near[:, :-1], near[:, 1:], dist[:, :-1], dist[:, 1:]),
                         (near[:-1], near[1:], dist[:-1], dist[1:])):
        sel = a != b  # every pixel has a nearest instance, so both are > 0
        lo, hi = np.minimum(a[sel], b[sel]), np.maximum(a[sel], b[sel])
        keys.append(lo.astype(np.int64) * n + hi)
        widths.append(da[sel] + db[sel])
    key, width = np.concatenate(keys), np.concatenate(widths)
    if not len(key):
        return none
    order = np.lexsort((width, key))  # by pair, then by width: each pair's first is its smallest
    key, width = key[order], width[order]
    first = np.r_[True, key[1:] != key[:-1]]
    return np.stack([key[first] // n, key[first] % n], axis=1), width[first]


def outline_band_px(mask: np.ndarray) -> float:
    """The width of the outline band a reference mask draws as background between grains that
    touch (segmenteverygrain's boundary class; an outline drawn in 0s): among the neighbouring
    pairs that meet (gap under MEETING_GAP x the smaller grain's equivalent-circle diameter), the
    OUTLINE_GAP_QUANTILE-th percentile of their smallest gaps. 0 for a mask whose grains touch, and
    for one with fewer than MIN_MEETING_PAIRS meeting pairs (sparse grains: nothing to read)."""
    pairs, gaps = neighbour_gaps(mask)
    if not len(gaps):
        return 0.0
    ecd = 2 * np.sqrt(np.bincount(check_mask(mask).ravel()) / np.pi)
    meet = gaps < MEETING_GAP * np.minimum(ecd[pairs[:, 0]], ecd[pairs[:, 1]])
    return float(np.percentile(gaps[meet], OUTLINE_GAP_QUANTILE)) if meet.sum() >= MIN_MEETING_PAIRS else 0.0


def restore_outlines(mask: np.ndarray, band_px: float) -> np.ndarray:
    """The reference grains grown by half an outline band into the background around them, no
    grain into another: touching grains meet again at the band's middle. A band of w px lies
    between two grains' last pixels, whose edges are half a pixel further out: each grain's edge
    moves w/2 out, taking the pixels whose centres lie within (w + 1)/2 of its own (skimage's
    expand_labels, each to its nearest grain; an odd band's middle pixel to one of the two)."""
    from skimage.segmentation import expand_labels

    if band_px < 0:
        raise PsdError(f"an outline band is a width >= 0 px, got {band_px}")
    m = check_mask(mask)
    return m.copy() if band_px == 0 else expand_labels(m, (band_px + 1) / 2)
