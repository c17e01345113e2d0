"""Thin I/O edges: atomic writes and friendly reads."""

from __future__ import annotations

import errno
import functools
import json
import logging
import os
import re
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import PsdError

if TYPE_CHECKING:
    import pyarrow
    from PIL import Image

logger = logging.getLogger(__name__)


class DiskFullError(PsdError):
    """A write failed because the filesystem it went to is full: the job stops at once (a batch
    does not go on to fail every other scene), with a message naming the disk and the file."""


# the temporary files atomic_path makes: ".<name>.<8 random characters>.tmp<suffix>" (tempfile.mkstemp)
TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp")
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name one file (the same path resolved, or one inode through links)."""
    a, b = Path(a), Path(b)
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def is_within(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether `path`, resolved, is `folder` or lies inside it (False where either cannot be looked at)."""
    try:
        return Path(path).resolve().is_relative_to(Path(folder).resolve())
    except OSError:
        return False


def current_umask() -> int:
    """The process's umask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; move it into place only if the block succeeds.

    An interrupted job therefore never leaves a half-written file under the final name. A
    failed block removes its temporary file; one left by a writer that was killed outright
    (SIGKILL) is removed by the next write of the same file. A full disk is a DiskFullError
    that names the disk and the file.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
        try:
            os.fchmod(fd, 0o666 & ~current_umask())  # mkstemp's 0600 would hide the file from the group
        finally:
            os.close(fd)
    except OSError as e:
        if disk_full(e, path.parent):
            raise DiskFullError(disk_full_message(path)) from e
        raise
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException as e:
        full = isinstance(e, Exception) and disk_full(e, path.parent)  # asked before the temporary file goes
        tmp_path.unlink(missing_ok=True)
        if full:
            raise DiskFullError(disk_full_message(path)) from e
        raise


@contextmanager
def atomic_dir(path: str | os.PathLike, what: str = "--out-dir", suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a new hidden folder beside `path` to fill; it replaces `path` (and whatever was there)
    only if the block succeeds, so the folder never holds a mix of two writes or half of one. A
    failed block removes the new folder and leaves `path` as it was. `what` names the folder in
    errors (the option that gave it)."""
    import shutil

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise PsdError(f"{what} {path} is a file; give a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent))
        stage.chmod(0o777 & ~current_umask())
    except OSError as e:
        raise PsdError(f"{what} {path}: cannot write in {path.parent} ({e.strerror})") from None
    try:
        yield stage
        old = path.with_name(stage.name + ".old")
        if path.exists():
            path.rename(old)
        try:
            stage.rename(path)
        except BaseException:
            if old.exists() and not path.exists():  # put the old folder back under its name
                old.rename(path)
            raise
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


@functools.lru_cache(maxsize=4096)
def _stale_temps(folder: str) -> dict[str, list[str]]:
    """atomic_path's temporary files in `folder` when this process first writes there, by the
    name they were for: left by a writer killed before it could rename or remove them. One
    listing per folder and process (a folder of 10,000 predicted masks is listed once)."""
    found: dict[str, list[str]] = {}
    try:
        names = os.listdir(folder)
    except OSError:
        return found
    for name in names:
        m = TEMP_NAME.match(name)
        if m:
            found.setdefault(m["name"], []).append(name)
    return found


def remove_stale_temps(path: Path) -> None:
    """Remove the temporary files that an earlier, killed writer of `path` left beside it."""
    for name in _stale_temps(str(path.parent)).pop(path.name, []):
        (path.parent / name).unlink(missing_ok=True)
        logger.debug(f"removed {path.parent / name}, left by a write of {path.name} that was killed")


# ---- a full disk ------------------------------------------------------------------------------


def disk_full(error: BaseException, folder: str | os.PathLike) -> bool:
    """Whether a write into `folder` failed because its filesystem is full: ENOSPC or EDQUOT, or,
    for libraries that do not pass the errno on (PyTorch's file writer, Arrow), a filesystem
    with no block left for this user."""
    if isinstance(error, DiskFullError):
        return False  # already said
    if isinstance(error, OSError) and error.errno in NO_SPACE or "No space left on device" in str(error):
        return True
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return (st.f_bfree if os.geteuid() == 0 else st.f_bavail) == 0


def mount_point(path: str | os.PathLike) -> Path:
    """The mount point of the filesystem that holds `path` (or would hold it)."""
    p = Path(os.path.abspath(path))
    while not p.exists() and p != p.parent:
        p = p.parent
    while not os.path.ismount(p):
        p = p.parent
    return p


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def disk_full_message(path: str | os.PathLike) -> str:
    """'No space left' naming the disk (its mount point, size and what is free) and the file."""
    where = mount_point(path)
    try:
        st = os.statvfs(where)
        size = f" ({_size(st.f_blocks * st.f_frsize)}, {_size(st.f_bavail * st.f_frsize)} free)"
    except OSError:
        size = ""
    return (f"no space left on device: the filesystem mounted at {where}{size} is full; writing {path} failed "
            "and nothing was left under its name. Free space there, or set `results:` to a folder on a larger "
            "disk, then rerun: what is done is kept")


def copy_file(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Copy a file atomically (a copy cut short never stands under the final name)."""
    import shutil

    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: str | os.PathLike, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=_json_default) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    if not path.is_file():
        raise PsdError(f"missing file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PsdError(f"{path} is not valid JSON ({e}); delete it and rerun the job that makes it") from None


def write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise PsdError(f"missing file: {path}")
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zipfile.BadZipFile, ValueError, EOFError ...
        raise PsdError(f"{path} is corrupt ({e}); delete it and rerun the job that makes it") from None


def write_parquet(path: str | os.PathLike, table: pyarrow.Table) -> None:
    import pyarrow.parquet as pq

    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")


def read_parquet(path: str | os.PathLike) -> pyarrow.Table:
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.exists():
        raise PsdError(f"missing file: {path}")
    try:  # one file: ParquetFile, not read_table, whose dataset machinery imports pandas (~0.6 s a job)
        with pq.ParquetFile(path) as f:
            return f.read()
    except Exception as e:
        raise PsdError(f"{path} is not a readable Parquet file ({e}); delete it and rerun") from None


def _arrow_array(values: Any) -> pyarrow.Array:
    """One column for `table_from_columns`: a 1-D numpy array of numbers, booleans or strings laid
    into Arrow buffers directly; anything else (a masked array too: its mask becomes nulls) through
    `pyarrow.array`."""
    import pyarrow as pa

    if not (isinstance(values, np.ndarray) and values.ndim == 1) or np.ma.isMaskedArray(values):
        return values if isinstance(values, pa.Array) else pa.array(values)
    a = values
    if a.dtype == bool:  # Arrow packs booleans into bits, least significant bit first
        return pa.Array.from_buffers(pa.bool_(), len(a), [None, pa.py_buffer(np.packbits(a, bitorder="little"))])
    if a.dtype.kind in "iuf":
        data = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("="))
        return pa.Array.from_buffers(pa.from_numpy_dtype(data.dtype), len(a), [None, pa.py_buffer(data)])
    if a.dtype.kind == "U":
        encoded = [v.encode("utf-8") for v in a.tolist()]
        offsets = np.zeros(len(encoded) + 1, dtype=np.int64)
        np.cumsum([len(b) for b in encoded], out=offsets[1:])
        if offsets[-1] < 2**31:  # a string column's 32-bit offsets
            return pa.Array.from_buffers(pa.string(), len(encoded), [None, pa.py_buffer(offsets.astype(np.int32)),
                                                                     pa.py_buffer(b"".join(encoded))])
    return pa.array(values)


def table_from_columns(columns: dict[str, Any]) -> pyarrow.Table:
    """A table of named 1-D columns, as `pyarrow.table(columns)` builds it (the same types and
    values), without its check for pandas objects: `pyarrow.table` and `pyarrow.array` import
    pandas (~0.4 s) in every scene job that writes a table. Numpy arrays of numbers, booleans and
    strings are laid into Arrow buffers directly; any other column goes through `pyarrow.array`.
    Two inputs `pyarrow.table` refuses or cuts are taken whole: a byte-swapped array (converted to
    the machine's order) and a string with a NUL character in it."""
    import pyarrow as pa

    arrays = [_arrow_array(v) for v in columns.values()]
    return pa.Table.from_arrays(arrays, names=list(columns))


def column_array(table: pyarrow.Table, name: str) -> np.ndarray:
    """A column of a table without nulls as a numpy array (a copy). pyarrow's own `to_numpy` imports
    pandas on its first call (~0.5 s of every scene job that reads a Parquet file); fixed-width
    numbers and booleans are read from their buffers instead, anything else falls back to it."""
    import pyarrow as pa

    col = table.column(name)
    if col.null_count or not (pa.types.is_boolean(col.type) or pa.types.is_integer(col.type)
                              or pa.types.is_floating(col.type)):
        return col.to_numpy()
    dtype = np.dtype(bool) if pa.types.is_boolean(col.type) else np.dtype(col.type.to_pandas_dtype())
    parts = []
    for chunk in col.chunks:
        data = chunk.buffers()[1]
        if data is None or len(chunk) == 0:
            continue
        if pa.types.is_boolean(chunk.type):  # bit-packed, least significant bit first
            bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")
            parts.append(bits[chunk.offset:chunk.offset + len(chunk)].astype(bool))
        else:
            parts.append(np.frombuffer(data, dtype=dtype, count=len(chunk), offset=chunk.offset * dtype.itemsize))
    return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)


def write_png(path: str | os.PathLike, array: np.ndarray, compress_level: int = 6) -> None:
    """RGB uint8 (H, W, 3) or 16-bit grey (H, W) uint16. `compress_level` is zlib's (PIL's
    default 6; 1 writes a photo-sized RGB image ~3x faster for ~3 % more bytes: a 3 MP overlay
    0.35 s against 1.1 s)."""
    from PIL import Image

    if array.dtype == np.uint16:
        img = Image.fromarray(array)  # mode "I;16"
    elif array.dtype == np.uint8:
        img = Image.fromarray(array)
    else:
        raise TypeError(f"write_png wants uint8 or uint16, got {array.dtype}")
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG", compress_level=compress_level)


# ---- particle meshes: a user's own shapes (shape 'mesh') ----------------------------------------


def _open_edges(mesh) -> int:
    """Edges that border only one face: the rim of a hole or of an open surface."""
    import trimesh

    return len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))


