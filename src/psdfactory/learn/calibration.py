"""Calibration against reference samples (`psdfactory calibrate`): a per-target correction from a
model's d10/d50/d90 to reference measurements (sieve analyses, a laser diffraction) of the same
samples, as camera PSD instruments are calibrated in plants and in the field. Torch-free, pure
functions: the command's I/O is `deploy.calibrate`; `apply_calibration` is what predict calls.

The correction is fitted per target (d10, d50, d90 independently), from predicted to reference:

- below `ISOTONIC_FROM` references an affine map, ``reference = slope * predicted + intercept``
  (least squares);
- from `ISOTONIC_FROM` references on an isotonic (monotone non-decreasing) map: the isotonic
  regression of the references on the predictions, interpolated linearly between its knots and
  extrapolated outside them along the chord from its first knot to its last (a non-negative slope:
  the map stays monotone and continuous).

The correction takes one of the model's readings of each image, its *basis*: the references' own
size definition and weighting where the model reads them, else (`basis_for`) a grain finder's
grains measured in the references' weighting (a mass-weighted sieve analysis: the found grains'
volume-weighted min Feret width), else the model's own weighting of the references' definition. The
corrected d-values are of the references' definition and weighting either way.

The corrected d-values are sorted, so d10 <= d50 <= d90 holds after correction too. The
leave-one-out error (each reference predicted by the correction fitted on the others) is the
honest estimate of the calibrated error; the in-fit error flatters.

A calibrated model carries the block `calibration_block` builds in its meta (`meta["calibration"]`,
plain data: the model file and an export's meta.json hold it alike); `calibration_problems`
validates it.
"""

from __future__ import annotations

import math

import numpy as np

from .. import PsdError
from ..photoset import Region
from ..psd import GRAIN_WEIGHTINGS, NAMES, SIZE_DEFINITIONS, TARGETS

MIN_REFERENCES = 3
ISOTONIC_FROM = 10  # references from which the correction is isotonic (below: affine)
METHODS = ("affine", "isotonic")
MAX_REFERENCES = 100_000  # what a meta's block may hold (a sanity bound for validation)


# the grains' measured size a grain finder's calibration takes where the references' weighting (area, volume) is
# not one the model reads their solid definition in: the narrowest width of a grain seen from above is the size it
# passes a sieve by and its b-axis; its equivalent-circle diameter stands for the sphere's (docs/calibration.md)
FOOTPRINT_FOR = {"sieve": "feret-min", "b-axis": "feret-min", "c-axis": "feret-min", "esd": "ecd"}


def method_for(n: int) -> str:
    """The correction fitted on `n` references."""
    return "isotonic" if n >= ISOTONIC_FROM else "affine"


def basis_for(wanted: dict, can_read, own_weighting) -> dict:
    """The model's reading a calibration to references of `wanted` ({"size_definition",
    "weighting"}) corrects: `wanted` itself where the model reads it (`can_read(definition,
    weighting)`), else the footprint size of `FOOTPRINT_FOR` in the wanted weighting where it reads
    that (a grain finder), else the wanted definition in the weighting the model reads it in
    (`own_weighting(definition)`): the correction then maps one weighting to the other."""
    definition, weighting = wanted["size_definition"], wanted["weighting"]
    if can_read(definition, weighting):
        return dict(wanted)
    footprint = FOOTPRINT_FOR.get(definition)
    if footprint is not None and can_read(footprint, weighting):
        return {"size_definition": footprint, "weighting": weighting}
    return {"size_definition": definition, "weighting": own_weighting(definition)}


def basis_of(block: dict) -> dict:
    """The reading a calibration block's correction takes (`basis_for`); a block without one
    corrects the reading it gives."""
    return dict(block.get("basis") or {"size_definition": block["size_definition"], "weighting": block["weighting"]})


def basis_phrase(block: dict) -> str:
    """", corrected from its <definition> reading, <weighting>-weighted" where a block's correction
    takes another reading than the one it gives; "" where it corrects that one."""
    basis = basis_of(block)
    if (basis["size_definition"], basis["weighting"]) == (block["size_definition"], block["weighting"]):
        return ""
    return f", corrected from its {basis['size_definition']} reading, {basis['weighting']}-weighted"


# ---- references -----------------------------------------------------------------------------


