"""Photo datasets (the config's `photos`): labelled photographs brought from outside, evaluated
like the synthetic test splits though nothing here made them. A photo set is a folder of
photos, each one's scale (one number, or a CSV column), optionally its reference instance mask
and its reference d10/d50/d90 in a named size definition.

`resolve` turns a photo set's config into its files and values, checking everything a job
would otherwise trip over hours later: the folder, the photos, each photo's scale, each mask
(there, a single-channel integer image of the photo's size) and each reference row. It reads
CSVs and image headers only (no pixel is decoded), so the config check, the workflow's
preflight and the DAG's input functions call it freely; `deploy/photos.py` evaluates a model
on what it gives. Torch-free, numpy-free.
"""

from __future__ import annotations

import csv
import fnmatch
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from . import PsdError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")  # what a photo may be
STEM = "{stem}"  # the placeholder of a mask pattern: the photo's name without its suffix
REFERENCE_COLUMNS = ("d10_mm", "d50_mm", "d90_mm")  # psd.TARGETS, named here without importing numpy's users
MASK_MODES = ("I;16", "I;16B", "I;16L", "I", "L")  # single-channel integer PNG modes an instance mask may have
MAX_CSV_BYTES = 50_000_000  # a scale / reference table far larger than this is not one


@dataclass(frozen=True)
class Region:
    """The part of a photo to measure (`predict --roi`): a box in px of the photo as taken (upright,
    full size: what an image viewer shows), `left`/`top` its first column/row, `right`/`bottom` one
    past its last. The photo is read as if cropped to it: grains cut by its sides touch the edge
    (left out of the visible-grain definitions, as at the photo's border) and what lies outside (a
    scale card, a belt's edge, a boot) is not looked at; positions in the particle table stay in
    the photo's pixels."""

    left: int
    top: int
    right: int
    bottom: int

    ORDER = "LEFT and TOP must be 0 or more, RIGHT above LEFT and BOTTOM above TOP (px of the photo as taken)"

    @staticmethod
    def out_of_order(left: int, top: int, right: int, bottom: int) -> bool:
        return min(left, top) < 0 or right <= left or bottom <= top

    def __post_init__(self) -> None:
        if self.out_of_order(self.left, self.top, self.right, self.bottom):
            raise PsdError(f"--roi {self}: {self.ORDER}")

    @classmethod
    def parse(cls, text: str) -> Region:
        """'LEFT,TOP,RIGHT,BOTTOM' (px, whole numbers) → the box; PsdError naming what is wrong, after
        '--roi <text as given>: '."""
        parts = [p.strip() for p in str(text).split(",")]
        if len(parts) != 4 or not all(re.fullmatch(r"-?[0-9]+", p) for p in parts):
            raise PsdError(f"--roi {text!r}: give the box as LEFT,TOP,RIGHT,BOTTOM in px of the photo as taken "
                           "(four whole numbers, e.g. 0,0,2000,1500)")
        box = [int(p) for p in parts]
        if cls.out_of_order(*box):
            raise PsdError(f"--roi {text!r}: {cls.ORDER}")
        return cls(*box)

    def __str__(self) -> str:
        return f"{self.left},{self.top},{self.right},{self.bottom}"

    @property
    def size_hw(self) -> tuple[int, int]:
        return self.bottom - self.top, self.right - self.left

    def check(self, path: Path | str, size_hw: tuple[int, int]) -> None:
        """Refuse a box that is not inside the photo of `size_hw` (upright, full size)."""
        h, w = size_hw
        if self.right > w or self.bottom > h:
            raise PsdError(f"{path}: --roi {self} is not inside the photo ({w} x {h} px as taken, upright): its "
                           "right and bottom must be at most the photo's width and height")

    def need(self, path: Path | str,
             network_hw: Callable[[int, int], tuple[int, int]]) -> Callable[[int, int], tuple[int, int]]:
        """`read_photo`'s `need` for the whole photo, from `network_hw(h, w)`: the size the box is
        read at (checked against the photo first), scaled to the photo."""
        def whole(h: int, w: int) -> tuple[int, int]:
            self.check(path, (h, w))
            (rh, rw), (nh, nw) = self.size_hw, network_hw(*self.size_hw)
            return math.ceil(nh * h / rh), math.ceil(nw * w / rw)
        return whole

    def crop(self, image, size_hw: tuple[int, int]):
        """The box of a photo decoded as `image` (an (H, W, ...) array; its full size `size_hw`, decoded
        reduced or not), and where that part lies in the photo: (top, left, height, width) in px of the
        photo at full size — the box, rounded to the decoded pixels where the photo was decoded reduced."""
        ky, kx = image.shape[0] / size_hw[0], image.shape[1] / size_hw[1]
        r0, c0 = int(round(self.top * ky)), int(round(self.left * kx))
        r1, c1 = max(r0 + 1, int(round(self.bottom * ky))), max(c0 + 1, int(round(self.right * kx)))
        return image[r0:r1, c0:c1].copy(), (r0 / ky, c0 / kx, (r1 - r0) / ky, (c1 - c0) / kx)


