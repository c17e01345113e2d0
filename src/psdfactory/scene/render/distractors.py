"""Things in a photo that are not grains: a scale card or a ruler laid on the bed, as people put
them in the shot to give the scale. Drawn over a rendered image (either backend) before the
sensor model, so the camera's blur, noise and JPEG fall on them too; the mask is 0 where they lie
(they hide the grains under them, which still count in the labels: the labels are of every
particle, hidden or not). A model trained on such scenes learns that a flat printed object with
sharp edges and stripes is not a grain.

Each comes from the scene's own ``distractors`` random stream: switching them on or changing
their settings changes no other draw of the scene.

- ``scale_card``: a grey or white card (50-90 mm) with a chequered black-and-white bar along one
  edge, a row of colour patches and dark print (text-like blobs);
- ``ruler``: a long light strip (wood, white or yellow; 25-35 mm wide) with mm ticks (5 and
  10 mm ones longer) and dark number-like marks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import PsdError
from ...config import config_fields

KINDS = ("scale_card", "ruler")
LENGTH_MM = {"scale_card": (50.0, 90.0), "ruler": (150.0, 300.0)}  # a card's long side, a ruler's length in view
Range = tuple[float, float]


@dataclass(frozen=True)
class DistractorParams:
    """The config's `render.distractors` section (defaults: the schema's, config.schema.yaml)."""

    probability: float  # share of the scenes with one (0 = none)
    kinds: tuple[str, ...]  # drawn from uniformly
    brightness: Range  # relative to the scene's light

    @classmethod
    def from_dict(cls, d: dict) -> DistractorParams:
        kw = config_fields(cls, d, "render.distractors")
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()}
        bad = [k for k in kw["kinds"] if k not in KINDS]
        if bad:
            raise PsdError(f"render.distractors.kinds: {', '.join(bad)} unknown; one of {', '.join(KINDS)}")
        return cls(**kw)


def _frame(shape: tuple[int, int], centre_px: np.ndarray, angle: float, px_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) in mm of every pixel centre in the object's own frame (u along its long side)."""
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    dy, dx = r - centre_px[0], c - centre_px[1]
    ca, sa = np.cos(angle), np.sin(angle)
    return (dx * ca + dy * sa) * px_mm, (-dx * sa + dy * ca) * px_mm


def _blobs(rng: np.random.Generator, u: np.ndarray, v: np.ndarray, box: tuple[float, float, float, float],
           n: int, size_mm: Range) -> np.ndarray:
    """Dark print: `n` small rounded rectangles (text, digits, a logo) inside `box` (u0, u1, v0, v1)."""
    ink = np.zeros(u.shape, dtype=bool)
    u0, u1, v0, v1 = box
    for _ in range(n):
        cu, cv = rng.uniform(u0, u1), rng.uniform(v0, v1)
        hu, hv = rng.uniform(*size_mm) / 2, rng.uniform(*size_mm) / 2 * rng.uniform(0.3, 1.0)
        ink |= (np.abs(u - cu) < hu) & (np.abs(v - cv) < hv)
    return ink


def _scale_card(rng: np.random.Generator, u: np.ndarray, v: np.ndarray, length: float):
    """(inside, rgb) of a scale card of long side `length` mm."""
    width = length * rng.uniform(0.55, 0.7)
    inside = (np.abs(u) < length / 2) & (np.abs(v) < width / 2)
    base = np.array([rng.uniform(0.55, 0.95)] * 3) * rng.uniform(0.95, 1.05, 3)
    rgb = np.broadcast_to(base, (*u.shape, 3)).copy()
    bar = (v > width / 2 - width * 0.18) & inside  # the chequered scale bar along one long edge
    check = rng.uniform(4.0, 10.0)  # mm per square
    black = ((np.floor((u + length / 2) / check) + np.floor(v / (check / 2))) % 2).astype(bool)
    rgb[bar & black] = 0.05
    rgb[bar & ~black] = 0.95
    patches = rng.uniform(0.1, 0.95, (int(rng.integers(3, 7)), 3))  # a row of colour patches
    row = (v < -width / 2 + width * 0.3) & (v > -width / 2 + width * 0.08) & inside
    k = np.clip(((u + length / 2) / length * len(patches)).astype(int), 0, len(patches) - 1)
    rgb[row] = patches[k[row]]
    print_ = _blobs(rng, u, v, (-length * 0.42, length * 0.42, -width * 0.12, width * 0.25),
                    int(rng.integers(6, 20)), (1.5, 6.0)) & inside
    rgb[print_] = 0.08
    return inside, rgb


def _ruler(rng: np.random.Generator, u: np.ndarray, v: np.ndarray, length: float, px_mm: float):
    """(inside, rgb) of a ruler strip of visible length `length` mm (it may run off the image)."""
    width = rng.uniform(25.0, 35.0)
    inside = (np.abs(u) < length / 2) & (np.abs(v) < width / 2)
    base = [np.array([0.78, 0.62, 0.40]), np.array([0.92, 0.92, 0.9]), np.array([0.9, 0.8, 0.25])][
        int(rng.integers(0, 3))]
    rgb = np.broadcast_to(base * rng.uniform(0.85, 1.1), (*u.shape, 3)).copy()
    mm = u + length / 2
    near = np.abs(mm - np.round(mm))  # distance to the nearest mm line, in mm
    tick_len = np.where(np.round(mm) % 10 == 0, 0.45, np.where(np.round(mm) % 5 == 0, 0.32, 0.2)) * width
    ticks = inside & (near < max(0.12, 0.35 * px_mm)) & (v > width / 2 - tick_len)
    rgb[ticks] = 0.06
    digits = _blobs(rng, u, v, (-length / 2, length / 2, 0.0, width * 0.15), int(length / 12), (1.5, 3.5)) & inside
    rgb[digits] = 0.06
    return inside, rgb


def add_distractors(rgb: np.ndarray, mask: np.ndarray, px_mm: float, p: DistractorParams,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The rendered image (float H×W×3 in [0, 1]) and mask with (maybe) one distractor laid on the
    bed: → (image, mask, what was drawn). The mask is 0 under it."""
    draw = rng.random() < p.probability  # drawn always, so the stream's next draws do not depend on it
    kind = p.kinds[int(rng.integers(0, len(p.kinds)))] if p.kinds else None
    length = float(rng.uniform(*LENGTH_MM[kind or KINDS[0]]))
    h, w = mask.shape
    centre = rng.uniform([0.1 * h, 0.1 * w], [0.9 * h, 0.9 * w])
    angle = float(rng.uniform(0, np.pi))
    light = float(rng.uniform(*p.brightness))
    if not draw or kind is None:
        return rgb, mask, []
    u, v = _frame((h, w), centre, angle, px_mm)
    inside, colour = _scale_card(rng, u, v, length) if kind == "scale_card" else _ruler(rng, u, v, length, px_mm)
    out = np.array(rgb, dtype=np.float32, copy=True)
    out[inside] = np.clip(colour[inside] * light, 0, 1)
    covered = mask.copy()
    covered[inside] = 0
    return out, covered, [{"kind": kind, "size_mm": round(length, 2), "centre_px": [round(float(x), 1) for x in centre],
                           "angle_deg": round(float(np.degrees(angle)), 1), "covered_px": int(inside.sum())}]
