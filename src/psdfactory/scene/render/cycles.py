"""The Blender Cycles render backend, host side.

Blender as a Python module (``bpy==4.5.15``) needs numpy<2, so it lives in its own
environment and runs ``blender_job.py`` in a subprocess. This side writes the scene (meshes,
poses, the look drawn for the fast backend, Cycles settings) to a temporary folder, runs
Blender on it and reads back the image and the object-index mask.

The Blender interpreter: ``$PSD_BLENDER_PYTHON`` if set, else ``.venv-blender/bin/python``
beside this checkout (``make blender`` creates it; conda users: ``envs/blender.yaml``).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import PsdError
from ...config import MAX_PARTICLES_CYCLES, config_fields

SCRIPT = Path(__file__).with_name("blender_job.py")  # package data: run by Blender's Python, never imported
REPO = Path(__file__).resolve().parents[4]  # src/psdfactory/scene/render/cycles.py → the checkout
DEFAULT_PYTHON = REPO / ".venv-blender" / "bin" / "python"
Range = tuple[float, float]


@dataclass(frozen=True)
class CyclesParams:
    """The config's `render.cycles` section (defaults: the schema's, config.schema.yaml)."""

    samples: int
    denoise: bool
    max_bounces: int
    device: str  # auto | cpu | gpu
    threads: int  # 0 = all cores
    roughness: Range
    sun_strength: Range  # W/m²
    sun_angle_deg: Range  # apparent size of the sun: soft shadow edges
    sky_strength: Range
    sky_rgb: tuple[float, float, float]
    timeout_s: float

    @classmethod
    def from_dict(cls, d: dict) -> CyclesParams:
        kw = config_fields(cls, d, "render.cycles")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()})


def blender_python() -> Path:
    """The interpreter that has `bpy`, or a clear error saying how to get one."""
    env = os.environ.get("PSD_BLENDER_PYTHON")
    py = Path(env) if env else DEFAULT_PYTHON
    if not py.is_file():
        where = f"PSD_BLENDER_PYTHON={env}" if env else str(py)
        raise PsdError(
            f"render.backend 'cycles' needs Blender's Python module, but there is no interpreter at {where}. "
            "Create it with `make blender` (a venv with bpy==4.5.15 and numpy<2), or "
            "`conda env create -f envs/blender.yaml` and export PSD_BLENDER_PYTHON=<that env>/bin/python"
        )
    return py


def draw_cycles_look(rng: np.random.Generator, c: CyclesParams, n: int) -> dict:
    """What Cycles adds to the shared look, drawn after it so the shared part stays the same."""

    def u(r: Range) -> float:
        return float(rng.uniform(*r))

    return {
        "roughness": rng.uniform(*c.roughness, size=n),
        "sun_strength": u(c.sun_strength),
        "sun_angle_deg": u(c.sun_angle_deg),
        "sky_strength": u(c.sky_strength),
        "seed": int(rng.integers(2**31)),
    }


def cycles_job(spec: dict, geometry, pos_mm: np.ndarray, p, look, extra: dict) -> dict:
    """The scene as Blender's job reads it (scene.json): camera, table, lights, materials —
    everything of the shared look that Cycles renders, and what it draws itself (`extra`)."""
    c = p.cycles
    T = float(spec["table_size"])
    H = p.camera_height_mm
    top = float(np.nanmax(pos_mm[:, 2]) + geometry.dims_mm[:, 0].max()) if len(geometry) else 1.0
    return {
        "resolution": p.resolution,
        "camera_height_mm": H,
        "fov_deg": math.degrees(2 * math.atan(T * look.view_fraction / 2 / H)),
        "top_mm": top + 10.0,
        "table_size_mm": T,
        "table_rgb": look.table_rgb,
        "table_texture": look.table_texture,
        "ground_mm": look.ground_level_mm,
        "grain_mm": look.table_grain_mm,
        "bump_mm": look.particle_grain_mm,
        "smooth": spec["shape_type"] in ("granule", "ellipsoid"),
        "light_dir": look.light_dir,
        "light_rgb": look.light_rgb,
        "sun_strength": extra["sun_strength"] * look.light_intensity,
        "sun_angle_deg": extra["sun_angle_deg"],
        "sky_rgb": list(c.sky_rgb),
        "sky_strength": extra["sky_strength"],
        "seed": extra["seed"],
        "cycles": {"samples": c.samples, "denoise": c.denoise, "max_bounces": c.max_bounces,
                   "device": c.device, "threads": c.threads},
    }


def render_cycles(spec: dict, geometry, pos_mm: np.ndarray, quats: np.ndarray, p, look, rng: np.random.Generator):
    """→ (rgb float32 HxWx3 in [0,1] before the sensor model, uint16 mask, extra metadata)."""
    c = p.cycles
    n = len(geometry)
    if n > MAX_PARTICLES_CYCLES:
        raise PsdError(f"{n} particles: Blender's object index tops out at {MAX_PARTICLES_CYCLES + 1}; "
                       "use the tiny backend")
    py = blender_python()
    extra = draw_cycles_look(rng, c, n)
    job = cycles_job(spec, geometry, pos_mm, p, look, extra)
    with tempfile.TemporaryDirectory(prefix="psd-cycles-") as tmp:
        d = Path(tmp)
        (d / "scene.json").write_text(json.dumps(job))
        np.savez(
            d / "scene.npz",
            vertices=geometry.vertices.astype(np.float32), faces=geometry.faces.astype(np.int32),
            vert_offsets=geometry.vert_offsets, face_offsets=geometry.face_offsets,
            positions_mm=np.asarray(pos_mm, dtype=np.float64), quats_xyzw=np.asarray(quats, dtype=np.float64),
            rgb=look.particle_rgb, roughness=extra["roughness"],
            detail=np.asarray(look.surface_detail, dtype=np.float64),
        )
        try:
            r = subprocess.run([str(py), "-P", str(SCRIPT), str(d)], capture_output=True, text=True,
                               timeout=c.timeout_s)
        except subprocess.TimeoutExpired:
            raise PsdError(f"Blender did not finish within render.cycles.timeout_s = {c.timeout_s} s") from None
        if r.returncode != 0 or not (d / "result.json").is_file():
            tail = "\n".join((r.stderr or r.stdout).strip().splitlines()[-15:])
            raise PsdError(f"Blender ({py}) failed with exit code {r.returncode}:\n{tail}")
        result = json.loads((d / "result.json").read_text())
        from PIL import Image

        with Image.open(d / "image.png") as im:
            rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        mask = np.load(d / "ids.npy")
    if rgb.shape[:2] != (p.resolution, p.resolution) or mask.shape != rgb.shape[:2]:
        raise PsdError(f"Blender returned a {rgb.shape[:2]} image and a {mask.shape} mask, expected {p.resolution}²")
    if mask.size and int(mask.max()) > n:
        raise PsdError(f"Blender's object-index pass holds id {int(mask.max())} but the scene has {n} particles")
    meta = {
        "cycles": {"device": result["device"], "blender": result["blender"], "samples": c.samples,
                   "denoise": c.denoise, "max_bounces": c.max_bounces, "build_s": result["build_s"],
                   "render_s": result["render_s"]},
        "look_cycles": {k: v for k, v in extra.items() if k != "roughness"},
    }
    return rgb, mask, meta