@dataclass(frozen=True)
class Photo:
    """One photo of a set: its file, scale, size (as read, upright), reference mask and d-values."""

    name: str  # the file name in the set's folder: its key in the CSVs and the outputs
    path: Path
    mm_per_px: float
    size_hw: tuple[int, int]  # upright (EXIF orientation applied), as io.read_photo gives it
    mask: Path | None = None
    reference_mm: tuple[float, float, float] | None = None  # d10, d50, d90 in the set's size definition

    @property
    def stem(self) -> str:
        return Path(self.name).stem


@dataclass(frozen=True)
class PhotoSet:
    name: str
    folder: Path
    photos: tuple[Photo, ...]
    size_definition: str  # what the reference's grain sizes (and d-values) are
    has_masks: bool
    has_reference: bool
    tables: tuple[Path, ...]  # the CSVs read (scale, reference)
    auto_scale: bool | None = None  # read as predict --auto-scale / --no-auto-scale reads; None: each model's default
    outline_band_px: float | str = 0  # px the reference masks keep between touching grains, or "auto" (measured)

    def files(self) -> list[Path]:
        """Every file the set's evaluation reads: the photos, their masks and the CSVs."""
        out = [p.path for p in self.photos] + [p.mask for p in self.photos if p.mask is not None]
        return out + list(dict.fromkeys(self.tables))


def in_folder(folder: Path, name: str) -> Path:
    """A file name of a photo set's config: relative to its folder (an absolute path stays)."""
    p = Path(name)
    return p if p.is_absolute() else folder / p


def mask_name(pattern: str, photo: str) -> str:
    return pattern.replace(STEM, Path(photo).stem)


def pattern_problem(pattern: str | None) -> str | None:
    """What is wrong with a mask pattern (read without touching a file), or None."""
    if pattern is None:
        return None
    if STEM not in pattern:
        return f"{pattern!r} must hold {STEM} (the photo's name without its suffix), e.g. \"{STEM}_mask.png\""
    if "/" in pattern.replace(STEM, "") or "\\" in pattern:
        return f"{pattern!r}: a mask lies in the photos' folder; give a file name pattern, not a path"
    if Path(pattern.replace(STEM, "x")).suffix.lower() not in IMAGE_SUFFIXES:
        return f"{pattern!r} must end in an image suffix ({', '.join(IMAGE_SUFFIXES)}), e.g. .png"
    return None


def photo_files(folder: Path, images: str, masks: str | None) -> list[Path]:
    """The photos of a folder: the files `images` matches with an image suffix, less those that
    are another photo's mask (by the `masks` pattern), sorted by name."""
    found = sorted(f for f in folder.iterdir() if fnmatch.fnmatchcase(f.name, images)
                   and f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".") and f.is_file())
    if masks is None:
        return found
    mask_names = {mask_name(masks, f.name) for f in found}
    return [f for f in found if f.name not in mask_names]


def read_table(path: Path, columns: tuple[str, ...], key: str) -> dict[str, dict[str, str]]:
    """A CSV as {image file name: row}, refusing a missing file, missing columns or an image twice;
    `key` names the config key in the messages."""
    if not path.is_file():
        return _raise(f"{key}: {path}: no such file")
    if path.stat().st_size > MAX_CSV_BYTES:
        return _raise(f"{key}: {path} is {path.stat().st_size:,} bytes, far more than a table of photos")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            have = reader.fieldnames or []
            lacking = [c for c in ("image", *columns) if c not in have]
            if lacking:
                return _raise(f"{key}: {path} has no column {', '.join(lacking)} (its columns: "
                              f"{', '.join(have) or 'none'})")
            rows: dict[str, dict[str, str]] = {}
            for i, r in enumerate(reader, start=2):
                name = (r.get("image") or "").strip()
                if name in rows:
                    return _raise(f"{key}: {path} line {i}: image {name!r} has a row already")
                rows[name] = r
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        return _raise(f"{key}: {path} is not a readable CSV ({e})")
    return rows


def _raise(message: str):
    raise PsdError(message)


def _number(row: dict, column: str, where: str) -> float:
    text = (row.get(column) or "").strip()
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise PsdError(f"{where}: {column} is {text!r}, not a number > 0")
    return v


def image_header(path: Path) -> tuple[tuple[int, int], str]:
    """(upright size (h, w), PIL mode) of an image file from its header alone; a file that is
    not one is a PsdError naming it."""
    from .io import open_image

    with open_image(path) as img:
        w, h = img.size
        try:
            turned = img.getexif().get(0x0112, 1) in (5, 6, 7, 8)
        except Exception:  # a broken EXIF block: io.read_photo shows it as stored
            turned = False
        return ((w, h) if turned else (h, w)), img.mode


