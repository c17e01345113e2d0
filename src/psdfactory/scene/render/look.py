"""What both render backends share: the render settings, the look drawn per scene (light,
particle and table colours) so that both see the same one, the camera's scale, and the sensor
model that turns either backend's image into the final 8-bit RGB."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ... import PsdError
from ...config import config_fields
from .cycles import CyclesParams

Range = tuple[float, float]


@dataclass(frozen=True)
class RenderParams:
    """The config's `render` section (defaults: the schema's, config.schema.yaml)."""

    backend: str
    resolution: int
    supersample: int
    camera_height_mm: float
    # light: direction toward the light, drawn per scene
    light_azimuth_deg: Range
    light_elevation_deg: Range
    light_intensity: Range
    ambient: Range
    shadow_strength: Range
    occlusion_strength: Range
    # materials
    palette: tuple[tuple[float, float, float], ...]
    particle_brightness: Range
    particle_hue_jitter: float
    surface_detail: float
    table_rgb: tuple[float, float, float]
    table_brightness: Range
    table_texture: float
    # camera / sensor
    exposure: Range
    white_balance_jitter: float
    vignetting: Range
    blur_px: Range
    noise_sigma: Range  # read noise, fraction of full scale
    shot_noise: Range
    # the Cycles backend's settings: None where another backend renders (config.render_params
    # leaves them out of that slice, so that editing them reruns nothing)
    cycles: CyclesParams | None

    @classmethod
    def from_dict(cls, d: dict) -> RenderParams:
        kw = config_fields(cls, {"cycles": None, **d}, "render")
        for k, v in kw.items():
            if k == "cycles":
                if v is not None:
                    kw[k] = CyclesParams.from_dict(v)
                elif kw["backend"] == "cycles":
                    raise PsdError("render.backend 'cycles' needs the render.cycles settings in the slice")
            elif k == "palette":
                kw[k] = tuple(tuple(map(float, c)) for c in v)
            elif isinstance(v, list):
                kw[k] = tuple(v)
        return cls(**kw)


@dataclass
class Look:
    """The randomised look of one scene (recorded in render.json)."""

    light_dir: list[float]
    light_azimuth_deg: float
    light_elevation_deg: float
    light_intensity: float
    ambient: float
    shadow_strength: float
    occlusion_strength: float
    table_rgb: list[float]
    exposure: float
    white_balance: list[float]
    vignetting: float
    blur_px: float
    noise_sigma: float
    shot_noise: float
    particle_rgb: np.ndarray = field(repr=False)


def draw_look(rng: np.random.Generator, p: RenderParams, n: int) -> Look:

    def u(r: Range) -> float:
        return float(rng.uniform(*r))

    az, el = u(p.light_azimuth_deg), u(p.light_elevation_deg)
    a, e = math.radians(az), math.radians(el)
    light_dir = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
    palette = np.asarray(p.palette, dtype=float)
    base = palette[rng.integers(len(palette), size=n)]
    bright = rng.uniform(*p.particle_brightness, size=(n, 1))
    hue = 1 + rng.uniform(-p.particle_hue_jitter, p.particle_hue_jitter, size=(n, 3))
    rgb = np.clip(base * bright * hue, 0.02, 1.0)
    table = np.clip(np.asarray(p.table_rgb) * u(p.table_brightness), 0, 1)
    wb = 1 + rng.uniform(-p.white_balance_jitter, p.white_balance_jitter, size=3)
    return Look(
        light_dir, az, el, u(p.light_intensity), u(p.ambient), u(p.shadow_strength), u(p.occlusion_strength),
        table.tolist(), u(p.exposure), wb.tolist(), u(p.vignetting), u(p.blur_px), u(p.noise_sigma),
        u(p.shot_noise), rgb,
    )


def mm_per_px(table_size_mm: float, resolution: int) -> float:
    return table_size_mm / resolution


def apply_sensor(img: np.ndarray, look: Look, p: RenderParams, rng: np.random.Generator) -> np.ndarray:
    """The camera: exposure, white balance, vignetting, defocus and noise → uint8 RGB."""
    r = p.resolution
    yy, xx = np.mgrid[0:r, 0:r]
    rad2 = ((xx - r / 2) ** 2 + (yy - r / 2) ** 2) / (r / 2) ** 2 / 2
    wb = np.asarray(look.white_balance, dtype=np.float32)
    img = img * look.exposure * wb * (1 - look.vignetting * rad2)[..., None]
    if look.blur_px > 0.05:
        img = ndimage.gaussian_filter(img, (look.blur_px, look.blur_px, 0))
    img = np.clip(img, 0, 1)
    noise = rng.standard_normal(img.shape).astype(np.float32)
    img = img + noise * np.sqrt(look.noise_sigma**2 + look.shot_noise * img)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
