"""Configuration: schema validation with defaults (Snakemake's own validator), the checks a
schema cannot express, and the resolved slice of config that each stage depends on.

The slices are what the Snakemake rules put in their ``params``, so Snakemake's rerun
triggers fire exactly where an edit changes a stage's inputs.
"""

from __future__ import annotations

import copy
from pathlib import Path

from . import PsdError

SCHEMA = Path(__file__).with_name("config.schema.yaml")  # package data; the workflow validates with it too
DEFAULT_INPUT_SIZE = {"inception_v3": 299}  # network input px where not 224 (the design size)


def validate(config: dict) -> dict:
    """Validate in place (filling defaults) with Snakemake's validator, then the semantic checks."""
    from snakemake.exceptions import WorkflowError
    from snakemake.utils import validate as sm_validate

    try:
        sm_validate(config, str(SCHEMA), set_default=True)
    except WorkflowError as e:
        raise PsdError(f"invalid config: {_short(e)}") from None
    problems = semantic_problems(config)
    if problems:
        raise PsdError("invalid config:\n  " + "\n  ".join(problems))
    return config


def _short(e: Exception) -> str:
    """The useful part of a jsonschema error: the message and the key path."""
    cause = e
    while getattr(cause, "__cause__", None) is not None or getattr(cause, "__context__", None) is not None:
        nxt = cause.__cause__ or cause.__context__
        if nxt is None:
            break
        cause = nxt
    path = getattr(cause, "absolute_path", None) or getattr(cause, "path", None)
    msg = getattr(cause, "message", None) or str(e)
    if path:
        return f"{'.'.join(str(p) for p in path)}: {msg}"
    return msg.splitlines()[0] if msg else str(e)


def load_config(path: Path) -> dict:
    import yaml

    if not Path(path).is_file():
        raise PsdError(f"config file not found: {path}")
    try:
        config = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError as e:
        raise PsdError(f"{path} is not valid YAML: {e}") from None
    if not isinstance(config, dict):
        raise PsdError(f"{path} must hold a mapping of config keys")
    return validate(config)


def _ordered(name: str, r: list, problems: list[str], strict: bool = False) -> None:
    if (r[0] >= r[1]) if strict else (r[0] > r[1]):
        problems.append(f"{name}: [{r[0]}, {r[1]}] must have lo {'<' if strict else '<='} hi")


def semantic_problems(config: dict) -> list[str]:
    problems: list[str] = []
    for name, ds in config["datasets"].items():
        key = f"datasets.{name}"
        _ordered(f"{key}.count", ds["count"], problems)
        if ds["count"][1] > 65534:
            problems.append(f"{key}.count: at most 65534 particles fit a 16-bit mask")
        size = ds["size"]
        _ordered(f"{key}.size.mean", size["mean"], problems)
        _ordered(f"{key}.size.sigma", size["sigma"], problems)
        _ordered(f"{key}.size.bounds", size["bounds"], problems, strict=True)
        if size["sigma"][0] <= 0:
            problems.append(f"{key}.size.sigma: must be > 0, got {size['sigma']}")
        if size["bounds"][1] >= ds["table_size"] / 2:
            problems.append(
                f"{key}.size.bounds: particles up to {size['bounds'][1]} mm do not fit a "
                f"{ds['table_size']} mm table; raise table_size or lower the upper bound"
            )
        if sum(ds["split"].values()) <= 0:
            problems.append(f"{key}.split: fractions must add up to more than 0")
        sp = ds["shape_params"]
        for r in ("aspect_b", "aspect_c", "n_points"):
            if r in sp:
                _ordered(f"{key}.shape_params.{r}", sp[r], problems)
        if ds["shape"] == "mesh":
            files = sp.get("mesh_files") or []
            if not files:
                problems.append(f"{key}.shape_params.mesh_files: shape 'mesh' needs at least one mesh file")
            for f in files:
                if not Path(f).is_file():
                    problems.append(f"{key}.shape_params.mesh_files: file not found: {f}")
        elif sp.get("mesh_files"):
            problems.append(f"{key}.shape_params.mesh_files: only used with shape 'mesh' (shape is {ds['shape']!r})")
    r = config["render"]
    for k in ("light_elevation_deg", "exposure", "blur_px", "noise_sigma", "ambient"):
        _ordered(f"render.{k}", r[k], problems)
    if r["backend"] == "cycles":
        for k in ("roughness", "sun_strength", "sun_angle_deg", "sky_strength"):
            _ordered(f"render.cycles.{k}", r["cycles"][k], problems)
        for name, ds in config["datasets"].items():
            if ds["count"][1] > 32766:
                problems.append(f"datasets.{name}.count: the cycles backend takes at most 32766 particles "
                                "(Blender's object index tops out at 32767)")
    lo, hi = r["light_elevation_deg"]
    if not (0 < lo and hi <= 90):
        problems.append("render.light_elevation_deg: must lie in (0, 90]")
    t = config["train"]
    if t["dataset"] not in config["datasets"]:
        problems.append(f"train.dataset: {t['dataset']!r} is not one of the configured datasets ({', '.join(config['datasets'])})")
    else:
        split = config["datasets"][t["dataset"]]["split"]
        for s in ("train", "val"):
            if split.get(s, 0) <= 0:
                problems.append(f"datasets.{t['dataset']}.split: training needs a '{s}' fraction > 0")
    if len(set(t["architectures"])) != len(t["architectures"]):
        problems.append("train.architectures: lists an architecture twice")
    return problems