def resolve(name: str, spec: dict) -> PhotoSet:
    """A photo set's config (validated: defaults filled in) as its photos, every file and value
    checked; the first problem is a PsdError that starts with the config key (photos.<name>...)."""
    key = f"photos.{name}"
    folder = Path(spec["folder"])
    if not folder.is_dir():
        where = "" if folder.is_absolute() else f", relative to the working directory {Path.cwd()}"
        raise PsdError(f"{key}.folder: {folder} is not a folder ({'a file' if folder.exists() else 'no such folder'}"
                       f"{where})")
    masks = spec.get("masks")
    problem = pattern_problem(masks)
    if problem:
        raise PsdError(f"{key}.masks: {problem}")
    files = photo_files(folder, spec.get("images", "*"), masks)
    if not files:
        raise PsdError(f"{key}: no photos in {folder} (looked for {spec.get('images', '*')!r} with a suffix of "
                       f"{', '.join(IMAGE_SUFFIXES)})")
    stems: dict[str, str] = {}
    for f in files:
        if f.stem in stems:  # their masks and outputs (overlays/<stem>.png) would be one file
            raise PsdError(f"{key}: the photos {stems[f.stem]} and {f.name} share the name {f.stem!r}; rename one")
        stems[f.stem] = f.name
    tables = []
    scale = spec["mm_per_px"]
    scale_rows = None
    if isinstance(scale, dict):
        table = in_folder(folder, scale["csv"])
        scale_rows = read_table(table, (scale["column"],), f"{key}.mm_per_px.csv")
        tables.append(table)
    ref = spec.get("reference")
    ref_rows = None
    if ref is not None:
        table = in_folder(folder, ref["csv"])
        ref_rows = read_table(table, REFERENCE_COLUMNS, f"{key}.reference.csv")
        tables.append(table)
    band = spec.get("outline_band_px", 0)
    if band != 0 and masks is None:
        raise PsdError(f"{key}.outline_band_px: {band!r} describes reference masks, and the set has none "
                       "(set masks, or leave outline_band_px at 0)")
    photos = []
    for f in files:
        size_hw, _ = image_header(f)
        if scale_rows is None:
            mm = float(scale)
        else:
            row = scale_rows.get(f.name)
            if row is None:
                raise PsdError(f"{key}.mm_per_px: {tables[0]} has no row for the photo {f.name} (its scale is "
                               "unknown: add its mm per px)")
            mm = _number(row, scale["column"], f"{key}.mm_per_px: {tables[0]}, image {f.name}")
        mask = None
        if masks is not None:
            mask = folder / mask_name(masks, f.name)
            if not mask.is_file():
                raise PsdError(f"{key}.masks: the photo {f.name} has no mask {mask.name} in {folder}")
            mask_hw, mode = image_header(mask)
            if mode not in MASK_MODES:
                raise PsdError(f"{key}.masks: {mask} is a {mode} image, not an instance mask (one channel of "
                               "integer ids: a 16-bit or 8-bit grey PNG, 0 = no grain)")
            if mask_hw != size_hw:
                raise PsdError(f"{key}.masks: {mask} is {mask_hw[1]} x {mask_hw[0]} px, its photo {f.name} "
                               f"{size_hw[1]} x {size_hw[0]} px: a mask must have its photo's size")
        d = None
        if ref_rows is not None:
            row = ref_rows.get(f.name)
            where = f"{key}.reference: {tables[-1]}, image {f.name}"
            if row is None:
                raise PsdError(f"{key}.reference: {tables[-1]} has no row for the photo {f.name}")
            d = tuple(_number(row, c, where) for c in REFERENCE_COLUMNS)
            if not d[0] <= d[1] <= d[2]:
                raise PsdError(f"{where}: d10 <= d50 <= d90 does not hold ({', '.join(f'{v:g}' for v in d)})")
        photos.append(Photo(f.name, f, mm, size_hw, mask, d))
    return PhotoSet(name, folder, tuple(photos), spec.get("size_definition", "ellipse-minor"), masks is not None,
                    ref is not None, tuple(tables), spec.get("auto_scale"), band)


def resolve_all(config: dict) -> tuple[dict[str, PhotoSet], list[str]]:
    """Every photo set of a (validated) config resolved, and the problems of those that are not
    (one line each, the config key first)."""
    sets, found = {}, []
    for name, spec in (config.get("photos") or {}).items():
        try:
            sets[name] = resolve(name, spec)
        except PsdError as e:
            found.append(str(e))
    return sets, found


def check(config: dict) -> dict[str, PhotoSet]:
    """`resolve_all`, its problems (all of them) one PsdError: the config check's and the
    workflow's preflight."""
    sets, found = resolve_all(config)
    if found:
        raise PsdError("invalid photo sets:\n  " + "\n  ".join(found))
    return sets
