"""From the network's maps to an instance mask: threshold, h-maxima seeds, watershed (torch-free)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ... import PsdError

DEFAULT_POSTPROCESS = {"threshold": 0.5, "h": 0.2, "min_distance": 0.0, "min_area_px": 4, "use_boundary": True}
# the post-processing grid searched on the validation masks after training
POSTPROCESS_GRID = {"h": (0.1, 0.2, 0.35, 0.5), "use_boundary": (False, True), "min_distance": (0.0, 3.0)}


# ---------------------------------------------------------------------------------------------
# from a network's maps to instances


def split_instances(
    foreground_prob: np.ndarray,
    boundary_prob: np.ndarray | None = None,
    distance: np.ndarray | None = None,
    *,
    threshold: float = 0.5,
    boundary_threshold: float = 0.5,
    h: float = 1.0,
    min_distance: float = 3.0,
    min_area_px: int = 4,
) -> np.ndarray:
    """Instance mask (uint16, 0 = background, 1..N) from per-pixel maps of a network.

    - foreground = `foreground_prob > threshold`;
    - distance map: `distance` if given (e.g. a predicted distance-to-boundary, any scale),
      else the Euclidean distance transform (px) of the foreground with the predicted boundary
      (`boundary_prob >= boundary_threshold`) removed, so touching grains come apart;
    - seeds: the maxima of the distance map that stand at least `h` (in the distance map's
      units; px for the transform) above the saddle to any higher maximum (h-maxima: regional
      maxima of the map reconstructed from itself lowered by h), which ignores the ripples of a
      digitised outline; seeds whose centres are closer than `min_distance` px within one
      foreground blob are merged into one;
    - watershed of the negated distance from the seeds, restricted to the foreground; a blob
      without a seed becomes one instance; instances under `min_area_px` pixels are dropped
      and the rest numbered 1..N.
    """
    from skimage.morphology import local_maxima, reconstruction
    from skimage.segmentation import watershed

    fg_prob = np.asarray(foreground_prob)
    if fg_prob.ndim != 2:
        raise PsdError(f"foreground map must be 2-D, got shape {fg_prob.shape}")
    for name, arr in (("boundary", boundary_prob), ("distance", distance)):
        if arr is not None and np.shape(arr) != fg_prob.shape:
            raise PsdError(f"{name} map has shape {np.shape(arr)}, the foreground map {fg_prob.shape}")
    fg = fg_prob > threshold
    if not fg.any():
        return np.zeros(fg.shape, dtype=np.uint16)
    if distance is None:
        interior = fg if boundary_prob is None else fg & (np.asarray(boundary_prob) < boundary_threshold)
        dist = ndimage.distance_transform_edt(interior)
    else:
        dist = np.where(fg, np.nan_to_num(np.asarray(distance, dtype=float)), 0.0)

    eight = np.ones((3, 3), dtype=bool)
    # h-maxima: the regional maxima of the distance map reconstructed (by dilation) from itself
    # lowered by h; peaks joined above their saddle minus h share one plateau, hence one seed
    hmax = reconstruction(dist - h, dist, method="dilation") if h > 0 else dist
    seeds, n_seeds = ndimage.label(local_maxima(hmax, connectivity=2) & fg, structure=eight)
    if n_seeds > 1 and min_distance > 0:
        seeds = _merge_close_seeds(seeds, n_seeds, fg, min_distance)
    labels = watershed(-dist, seeds, mask=fg)
    # blobs that got no seed (e.g. flatter than h) become one instance each
    orphans, n_orphans = ndimage.label(fg & (labels == 0), structure=eight)
    if n_orphans:
        labels = np.where(orphans > 0, orphans + labels.max(), labels)
    return _renumber(labels, min_area_px)


def _merge_close_seeds(seeds: np.ndarray, n: int, fg: np.ndarray, min_distance: float) -> np.ndarray:
    """Give seeds whose centres lie within `min_distance` px, in one foreground blob, one label."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    r, c = np.nonzero(seeds)
    k = seeds[r, c] - 1
    size = np.bincount(k, minlength=n)
    sums = np.column_stack([np.bincount(k, weights=r, minlength=n), np.bincount(k, weights=c, minlength=n)])
    centres = sums / size[:, None]
    _, first = np.unique(k, return_index=True)  # one pixel of each seed, to find its blob
    blobs, _ = ndimage.label(fg, structure=np.ones((3, 3), dtype=bool))
    blob = blobs[r[first], c[first]]
    pairs = cKDTree(centres).query_pairs(min_distance, output_type="ndarray")
    pairs = pairs[blob[pairs[:, 0]] == blob[pairs[:, 1]]]
    if not len(pairs):
        return seeds
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    lut = np.concatenate([[0], group + 1])
    return lut[seeds]


def _renumber(labels: np.ndarray, min_area_px: int) -> np.ndarray:
    """Drop instances under `min_area_px`, renumber the rest 1..N keeping their order, as uint16."""
    flat = labels.ravel()
    area = np.bincount(flat)
    keep = area >= max(int(min_area_px), 1)
    keep[0] = False
    kept = np.flatnonzero(keep)
    if len(kept) > np.iinfo(np.uint16).max:
        raise PsdError(f"{len(kept)} instances do not fit a 16-bit mask")
    lut = np.zeros(len(area), dtype=np.uint16)
    lut[kept] = np.arange(1, len(kept) + 1, dtype=np.uint16)
    return lut[labels]



# ---------------------------------------------------------------------------------------------
# from maps to instances, to the PSD, to the calibrated read-out


def postprocess(maps: np.ndarray, settings: dict) -> np.ndarray:
    """Instance mask (uint16) from one image's 3×H×W maps (foreground, boundary, distance, all in
    [0, 1]): the watershed of `split_instances` on the predicted distance (multiplied by
    1 − boundary with `use_boundary`), seeds its h-maxima."""
    fg, bd, dist = (np.asarray(maps[i], dtype=np.float32) for i in range(3))
    if settings.get("use_boundary", True):
        dist = dist * (1.0 - bd)
    return split_instances(fg, distance=dist, threshold=settings["threshold"], h=settings["h"],
                           min_distance=settings["min_distance"], min_area_px=int(settings["min_area_px"]))