def _list(names: list[str], limit: int = 8) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def check_references(names: list[str], values: np.ndarray, where: str = "the references") -> None:
    """Refuse, in one line naming the rows, references that cannot be calibrated on: fewer than
    `MIN_REFERENCES`, duplicate image names, values that are not finite or not positive, and
    d10 <= d50 <= d90 violated. `values`: N x 3 (d10, d50, d90 in mm)."""
    values = np.asarray(values, dtype=float).reshape(-1, len(TARGETS))
    if len(names) != len(values):
        raise PsdError(f"{where}: {len(names)} names for {len(values)} rows of values")
    seen: dict[str, int] = {}
    dupes = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        if seen[name] == 2:
            dupes.append(name)
    if dupes:
        raise PsdError(f"{where}: duplicate images ({_list(dupes)}): give each reference sample once")
    bad = [f"{n} ({', '.join(f'{t}={v:g}' for t, v in zip(TARGETS, row, strict=True) if not math.isfinite(v))})"
           for n, row in zip(names, values, strict=True) if not np.isfinite(row).all()]
    if bad:
        raise PsdError(f"{where}: values that are not finite numbers: {_list(bad)}")
    bad = [f"{n} ({', '.join(f'{t}={v:g}' for t, v in zip(TARGETS, row, strict=True) if v <= 0)})"
           for n, row in zip(names, values, strict=True) if (row <= 0).any()]
    if bad:
        raise PsdError(f"{where}: sizes must be positive (mm): {_list(bad)}")
    bad = [f"{n} ({', '.join(f'{v:g}' for v in row)})" for n, row in zip(names, values, strict=True)
           if not (row[0] <= row[1] <= row[2])]
    if bad:
        raise PsdError(f"{where}: d10 <= d50 <= d90 violated (columns swapped?): {_list(bad)}")
    if len(names) < MIN_REFERENCES:
        raise PsdError(f"{where}: {len(names)} reference sample(s); calibration needs at least {MIN_REFERENCES} "
                       f"(an affine correction per target; an isotonic one from {ISOTONIC_FROM} on)")


# ---- fit and apply --------------------------------------------------------------------------