def solid_problem(mesh) -> str | None:
    """Why a triangle mesh is not a closed solid with a positive volume (what a particle must
    be: the physics and the labels need its volume), or None."""
    if not mesh.is_watertight:
        n = _open_edges(mesh)
        holes = (f"{n} edge{'s' * (n != 1)} border{'s' * (n == 1)} only one face" if n
                 else "some edges border more than two faces")
        return (f"is not a closed solid ({holes}: an open surface or holes), so it has no volume. Close it "
                "(e.g. Blender: Select All, Mesh > Clean Up > Fill Holes; or trimesh's fill_holes) and export it again")
    if not mesh.is_winding_consistent:
        return ("is not consistently oriented (some faces point inwards, some outwards), so its volume is not "
                "defined. Recalculate its normals (Blender: Mesh > Normals > Recalculate Outside) and export it again")
    volume = float(mesh.volume)
    if not volume > 0:  # NaN too
        if volume < 0:
            return (f"is inside out: its faces point inwards (volume {volume:.4g} < 0). Flip its normals "
                    "(Blender: Mesh > Normals > Recalculate Outside) and export it again")
        return "has no volume (a flat or collapsed surface): a particle must be a solid"
    return None


def read_mesh(path: str | os.PathLike, max_faces: int):
    """A user's particle mesh file (OBJ/STL/PLY/GLB, loaded with trimesh, vertices merged) as a
    trimesh.Trimesh that is a closed, outward-facing solid with a positive volume and at most
    `max_faces` triangles; otherwise a PsdError naming the file and what is wrong with it."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise PsdError(f"particle mesh file not found: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # trimesh divides by a zero volume
            mesh = trimesh.load(path, force="mesh")
    except Exception as e:
        raise PsdError(f"could not read particle mesh {path}: {e}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise PsdError(f"particle mesh {path} holds no triangles")
    if len(mesh.faces) > max_faces:
        raise PsdError(f"particle mesh {path} has {len(mesh.faces)} faces; decimate it to at most {max_faces} "
                       "(every particle of every scene stores its own copy)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        problem = solid_problem(mesh)
    if problem:
        raise PsdError(f"particle mesh {path} {problem}")
    return mesh


# ---- images: one reader for the factory's own PNGs and for any photo given to predict ---------

REDUCE_ABOVE_PIXELS = 4_000_000  # a photo larger than this is decoded reduced (read_photo)
SIXTEEN_BIT = ("I;16", "I;16B", "I;16L", "I;16N")
# EXIF orientation → the transpose that shows the image upright (as PIL.ImageOps.exif_transpose)
ORIENTATION = {2: "FLIP_LEFT_RIGHT", 3: "ROTATE_180", 4: "FLIP_TOP_BOTTOM", 5: "TRANSPOSE", 6: "ROTATE_270",
               7: "TRANSVERSE", 8: "ROTATE_90"}


def pixel_limit() -> int:
    """The most pixels an image may have: PIL's decompression-bomb limit (Image.MAX_IMAGE_PIXELS)."""
    from PIL import Image

    return int(Image.MAX_IMAGE_PIXELS or 2**62)


