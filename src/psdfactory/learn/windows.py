"""Training windows labelled by their own particles (`train.crop`).

A window of a scene image holds a sample of the bed, not the bed: its d10/d50/d90 are those of the
particles whose centre lies inside it (hidden ones too, as the scene's labels count every particle in view),
in the labels' size definition and weighting. A window labelled with the whole scene's d-values
teaches a CNN a label its pixels do not hold — a 128-px window of a 256-px image often misses the
few largest particles that set d90 (docs/experiments.md, "windows"). The particle table gives every
particle's position, so each window gets its true labels.

Image frame (`render.json`'s image_origin): centred on the table, row 0 at the +y edge of the view,
column 0 at the -x edge; the view is `mm_per_px * resolution` mm wide.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import PsdError
from ..psd import weighted_percentiles

PARTICLE_COLUMNS = ("particle_id", "size_mm", "volume_mm3", "x_mm", "y_mm")  # what a window's labels need
MIN_WINDOW_PARTICLES = 10  # a window with fewer is drawn again (its percentiles would be a handful of particles)
WINDOW_DRAWS = 8  # draws per item before the window with the most particles is taken


def particle_pixels(x_mm: np.ndarray, y_mm: np.ndarray, view_mm: float, size_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(column, row) in px of particle centres in an image of `size_px` px over `view_mm` mm."""
    px = size_px / float(view_mm)
    return (np.asarray(x_mm, float) + view_mm / 2) * px, (view_mm / 2 - np.asarray(y_mm, float)) * px


def inside(col: np.ndarray, row: np.ndarray, r0: int, c0: int, window: int) -> np.ndarray:
    """Which centres lie in the window of `window` px whose top-left pixel is (r0, c0)."""
    return (col >= c0) & (col < c0 + window) & (row >= r0) & (row < r0 + window)


def window_targets(sizes: np.ndarray, volumes: np.ndarray, keep: np.ndarray, weighting: str) -> np.ndarray:
    """d10/d50/d90 of the particles `keep` (a boolean mask), number- or volume-weighted as the labels are."""
    s = np.asarray(sizes, float)[keep]
    return weighted_percentiles(s, np.asarray(volumes, float)[keep] if weighting == "volume" else None)


class SceneWindows(torch.utils.data.Dataset):
    """The items of `scenes` (uint8 C×S×S images, any channels, and the scene's targets), each cut
    to a random `window`×`window` px window drawn by `gen`, with the window's own targets. `rows`:
    the scenes' manifest rows (scene_id, mm_per_px, resolution), `particles`: scene_id → the
    PARTICLE_COLUMNS arrays (`data.particles_by_scene`)."""

    def __init__(self, scenes, rows: list[dict], particles: dict[str, dict[str, np.ndarray]], window: int,
                 weighting: str, gen: torch.Generator):
        missing = [r["scene_id"] for r in rows if r["scene_id"] not in particles]
        if missing:
            raise PsdError(f"train.crop labels each window by its particles, and the particle manifest has no rows "
                           f"for {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}; rerun their label jobs")
        self.scenes, self.rows, self.particles = scenes, rows, particles
        self.window, self.weighting, self.gen = int(window), weighting, gen
        self.centres: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.scenes)

    def _centres(self, i: int, size_px: int) -> tuple[np.ndarray, np.ndarray]:
        if i not in self.centres:
            r, p = self.rows[i], self.particles[self.rows[i]["scene_id"]]
            self.centres[i] = particle_pixels(p["x_mm"], p["y_mm"], float(r["mm_per_px"]) * float(r["resolution"]),
                                              size_px)
        return self.centres[i]

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        x, _ = self.scenes[i]
        h, w = x.shape[-2:]
        win = min(self.window, h, w)
        col, row = self._centres(i, w)
        best = None
        for _ in range(WINDOW_DRAWS):
            r0 = int(torch.randint(0, h - win + 1, (1,), generator=self.gen))
            c0 = int(torch.randint(0, w - win + 1, (1,), generator=self.gen))
            keep = inside(col, row, r0, c0, win)
            if best is None or keep.sum() > best[2].sum():
                best = (r0, c0, keep)
            if keep.sum() >= MIN_WINDOW_PARTICLES:
                break
        r0, c0, keep = best
        if not keep.any():
            raise PsdError(f"scene {self.rows[i]['scene_id']}: no particle in any of {WINDOW_DRAWS} random "
                           f"{win}-px windows; train.crop must be larger for scenes this sparse")
        p = self.particles[self.rows[i]["scene_id"]]
        y = window_targets(p["size_mm"], p["volume_mm3"], keep, self.weighting)
        return x[..., r0 : r0 + win, c0 : c0 + win], torch.as_tensor(y, dtype=torch.float32)