def _affine(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope and intercept of y on x."""
    xm, ym = x.mean(), y.mean()
    slope = float(((x - xm) * (y - ym)).sum() / ((x - xm) ** 2).sum())
    return slope, float(ym - slope * xm)


def _isotonic(x: np.ndarray, y: np.ndarray) -> tuple[list[float], list[float], float]:
    """Knots (x increasing, y non-decreasing) of the isotonic regression of y on x (tied x pooled
    into one weighted point) and the extrapolation slope: the chord from the first knot to the last."""
    from scipy.optimize import isotonic_regression

    xs, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    ys = np.bincount(inverse, weights=y) / counts
    fitted = isotonic_regression(ys, weights=counts.astype(float), increasing=True).x
    slope = float((fitted[-1] - fitted[0]) / (xs[-1] - xs[0]))
    return [float(v) for v in xs], [float(v) for v in fitted], slope


def fit(predicted: np.ndarray, reference: np.ndarray, method: str | None = None) -> dict:
    """The correction from `predicted` to `reference` (both N x 3, d10/d50/d90 in mm) as plain data:
    {"method": "affine", "slope": [3], "intercept": [3]} or {"method": "isotonic", "x": [3 lists],
    "y": [3 lists], "slope_out": [3]}. `method`: ``method_for(N)`` when not given. A target whose
    predictions are all the same has nothing to fit a correction to, and is refused."""
    p = np.asarray(predicted, dtype=float).reshape(-1, len(TARGETS))
    r = np.asarray(reference, dtype=float).reshape(-1, len(TARGETS))
    method = method or method_for(len(p))
    if method not in METHODS:
        raise PsdError(f"calibration method {method!r}: one of {', '.join(METHODS)}")
    if len(p) != len(r) or len(p) < 2:
        raise PsdError(f"calibration: {len(p)} predictions for {len(r)} references (at least 2 each needed)")
    if not (np.isfinite(p).all() and np.isfinite(r).all()):
        raise PsdError("calibration: the predictions and references must be finite numbers")
    for k, name in enumerate(NAMES):
        if np.ptp(p[:, k]) <= 1e-9 * max(1.0, float(np.abs(p[:, k]).max())):
            raise PsdError(f"calibration: the model gives the same {name} ({p[0, k]:.4g} mm) for every reference "
                           "image: there is nothing to fit a correction to (are the reference images all alike?)")
    if method == "affine":
        pairs = [_affine(p[:, k], r[:, k]) for k in range(len(TARGETS))]
        return {"method": "affine", "slope": [a for a, _ in pairs], "intercept": [b for _, b in pairs]}
    knots = [_isotonic(p[:, k], r[:, k]) for k in range(len(TARGETS))]
    return {"method": "isotonic", "x": [k[0] for k in knots], "y": [k[1] for k in knots],
            "slope_out": [k[2] for k in knots]}


def _apply_isotonic(x: np.ndarray, knots_x: list[float], knots_y: list[float], slope: float) -> np.ndarray:
    kx, ky = np.asarray(knots_x, dtype=float), np.asarray(knots_y, dtype=float)
    out = np.interp(x, kx, ky)
    out = np.where(x < kx[0], ky[0] + slope * (x - kx[0]), out)
    return np.where(x > kx[-1], ky[-1] + slope * (x - kx[-1]), out)


def apply(params: dict, d: np.ndarray) -> np.ndarray:
    """`d` (3, or N x 3: d10/d50/d90 in mm) corrected by `params` (`fit`'s), each row sorted so that
    d10 <= d50 <= d90."""
    d = np.asarray(d, dtype=float)
    x = d.reshape(-1, len(TARGETS))
    out = np.empty_like(x)
    for k in range(len(TARGETS)):
        if params["method"] == "affine":
            out[:, k] = params["slope"][k] * x[:, k] + params["intercept"][k]
        else:
            out[:, k] = _apply_isotonic(x[:, k], params["x"][k], params["y"][k], params["slope_out"][k])
    return np.sort(out, axis=1).reshape(d.shape)


def leave_one_out(predicted: np.ndarray, reference: np.ndarray, method: str | None = None) -> np.ndarray:
    """Each reference's corrected value from the correction fitted on all the others (N x 3), with
    the method of the full fit (``method_for(N)`` when not given)."""
    p = np.asarray(predicted, dtype=float).reshape(-1, len(TARGETS))
    r = np.asarray(reference, dtype=float).reshape(-1, len(TARGETS))
    method = method or method_for(len(p))
    out = np.empty_like(p)
    for i in range(len(p)):
        keep = np.arange(len(p)) != i
        out[i] = apply(fit(p[keep], r[keep], method), p[i])
    return out


def errors(estimated: np.ndarray, reference: np.ndarray) -> dict:
    """Per target {"mape_pct": mean |error| / reference in %, "mae_mm": mean |error| in mm}."""
    e = np.asarray(estimated, dtype=float).reshape(-1, len(TARGETS))
    r = np.asarray(reference, dtype=float).reshape(-1, len(TARGETS))
    err = np.abs(e - r)
    return {name: {"mape_pct": float(100 * (err[:, k] / r[:, k]).mean()), "mae_mm": float(err[:, k].mean())}
            for k, name in enumerate(NAMES)}


def calibration_block(names: list[str], predicted: np.ndarray, reference: np.ndarray, size_definition: str,
                      weighting: str, mm_per_px: float | None, date: str, version: str,
                      basis: dict | None = None) -> dict:
    """What a calibrated model's meta holds under "calibration": the references (image, values, the
    model's uncalibrated prediction), the fitted correction, its leave-one-out, in-fit and the
    uncalibrated errors on the references, what the d-values are of, the reading the correction takes
    (`basis`, recorded where it is not that; `predicted` is of it), and when and by what it was made."""
    p = np.asarray(predicted, dtype=float).reshape(-1, len(TARGETS))
    r = np.asarray(reference, dtype=float).reshape(-1, len(TARGETS))
    check_references(list(names), r)
    method = method_for(len(p))
    params = fit(p, r, method)
    refs = [{"image": str(n), **{t: float(v) for t, v in zip(TARGETS, ref, strict=True)},
             "predicted": [float(v) for v in pred]} for n, ref, pred in zip(names, r, p, strict=True)]
    block = {"method": method, "n": len(p), "targets": list(TARGETS), "references": refs, "params": params,
             "loo": errors(leave_one_out(p, r, method), r), "fit": errors(apply(params, p), r),
             "uncalibrated": errors(p, r), "size_definition": size_definition, "weighting": weighting,
             "mm_per_px": None if mm_per_px is None else float(mm_per_px), "date": date, "version": version}
    if basis is not None and (basis["size_definition"], basis["weighting"]) != (size_definition, weighting):
        block["basis"] = {"size_definition": basis["size_definition"], "weighting": basis["weighting"]}
    return block


def calibration_warnings(block: dict) -> list[str]:
    """What a user should know about a fitted calibration: a correction that turns bigger readings
    into smaller (or equal) sizes, and one that does not beat the uncalibrated model in leave-one-out."""
    out = []
    params = block["params"]
    slopes = params["slope"] if params["method"] == "affine" else params["slope_out"]
    for name, slope in zip(NAMES, slopes, strict=True):
        if slope <= 0:
            less = "a smaller" if slope < 0 else "the same"
            out.append(f"the {name} correction has slope {slope:.3g}: a bigger reading gives {less} size; are the "
                       "references paired with the right images, and do they span a range of sizes?")
    for name in NAMES:
        loo, raw = block["loo"][name]["mape_pct"], block["uncalibrated"][name]["mape_pct"]
        if loo >= raw:
            out.append(f"{name}: the calibration does not improve on the uncalibrated model in leave-one-out "
                       f"({loo:.1f} % vs {raw:.1f} % mean absolute error): more references, or keep the uncalibrated "
                       "model")
    return out


# ---- a calibrated model -----------------------------------------------------------------------


def _num(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _nums(v: object, n: int | None = None) -> bool:
    return isinstance(v, list) and (n is None or len(v) == n) and all(map(_num, v))


def _params_problems(params: object, method: object) -> list[str]:
    if not isinstance(params, dict) or params.get("method") != method:
        return [f"calibration.params must be a dict whose method is {method!r}"]
    if method == "affine":
        if not (_nums(params.get("slope"), 3) and _nums(params.get("intercept"), 3)):
            return ["calibration.params: slope and intercept must be lists of 3 finite numbers"]
        return []
    xs, ys = params.get("x"), params.get("y")
    if not (isinstance(xs, list) and isinstance(ys, list) and len(xs) == len(ys) == 3):
        return ["calibration.params: x and y must be lists of 3 lists (one per target)"]
    if not _nums(params.get("slope_out"), 3) or any(s < 0 for s in params["slope_out"]):
        return ["calibration.params.slope_out must be 3 finite numbers >= 0"]
    for name, x, y in zip(NAMES, xs, ys, strict=True):
        if not (_nums(x) and _nums(y) and 2 <= len(x) == len(y) <= MAX_REFERENCES):
            return [f"calibration.params ({name}): x and y must be lists of the same length (2 or more) of finite "
                    "numbers"]
        if (np.diff(x) <= 0).any() or (np.diff(y) < 0).any():
            return [f"calibration.params ({name}): x must increase and y must not decrease"]
    return []


def _errors_ok(v: object) -> bool:
    return isinstance(v, dict) and all(
        isinstance(v.get(n), dict) and _num(v[n].get("mape_pct")) and _num(v[n].get("mae_mm")) for n in NAMES)


def calibration_problems(block: object) -> list[str]:
    """What is wrong with a model meta's "calibration" block (`calibration_block`'s); empty when fine."""
    if not isinstance(block, dict):
        return ["calibration must be a dict"]
    method, n = block.get("method"), block.get("n")
    if method not in METHODS:
        return [f"calibration.method must be one of {', '.join(METHODS)} (got {str(method)[:40]!r})"]
    if not (isinstance(n, int) and not isinstance(n, bool) and MIN_REFERENCES <= n <= MAX_REFERENCES):
        return [f"calibration.n must be a whole number of at least {MIN_REFERENCES} (got {str(n)[:40]!r})"]
    if block.get("size_definition") not in SIZE_DEFINITIONS or block.get("weighting") not in GRAIN_WEIGHTINGS:
        return [f"calibration.size_definition must be one of {', '.join(SIZE_DEFINITIONS)} and calibration.weighting "
                f"one of {', '.join(GRAIN_WEIGHTINGS)}"]
    if block.get("targets", list(TARGETS)) != list(TARGETS):
        return [f"calibration.targets must be {list(TARGETS)}"]
    problems = _params_problems(block.get("params"), method)
    refs = block.get("references")
    if not (isinstance(refs, list) and len(refs) == n and all(
            isinstance(r, dict) and isinstance(r.get("image"), str) and all(_num(r.get(t)) for t in TARGETS)
            for r in refs)):
        problems.append(f"calibration.references must be a list of {n} {{image, {', '.join(TARGETS)}}} entries")
    elif not all(_nums(r.get("predicted", [1.0] * 3), 3) for r in refs):
        problems.append("calibration.references: predicted must be 3 finite numbers")
    else:
        try:
            check_references([r["image"] for r in refs], np.array([[r[t] for t in TARGETS] for r in refs]),
                             "calibration.references")
        except PsdError as e:
            problems.append(str(e))
    basis = block.get("basis")  # absent: the block's own reading, checked above
    if "basis" in block and not (isinstance(basis, dict) and basis.get("size_definition") in SIZE_DEFINITIONS
                                 and basis.get("weighting") in GRAIN_WEIGHTINGS):
        problems.append(f"calibration.basis must give a size_definition ({', '.join(SIZE_DEFINITIONS)}) and a "
                        f"weighting ({', '.join(GRAIN_WEIGHTINGS)})")
    if not isinstance(block.get("auto_scale", False), bool):
        problems.append("calibration.auto_scale must be true or false (how its photos were read)")
    bad = [k for k in ("loo", "uncalibrated") if not _errors_ok(block.get(k))]
    if bad:
        problems.append(f"calibration.{' and calibration.'.join(bad)} must give mape_pct and mae_mm per target")
    if block.get("roi") is not None:
        try:
            Region.parse(block["roi"])
        except PsdError as e:
            problems.append(f"calibration.roi (the box of its photos it read): {e}")
    mm = block.get("mm_per_px")
    if mm is not None and not (_num(mm) and mm > 0):
        problems.append("calibration.mm_per_px must be a positive number or null")
    if not (isinstance(block.get("date"), str) and isinstance(block.get("version"), str)):
        problems.append("calibration.date and calibration.version must be strings")
    return problems


def calibration_note(meta: dict, what: dict) -> str | None:
    """The log's line on a calibrated model ("calibrated on N references (method), LOO error ..."),
    None for one without calibration. Refuses a reading (`what`: its size definition and weighting)
    other than the one the calibration was fitted in."""
    block = meta.get("calibration")
    if block is None:
        return None
    check_reading(block, what)
    loo = ", ".join(f"{n} {block['loo'][n]['mape_pct']:.1f} %" for n in NAMES)
    raw = ", ".join(f"{n} {block['uncalibrated'][n]['mape_pct']:.1f} %" for n in NAMES)
    scale = "" if block.get("mm_per_px") is None else f" at {block['mm_per_px']:g} mm/px"
    if block.get("roi") is not None:
        scale += f", the box {block['roi']} of each photo (predict --roi)"
    return (f"calibrated on {block['n']} references ({block['method']}, {block['size_definition']} size, "
            f"{block['weighting']}-weighted{basis_phrase(block)}{scale}, {block['date']}): LOO error (mean abs %) "
            f"{loo}; uncalibrated {raw}")


def check_reading(block: dict, what: dict) -> None:
    if (what["size_definition"], what["weighting"]) != (block["size_definition"], block["weighting"]):
        raise PsdError(f"this model is calibrated for the {block['size_definition']} size, {block['weighting']}-"
                       f"weighted; its correction does not apply to the {what['size_definition']} size, "
                       f"{what['weighting']}-weighted: predict without --size-definition and --weighting (or with "
                       f"--size-definition {block['size_definition']} --weighting {block['weighting']}), or calibrate "
                       f"the model for the {what['size_definition']} size, {what['weighting']}-weighted")


def source_reading(meta: dict, what: dict) -> dict:
    """The reading to take of an image for the d-values `what` asks: for a calibrated model the
    calibration's basis (`basis_of`; a reading other than its own refused), else `what` itself."""
    block = meta.get("calibration")
    if block is None:
        return dict(what)
    check_reading(block, what)
    return basis_of(block)


def apply_calibration(meta: dict, what: dict, d: np.ndarray) -> np.ndarray:
    """A reading's d10/d50/d90 (`d`, mm: the reading `source_reading` names) corrected by the model's
    calibration (`meta["calibration"]`); as they are for a model without one. A reading of another
    size definition or weighting than the calibration's is refused, and so is a corrected size that
    is not positive (the reading lies far below the references the correction was fitted on)."""
    block = meta.get("calibration")
    if block is None:
        return d
    check_reading(block, what)
    out = apply(block["params"], d)
    if not (np.isfinite(out).all() and (out > 0).all()):
        raw = ", ".join(f"{v:.3g}" for v in np.asarray(d, dtype=float).ravel())
        lo = min(min(r["predicted"]) for r in block["references"]) if all(
            "predicted" in r for r in block["references"]) else None
        span = f" (the references' readings start at {lo:.3g} mm)" if lo is not None else ""
        raise PsdError(f"the calibrated d-values are not positive: the reading {raw} mm lies far outside the range "
                       f"the calibration was fitted on{span}")
    return out
