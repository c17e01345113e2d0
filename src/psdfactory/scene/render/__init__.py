"""Stage 3: render the settled bed top-down: ``image.png`` (RGB) and ``mask.png`` (16-bit ids).

Backends (``render.backend``): ``tiny`` (pybullet's TinyRenderer, fast, ``tiny.py``) and
``cycles`` (Blender, photorealistic, ``cycles.py``). Both see the same camera, the same look
(particle colours and textures, light direction and colour, table colour and texture, field of
view) drawn from the scene's render and look streams, and the same sensor model
(``look.py``). Over either backend's image, before the sensor: markings on the particles
(``markings.py``: veins, speckle, patches) and a scale card or ruler (``distractors.py``), each
from its own random stream. ``render_scene`` below runs the configured one.

``blender_job.py`` is not a module of the host: it is the script that Blender's own Python
runs (``python -P blender_job.py JOB_DIR``), shipped as package data beside ``cycles.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

import numpy as np

from ... import PsdError
from ...config import MAX_PARTICLES_16BIT
from ...seeding import rng_for
from ..geometry import Geometry
from .cycles import render_cycles
from .distractors import add_distractors
from .look import RenderParams, apply_sensor, draw_look, mm_per_px
from .markings import add_markings
from .tiny import render_tiny

BACKENDS: dict[str, Callable] = {"tiny": render_tiny, "cycles": render_cycles}


def render_scene(spec: dict, geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, p: RenderParams,
                 entropy: list[int]):
    """→ (image uint8 HxWx3, mask uint16 HxW, metadata dict)."""
    if p.backend not in BACKENDS:
        raise PsdError(f"unknown render backend {p.backend!r}; available: {', '.join(BACKENDS)}")
    if len(pos_mm) != len(geometry):
        raise PsdError(f"poses hold {len(pos_mm)} particles but the spec has {len(geometry)}; rerun simulate")
    n = len(geometry)
    if n > MAX_PARTICLES_16BIT:
        raise PsdError(f"{n} particles do not fit a 16-bit mask (max {MAX_PARTICLES_16BIT})")
    rng = rng_for(entropy, "render")
    look = draw_look(rng, p, n, rng_for(entropy, "look"))  # the same look (colours, light, view) for every backend
    px_mm = mm_per_px(float(spec["table_size"]), p.resolution, look.view_fraction)
    rgb, mask, extra = BACKENDS[p.backend](spec, geometry, pos_mm, quats, p, look, rng)
    markings = None
    if p.markings is not None:
        rgb, markings = add_markings(rgb, mask, n, px_mm, p.markings, rng_for(entropy, "markings"))
    drawn = []
    if p.distractors is not None:
        rgb, mask, drawn = add_distractors(rgb, mask, px_mm, p.distractors, rng_for(entropy, "distractors"))
    image = apply_sensor(rgb, look, p, rng)
    look_meta = {k: v for k, v in asdict(look).items() if k != "particle_rgb"}
    meta = {
        "backend": p.backend,
        "resolution": p.resolution,
        **extra,
        "mm_per_px": px_mm,
        "table_size_mm": float(spec["table_size"]),
        "view_mm": px_mm * p.resolution,
        "camera_height_mm": p.camera_height_mm,
        "image_origin": "centred on the table; row 0 = +y edge of the view, column 0 = -x edge",
        "look": look_meta,
        "distractors": drawn,
        **({"markings": markings} if markings is not None else {}),
    }
    return image, mask, meta