# ---- the slice of config each stage depends on ---------------------------------------------

def sample_params(config: dict, dataset: str, index: int | None = None) -> dict:
    """A dataset's sampling settings; with `index`, one scene's (else the scene runner adds it)."""
    ds = config["datasets"][dataset]
    out = {
        "seed": config["seed"],
        "dataset": dataset,
        "shape": ds["shape"],
        "shape_params": copy.deepcopy(ds["shape_params"]),
        "table_size": ds["table_size"],
        "count": list(ds["count"]),
        "size": copy.deepcopy(ds["size"]),
        "placement": copy.deepcopy(ds["placement"]),
    }
    if index is not None:
        out["index"] = int(index)
    return out


def simulate_params(config: dict) -> dict:
    return copy.deepcopy(config["physics"])


def render_params(config: dict) -> dict:
    """The render slice; the Cycles settings only when that backend renders (so editing them
    does not rerun the fast backend's renders)."""
    out = copy.deepcopy(config["render"])
    if out["backend"] != "cycles":
        out.pop("cycles", None)
    return out


def label_params(config: dict) -> dict:
    return copy.deepcopy(config["labels"])


def compare_params(config: dict) -> dict:
    """The render settings, Cycles' included, for rendering scenes with both backends."""
    return copy.deepcopy(config["render"])


def manifest_params(config: dict, dataset: str) -> dict:
    return {"split": dict(config["datasets"][dataset]["split"])}


def n_shards(config: dict, dataset: str) -> int:
    ds = config["datasets"][dataset]
    return -(-ds["n_scenes"] // ds["shard_size"])


def shard_indices(config: dict, dataset: str, shard: int) -> range:
    ds = config["datasets"][dataset]
    lo = shard * ds["shard_size"]
    return range(lo, min(lo + ds["shard_size"], ds["n_scenes"]))


def batch_indices(config: dict, dataset: str, batch: int) -> range:
    n = config["scenes_per_job"]
    return range(batch * n, min((batch + 1) * n, config["datasets"][dataset]["n_scenes"]))


def shard_batches(config: dict, dataset: str, shard: int) -> range:
    """The scene batches that hold a manifest shard's scenes."""
    rng = shard_indices(config, dataset, shard)
    n = config["scenes_per_job"]
    return range(rng.start // n, (rng.stop - 1) // n + 1)


def train_params(config: dict, arch: str) -> dict:
    t = config["train"]
    keys = ("dataset", "pretrained", "epochs", "batch_size", "lr", "weight_decay", "lr_factor", "lr_patience",
            "early_stopping_patience", "precision", "device", "aux_loss_weight", "augment")
    out = {k: t[k] for k in keys}
    out.update(arch=arch, seed=config["seed"], input_size=int(t["input_size"].get(arch, DEFAULT_INPUT_SIZE.get(arch, 224))))
    return out