def not_a_file(path: Path) -> str | None:
    """Why `path` cannot be read as a file, in words (None when it is a regular file): missing, a
    folder, a FIFO, a device, a socket, a loop of symbolic links, a name too long, no permission."""
    import stat

    try:
        st = path.stat()
    except FileNotFoundError:
        return "missing image (no such file)" if not path.is_symlink() else "a symbolic link to nothing"
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "a loop of symbolic links, not an image"
        if e.errno == errno.ENAMETOOLONG:
            return "the file name is too long for this filesystem"
        if e.errno in (errno.EACCES, errno.EPERM):
            return "cannot be read: permission denied"
        if e.errno == errno.ENOTDIR:
            return "missing image (a part of its path is a file, not a folder)"
        return f"cannot be read ({e.strerror})"
    mode = st.st_mode
    if stat.S_ISREG(mode):
        return None
    kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode)
            else "not a regular file")
    return f"{kind}, not an image file"


@contextmanager
def open_image(path: str | os.PathLike, max_pixels: int | None = None) -> Iterator[Image.Image]:
    """An image opened lazily: only its header is read, and its size is checked against
    `max_pixels` (default: `pixel_limit()`) before a single pixel is decoded, so a decompression
    bomb is refused at once. Any failure — missing, unreadable, empty, not an image, truncated,
    too large — is a PsdError naming the file and the reason (also for what the block decodes)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    limit = max_pixels or pixel_limit()
    bomb = (f"{path} refused: its header declares {{}} pixels, more than the limit of {limit:,} (a decompression "
            "bomb, or an image far larger than a photo); nothing was decoded — crop or downscale it")
    problem = not_a_file(path)
    if problem:
        raise PsdError(f"{path}: {problem}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(path)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        found = re.search(r"\((\d+) pixels\)", str(e))  # PIL: "Image size (N pixels) exceeds limit of ..."
        raise PsdError(bomb.format(f"{int(found.group(1)):,}" if found else f"more ({e})")) from None
    except PermissionError as e:
        raise PsdError(f"{path} cannot be read: permission denied ({e.strerror or e})") from None
    except UnidentifiedImageError:
        what = "an empty file (0 bytes)" if path.stat().st_size == 0 else "not an image format PIL can read"
        raise PsdError(f"{path} is not a readable image: {what}") from None
    except (OSError, SyntaxError, ValueError, EOFError) as e:
        raise PsdError(f"{path} is not a readable image ({e})") from None
    with img:
        w, h = img.size
        if w * h > limit:
            raise PsdError(bomb.format(f"{w} x {h} = {w * h:,}"))
        try:
            yield img
        except (OSError, SyntaxError, ValueError, EOFError, IndexError, Image.DecompressionBombError) as e:
            reason = "truncated: the file ends before the image does" if "truncated" in str(e) else str(e)
            raise PsdError(f"{path} is not a readable image ({reason})") from None
        except MemoryError:
            raise PsdError(f"{path}: not enough memory to decode {w} x {h} pixels") from None


def read_png(path: str | os.PathLike) -> np.ndarray:
    """The factory's own images, pixel for pixel: RGB uint8 (H, W, 3), or a 16-bit mask as
    uint16 (H, W)."""
    with open_image(path) as img:
        img.load()
        if img.mode in SIXTEEN_BIT + ("I",):
            return np.asarray(img).astype(np.uint16)
        return np.asarray(img.convert("RGB"))


def reduce_factor(size_hw: tuple[int, int], need_hw: tuple[int, int] | None,
                  reduce_above: int = REDUCE_ABOVE_PIXELS) -> int:
    """By how much a photo of `size_hw` may be shrunk (an integer) while keeping at least twice
    the pixels the caller needs on each axis; 1 for images up to `reduce_above` pixels (read
    as they are)."""
    h, w = size_hw
    if need_hw is None or h * w <= reduce_above:
        return 1
    return max(1, int(min(h / max(need_hw[0], 1), w / max(need_hw[1], 1)) // 2))


def to_rgb8(img: Image.Image, path: Path) -> np.ndarray:
    """Any decoded PIL image as RGB uint8 (H, W, 3): 16-bit scaled to 8 (÷257), greyscale and
    palettes expanded, CMYK converted, an alpha channel dropped."""
    if img.mode == "I":
        a = np.asarray(img).astype(np.float32)
        hi = 65535.0 if a.max(initial=0) <= 65535 else float(a.max())
        grey = np.rint(np.clip(a, 0, None) * (255.0 / hi)).astype(np.uint8)
        return np.repeat(grey[:, :, None], 3, axis=2)
    if img.mode == "F":
        raise PsdError(f"{path} has 32-bit float pixels (not a camera image): save it as an 8- or 16-bit image")
    return np.asarray(img.convert("RGB"))


def read_photo(path: str | os.PathLike, need=None, max_pixels: int | None = None,
               reduce_above: int | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """Any image file as an upright RGB uint8 (H, W, 3) array, and its upright size (H, W) as
    stored. `need(h, w)` → the (height, width) the caller will resize it to: a photo larger than
    `reduce_above` pixels is decoded reduced (JPEG: at 1/2, 1/4 or 1/8 scale in the decoder,
    `Image.draft`; other formats: `Image.reduce` of the 8-bit pixels), keeping at least twice
    what is needed, so no full-size float copy is ever made. The EXIF orientation is applied."""
    from PIL import Image

    with open_image(path, max_pixels) as img:
        try:
            orientation = img.getexif().get(0x0112, 1)
        except Exception:  # a broken EXIF block: show the image as stored
            orientation = 1
        w, h = img.size
        upright = (w, h) if orientation in (5, 6, 7, 8) else (h, w)
        above = REDUCE_ABOVE_PIXELS if reduce_above is None else reduce_above
        k = reduce_factor(upright, need(*upright) if need else None, above)
        tw, th = -(-w // k), -(-h // k)  # the stored image's size reduced by k, rounded up
        if k > 1 and img.format == "JPEG":
            img.draft("RGB", (tw, th))  # the decoder scales by 1/2, 1/4 or 1/8, never below (tw, th)
        img.load()
        if img.mode in SIXTEEN_BIT:
            img = img.convert("I")
        elif img.mode in ("1", "P", "PA"):
            img = img.convert("RGB")
        r = min(img.size[0] // tw, img.size[1] // th)  # what the decoder has not reduced yet
        if r > 1:
            img = img.reduce(r)
        if orientation in ORIENTATION:
            img = img.transpose(getattr(Image.Transpose, ORIENTATION[orientation]))
        return to_rgb8(img, Path(path)), upright


def pyplot():
    """matplotlib's pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> None:
    """Write a matplotlib figure as PNG atomically, then free it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    pyplot().close(fig)
