"""Configuration: schema validation with defaults (Snakemake's own validator), the checks a
schema cannot express, and the resolved slice of config that each stage depends on.

The slices are what the Snakemake rules put in their ``params``, so Snakemake's rerun
triggers fire exactly where an edit changes a stage's inputs.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path

from . import PsdError

SCHEMA = Path(__file__).with_name("config.schema.yaml")  # package data; the workflow validates with it too

# What a scene's files can hold: checked here when a config is read, and where the files are made.
MAX_PARTICLES_16BIT = 65534  # particles that a 16-bit mask.png holds (0 = table, particle k is k + 1)
MAX_PARTICLES_CYCLES = 32766  # Blender's object index (pass_index) is a signed 16-bit value, at most 32767
MAX_MESH_FACES = 5000  # triangles of a user's particle mesh (every particle of every scene stores its own copy)

DESIGN_INPUT_SIZE = 224  # network input px of the torchvision models
# where the design size differs; for the instance estimator: its training crops (it runs on whole images)
DEFAULT_INPUT_SIZE = {"inception_v3": 299, "instances": 128}
MIN_INPUT_SIZE = {"inception_v3": 75}  # the smallest input (px) an architecture accepts where not 32
# psdfactory predict --tile: the side (px at the network's scale) of the tiles an image too large for one pass is
# run in by an estimator whose outputs are maps (~1.2 GB for the instance network on a CPU)
PREDICT_TILE_PX = 1024
# predict's first look at a photo, as a factor of the model's scale: how large its grains look there (deploy/predict
# choose_scale); training records how large its validation grains look at it (meta grain_px_probe_max) and at which
# factor (grain_px_probe_scale). Half the scale, not a quarter: at a quarter the validation grains are a few px and
# their reference depends on the look trained on (docs/experiments.md, "The automatic scale's first look").
AUTO_SCALE_PROBE = 0.5
# models trained before the factor was recorded probed at a quarter of the scale: they keep doing so
LEGACY_AUTO_SCALE_PROBE = 0.25
# a photo is read coarser only where its grains look this much larger at the probe than the largest validation
# image's: between what in-range scenes and scenes of 3x larger grains read there (the same entry)
AUTO_SCALE_MARGIN = 1.25
PREDICT_RUNTIMES = ("auto", "torch", "onnx")  # what runs a model.pt's network in predict (deploy/fastpath.py)


def default_input_size(arch: str) -> int:
    """The network input px of an architecture where train.input_size does not set it."""
    return DEFAULT_INPUT_SIZE.get(arch, DESIGN_INPUT_SIZE)


def min_input(arch: str) -> int:
    """The smallest input (px) `arch` accepts."""
    return MIN_INPUT_SIZE.get(arch, 32)


def inception_aux_fits(size: int) -> bool:
    """InceptionV3's auxiliary head needs a 17×17 Mixed_6e map, i.e. an input of at least 299 px."""
    x = (size - 3) // 2 + 1 - 2  # Conv2d_1a (s2), Conv2d_2a
    x = (x - 3) // 2 + 1 - 2  # maxpool, Conv2d_4a
    x = (x - 3) // 2 + 1  # maxpool
    x = (x - 3) // 2 + 1  # Mixed_6a (s2)
    return (x - 5) // 3 + 1 >= 5


def input_size_problem(arch: str, size: int) -> str | None:
    """What is wrong with `size` px as `arch`'s input (train.input_size), or None."""
    if size < min_input(arch):
        return f"train.input_size.{arch} = {size} is below the {min_input(arch)} px that {arch} accepts"
    return None


def crop_problem(arch: str, crop: int, size: int) -> str | None:
    """What is wrong with `crop` px windows (train.crop) for a CNN regressor `arch` at input `size`, or None."""
    if crop <= 0 or crop >= size:
        return None  # off, or the whole image
    if crop < min_input(arch):
        return (f"train.crop = {crop} is below the {min_input(arch)} px that {arch} accepts; set train.crop to 0 "
                f"(off) or at least {min_input(arch)}")
    if arch == "inception_v3" and inception_aux_fits(size) and not inception_aux_fits(crop):
        return (f"train.crop = {crop}: inception_v3 at {size} px trains its auxiliary head, which needs windows "
                f"of at least 299 px; set train.crop to 0 (off), at least 299, or train.input_size.inception_v3 "
                f"below 299 (the head is then dropped)")
    return None


def config_fields(cls, params: dict, key: str) -> dict:
    """`params` (a config slice: the settings under `key`) as the keyword arguments of the
    dataclass `cls`, which has one field per setting and no defaults of its own: the defaults
    are the schema's, filled in when the config is validated. A key too many or too few is an
    error that names it."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown, missing = sorted(set(params) - names), sorted(names - set(params))
    if unknown:
        raise PsdError(f"unknown {key} setting{'s' * (len(unknown) > 1)}: {', '.join(unknown)}")
    if missing:
        raise PsdError(f"{key} lacks {', '.join(missing)}: pass the validated config's slice "
                       "(psdfactory.config: sample_params, simulate_params, ...)")
    return dict(params)


def validate(config: dict) -> dict:
    """Validate in place (filling defaults) with Snakemake's validator, then the semantic checks."""
    from snakemake.exceptions import WorkflowError
    from snakemake.utils import validate as sm_validate

    extra = [f"datasets.{n}: a re-render takes its scenes from its source; "
             f"drop {', '.join(sorted(set(ds) - RERENDER_KEYS))}"
             for n, ds in (config.get("datasets") or {}).items()
             if isinstance(ds, dict) and "rerender_of" in ds and set(ds) - RERENDER_KEYS]
    if object_size(config) > MAX_YAML_NODES:
        raise PsdError(f"invalid config: it expands (through YAML aliases) to more than {MAX_YAML_NODES:,} values; "
                       "write it out without them")
    extra += non_finite(config)
    if extra:
        raise PsdError("invalid config:\n  " + "\n  ".join(extra))
    try:
        sm_validate(config, str(SCHEMA), set_default=True)
    except WorkflowError as e:
        raise PsdError(f"invalid config: {_short(e)}") from None
    problems = size_problems(config) or rerender_problems(config) or resolve_datasets(config)
    problems = problems or semantic_problems(config)
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


def apply_settings(raw: dict, settings: list[str], settable: tuple[str, ...]) -> dict:
    """`raw` (a config as read, before validation) with each KEY=VALUE of `settings` set: KEY dotted
    under one of the `settable` prefixes (e.g. "train."), VALUE parsed as YAML (bench scripts' --set)."""
    import yaml

    for item in settings:
        key, sep, value = item.partition("=")
        if not sep or not key.startswith(settable) or key in settable:
            raise PsdError(f"--set {item!r}: give KEY=VALUE with a key under {' or '.join(s[:-1] for s in settable)}")
        *parents, leaf = key.split(".")
        node = raw
        for k in parents:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise PsdError(f"--set {item!r}: {k} is not a section of the config")
        try:
            node[leaf] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            raise PsdError(f"--set {item!r}: the value is not YAML ({str(e).splitlines()[0]})") from None
    return raw


def load_config(path: Path, edit: Callable[[dict], dict] | None = None) -> dict:
    """The config file, validated (schema defaults filled in); `edit` changes the raw mapping
    first (e.g. bench/seed_spread.py's --set)."""
    import yaml

    if not Path(path).is_file():
        raise PsdError(f"config file not found: {path}")
    try:
        config = read_yaml(path) or {}
    except yaml.YAMLError as e:
        raise PsdError(f"{path} is not valid YAML: {str(e)[:500]}") from None
    if not isinstance(config, dict):
        raise PsdError(f"{path} must hold a mapping of config keys")
    config = edit(config) if edit else config  # its own errors name what was edited, not the file
    try:
        return validate(config)
    except PsdError as e:
        raise PsdError(f"{path}: {e}") from None


def _ordered(name: str, r: list, problems: list[str], strict: bool = False) -> None:
    if (r[0] >= r[1]) if strict else (r[0] > r[1]):
        problems.append(f"{name}: [{r[0]}, {r[1]}] must have lo {'<' if strict else '<='} hi")


# ---- per-dataset render settings and re-render datasets -------------------------------------

# render sections drawn over a share of the scenes or particles (`probability`), off at 0
SHARE_DRAWS = ("markings", "distractors")
MAX_YAML_NODES = 100_000  # a config file expanded through its aliases: more is a "billion laughs", not a config
MAX_SCENE_JOBS = 250_000  # stage jobs the DAG may hold (4 per batch of scenes_per_job scenes; bench/dag_scale.py)
REPO = Path(__file__).resolve().parents[2]  # the source checkout, when the package runs from one
SOURCE_FOLDERS = ("src", "rules", "workflow", "config", "tests", "slurm", "envs", "bench", ".git")


def _expanded_size(node, limit: int, memo: dict | None = None) -> int:
    """Nodes of a composed YAML document as its aliases expand it (an alias counts its target's
    whole size each time), stopping past `limit`."""
    import yaml

    memo = {} if memo is None else memo
    if id(node) in memo:
        return memo[id(node)]
    memo[id(node)] = 1  # a node that holds itself counts once
    if isinstance(node, yaml.SequenceNode):
        kids = node.value
    elif isinstance(node, yaml.MappingNode):
        kids = [n for pair in node.value for n in pair]
    else:
        kids = []
    n = 1
    for k in kids:
        n += _expanded_size(k, limit, memo)
        if n > limit:
            break
    memo[id(node)] = n
    return n


def read_yaml(path: Path) -> object:
    """A YAML file as Python data, refusing what no config holds: bytes that are not UTF-8, a key
    twice in one mapping, and aliases that expand past MAX_YAML_NODES nodes (never expanded here)."""
    import yaml

    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise PsdError(f"{path} is not UTF-8 text (byte {e.start}); save it as UTF-8") from None

    class Loader(yaml.SafeLoader):
        pass

    def mapping(loader, node, deep=False):
        seen = {}
        for k, _ in node.value:
            key = loader.construct_object(k, deep=True)
            if isinstance(key, str) and key != "<<" and key in seen:
                raise PsdError(f"{path}: key {key!r} appears twice in one mapping (lines {seen[key]} and "
                               f"{k.start_mark.line + 1}); keep one")
            seen[key] = k.start_mark.line + 1
        return loader.construct_mapping(node, deep=deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    loader = Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        try:
            size = _expanded_size(node, MAX_YAML_NODES)
        except RecursionError:
            raise PsdError(f"{path} is nested too deeply to be a config") from None
        if size > MAX_YAML_NODES:
            raise PsdError(f"{path}: its YAML aliases expand to more than {MAX_YAML_NODES:,} values; "
                           "write the config out without them")
        return loader.construct_document(node)
    finally:
        loader.dispose()


def object_size(obj: object, limit: int = MAX_YAML_NODES, memo: dict | None = None) -> int:
    """Values in a config as its shared parts (YAML aliases: one object in several places) expand
    it, stopping past `limit`: what a schema check or a printout would walk."""
    memo = {} if memo is None else memo
    if not isinstance(obj, dict | list):
        return 1
    if id(obj) in memo:
        return memo[id(obj)]
    memo[id(obj)] = 1
    n = 1
    for v in (obj.values() if isinstance(obj, dict) else obj):
        n += object_size(v, limit, memo)
        if n > limit:
            break
    memo[id(obj)] = n
    return n


def non_finite(config: object, path: str = "", seen: set | None = None) -> list[str]:
    """Where a config holds NaN or an infinity (YAML's .nan, .inf), which no setting accepts.
    A part shared by several keys (a YAML alias) is looked at once."""
    import math

    seen = set() if seen is None else seen
    if isinstance(config, float) and not math.isfinite(config):
        return [f"{path or 'the config'}: {config} is not a finite number"]
    if not isinstance(config, dict | list) or id(config) in seen:
        return []
    seen.add(id(config))
    if isinstance(config, dict):
        return [p for k, v in config.items() for p in non_finite(v, f"{path}.{k}" if path else str(k), seen)]
    return [p for i, v in enumerate(config) for p in non_finite(v, f"{path}[{i}]", seen)]


def results_problems(results: str) -> list[str]:
    """Why a results root cannot be used: empty, the filesystem root, the home folder itself, or
    one of this source checkout's own folders (outputs would mix with the code)."""
    if not str(results).strip():
        return ["results: must name a folder (e.g. results)"]
    root = Path(results).expanduser().resolve()
    if root == Path(root.anchor):
        return [f"results: {results!r} is the filesystem root; name a folder for the outputs"]
    if root == Path.home().resolve():
        return [f"results: {results!r} is the home folder itself; name a folder inside it"]
    if (REPO / "Snakefile").is_file():
        for name in SOURCE_FOLDERS:
            src = REPO / name
            if root == REPO or root == src or root.is_relative_to(src):
                return [f"results: {results!r} is {'the source checkout' if root == REPO else src}; outputs would "
                        "mix with the code: use e.g. results/"]
    return []


RERENDER_KEYS = {"rerender_of", "render", "n_scenes", "shard_size"}  # what a re-render may set itself


def _merged(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def rerender_problems(config: dict) -> list[str]:
    """Checks of re-render datasets that must see the keys as the user gave them (before the
    schema's defaults are filled in, a dataset's own count or size would be indistinguishable)."""
    problems = []
    for name, ds in config["datasets"].items():
        src = ds.get("rerender_of", {}).get("dataset")
        if src is None:
            continue
        key = f"datasets.{name}.rerender_of"
        if src not in config["datasets"]:
            problems.append(f"{key}.dataset: {src!r} is not one of the configured datasets")
        elif "rerender_of" in config["datasets"][src]:
            problems.append(f"{key}.dataset: {src!r} is itself a re-render; name the dataset it re-renders")
        else:
            for split in rerender_splits(ds):
                if split not in config["datasets"][src]["split"]:
                    problems.append(f"{key}.split: {src!r} has no split {split!r} "
                                    f"(its splits: {', '.join(config['datasets'][src]['split'])})")
    return problems


def rerender_splits(ds: dict) -> list[str]:
    """The source splits a re-render dataset takes its scenes from (`rerender_of.split`: one name or a list)."""
    split = ds["rerender_of"].get("split", "test")
    return [split] if isinstance(split, str) else list(split)


def dataset_splits(config: dict, dataset: str) -> set[str]:
    """The splits a dataset's scenes fall in: those with a fraction > 0, of a re-render the source
    splits it takes (each scene keeps its source's split)."""
    ds = config["datasets"][dataset]
    if "rerender_of" in ds:
        return set(rerender_splits(ds))
    return {name for name, f in ds["split"].items() if f > 0}


def resolve_datasets(config: dict) -> list[str]:
    """Fill in each dataset's own `render` (the top-level one with its overrides, validated like
    it) and a re-render's scene settings (its source's), its scene count and its split."""
    from snakemake.exceptions import WorkflowError
    from snakemake.utils import validate as sm_validate

    problems = []
    for name, ds in config["datasets"].items():
        if "render" in ds:
            merged = {"datasets": {"x": {"n_scenes": 1}}, "render": _merged(config["render"], ds["render"])}
            try:
                sm_validate(merged, str(SCHEMA), set_default=True)
            except WorkflowError as e:
                problems.append(f"datasets.{name}.{_short(e)}")
                continue
            ds["render"] = merged["render"]
        if "rerender_of" not in ds:
            continue
        src = config["datasets"][ds["rerender_of"]["dataset"]]
        for k in ("shape", "shape_params", "shape_library", "table_size", "count", "size", "placement"):
            ds[k] = copy.deepcopy(src[k])
        n = len(source_indices(config, name, cap=False))
        ds["n_scenes"] = min(ds.get("n_scenes", n), n)
        # the source's fractions: each scene keeps its source's split (assign_split of the same random stream)
        ds["split"] = copy.deepcopy(src["split"])
        if ds["n_scenes"] == 0:
            problems.append(f"datasets.{name}.rerender_of: {ds['rerender_of']['dataset']!r} has no "
                            f"{' or '.join(map(repr, rerender_splits(ds)))} scenes to re-render")
    return problems


def dataset_render(config: dict, dataset: str) -> dict:
    """The render settings of one dataset (its own, or the top-level ones)."""
    return config["datasets"][dataset].get("render") or config["render"]


def source_indices(config: dict, dataset: str, cap: bool = True) -> list[int]:
    """A re-render's scenes: the indices of its source's scenes in the chosen splits (known from
    each scene's random stream, before any scene exists), in order, at most n_scenes of them."""
    ds = config["datasets"][dataset]
    r = ds["rerender_of"]
    src = config["datasets"][r["dataset"]]
    fractions = tuple(sorted(src["split"].items()))
    idx = sorted(i for split in rerender_splits(ds)
                 for i in _split_indices(config["seed"], r["dataset"], src["n_scenes"], fractions, split))
    return idx[: ds["n_scenes"]] if cap else idx


@functools.lru_cache(maxsize=64)
def _split_indices(seed: int, dataset: str, n: int, fractions: tuple, split: str) -> tuple[int, ...]:
    from .seeding import assign_split, scene_entropy

    fr = dict(fractions)
    return tuple(i for i in range(n) if assign_split(scene_entropy(seed, dataset, i), fr) == split)


def mesh_file_problem(path: str) -> str | None:
    """Why a user's particle mesh cannot be used (missing, unreadable, not a closed solid, no
    volume, too many faces), or None: checked when the config is read, before any scene."""
    if not Path(path).is_file():
        return f"file not found: {path}"
    stat = Path(path).stat()
    return _mesh_problem(path, str(Path(path).resolve()), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=64)
def _mesh_problem(path: str, resolved: str, mtime_ns: int, size: int) -> str | None:
    """mesh_file_problem, read once per file version (the Snakefile is parsed more than once)."""
    from .io import read_mesh

    try:
        read_mesh(path, MAX_MESH_FACES)
    except PsdError as e:
        return str(e)
    return None


def size_problems(config: dict) -> list[str]:
    """A workflow too large to plan, found by arithmetic before any planning (or listing of scenes)."""
    n = [int(ds.get("n_scenes") or 0) for ds in config["datasets"].values()]
    per_job = config["scenes_per_job"]
    jobs = sum(4 * -(-k // per_job) for k in n)
    if jobs <= MAX_SCENE_JOBS:
        return []
    return [f"datasets: {sum(n):,} scenes make {jobs:,} scene jobs (4 per batch of scenes_per_job = {per_job}), more "
            f"than the {MAX_SCENE_JOBS:,} a workflow can plan; raise scenes_per_job to at least "
            f"{-(-4 * sum(n) // MAX_SCENE_JOBS)}"]


def semantic_problems(config: dict) -> list[str]:
    problems: list[str] = results_problems(config["results"])
    for name, ds in config["datasets"].items():
        key = f"datasets.{name}"
        _ordered(f"{key}.count", ds["count"], problems)
        if ds["count"][1] > MAX_PARTICLES_16BIT:
            problems.append(f"{key}.count: at most {MAX_PARTICLES_16BIT} particles fit a 16-bit mask")
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
            if "rerender_of" not in ds:  # a re-render's meshes are its source's, checked there
                problems += [f"{key}.shape_params.mesh_files[{i}]: {p}" for i, f in enumerate(files)
                             if (p := mesh_file_problem(f))]
            if ds["shape_library"]:
                problems.append(f"{key}.shape_library: shape 'mesh' draws from its mesh files; set it to 0 "
                                "(a library is for the generated families)")
        elif sp.get("mesh_files"):
            problems.append(f"{key}.shape_params.mesh_files: only used with shape 'mesh' (shape is {ds['shape']!r})")
    renders = [("render", config["render"])] + [(f"datasets.{n}.render", ds["render"])
                                                for n, ds in config["datasets"].items() if "render" in ds]
    for key, r in renders:
        for k in ("light_elevation_deg", "exposure", "blur_px", "noise_sigma", "ambient", "view_fraction",
                  "surface_detail", "particle_grain_mm", "table_texture", "table_grain_mm", "ground_level_mm",
                  "light_tint", "jpeg_quality"):
            _ordered(f"{key}.{k}", r[k], problems)
        for sub in SHARE_DRAWS:  # every [lo, hi] range of these sections
            for k, v in (r.get(sub) or {}).items():
                if k != "kinds" and isinstance(v, list) and len(v) == 2:
                    _ordered(f"{key}.{sub}.{k}", v, problems)
        lo, hi = r["light_elevation_deg"]
        if not (0 < lo and hi <= 90):
            problems.append(f"{key}.light_elevation_deg: must lie in (0, 90]")
        if r["backend"] == "cycles":
            for k in ("roughness", "sun_strength", "sun_angle_deg", "sky_strength"):
                _ordered(f"{key}.cycles.{k}", r["cycles"][k], problems)
    for name, ds in config["datasets"].items():
        if dataset_render(config, name)["backend"] == "cycles" and ds["count"][1] > MAX_PARTICLES_CYCLES:
            problems.append(f"datasets.{name}.count: the cycles backend takes at most {MAX_PARTICLES_CYCLES} "
                            f"particles (Blender's object index tops out at {MAX_PARTICLES_CYCLES + 1})")
    t = config["train"]
    _ordered("train.scale_augment", t["scale_augment"], problems)
    problems += training_datasets_problems(config, "train.datasets", t["datasets"])
    for arch, own in estimator_datasets(config).items():  # train.instances.datasets, listed architecture or not
        problems += training_datasets_problems(config, f"train.{arch}.datasets", own)
    for arch, section in t.items():  # train.instances.calibration_datasets: some of what it trains on
        names = section.get("calibration_datasets") if isinstance(section, dict) else None
        if names is not None:
            own, key = section.get("datasets") or t["datasets"], f"train.{arch}.calibration_datasets"
            outside = [f"{key}: {d!r} is not one of the datasets it trains on ({', '.join(own)}: "
                       f"train.{arch}.datasets, else train.datasets)" for d in names if d not in own]
            problems += outside or training_datasets_problems(config, key, names)
    if len(set(t["architectures"])) != len(t["architectures"]):
        problems.append("train.architectures: lists an architecture twice")
    for arch in t["architectures"]:  # what each training job will be given, checked now, not after the scenes
        p = train_params(config, arch)
        problem = input_size_problem(arch, p["input_size"]) or crop_problem(arch, p.get("crop", 0), p["input_size"])
        if problem:
            problems.append(problem)
    if not problems and not evaluation_datasets(config):
        problems.append("datasets: none to evaluate the models on: give one a test split (e.g. split: {train: 0.7, "
                        "val: 0.15, test: 0.15}) or add one that no model trains on")
    problems += photo_problems(config)
    return problems


def estimator_datasets(config: dict) -> dict[str, list[str]]:
    """The estimators' own training datasets where their section gives them (train.<arch>.datasets)."""
    t = config["train"]
    return {k: list(v["datasets"]) for k, v in t.items() if isinstance(v, dict) and v.get("datasets") is not None}


def trained_datasets(config: dict, archs: list[str] | None = None) -> list[str]:
    """Every dataset the models of `archs` (default: train.architectures) train on: train.datasets,
    then the estimators' own (train.instances.datasets), in order, once each."""
    out = list(config["train"]["datasets"])
    for arch in config["train"]["architectures"] if archs is None else archs:
        out += [d for d in train_params(config, arch)["datasets"] if d not in out]
    return out


def training_datasets_problems(config: dict, key: str, names: list[str]) -> list[str]:
    """What is wrong with a list of datasets to train on (`key`: where the config gives it)."""
    problems = [f"{key}: {d!r} is not one of the configured datasets ({', '.join(config['datasets'])})"
                for d in names if d not in config["datasets"]]
    unknown = bool(problems)
    if len(set(names)) != len(names):
        problems.append(f"{key}: lists a dataset twice")
    if unknown:
        return problems
    have = set().union(*(dataset_splits(config, d) for d in names))
    for s in ("train", "val"):
        if s not in have:
            problems.append(f"{key}: none of {', '.join(names)} has '{s}' scenes; training "
                            f"needs them (datasets.<name>.split, or a re-render's rerender_of.split)")
    for d in names:
        if not dataset_splits(config, d) & {"train", "val"}:
            problems.append(f"{key}: {d!r} has no train or val scenes (only "
                            f"{', '.join(sorted(dataset_splits(config, d)))}): it would add nothing to training")
    return problems


def photo_problems(config: dict) -> list[str]:
    """What is wrong with the photo sets that shows without opening a file (their files are
    checked by `photoset.check`: at check-config and the workflow's preflight, where the working
    directory their folders are relative to is the run's)."""
    from .photoset import pattern_problem

    problems = []
    for name, p in config["photos"].items():
        if name in config["datasets"]:
            problems.append(f"photos.{name}: a dataset has this name too; give the photo set a name of its own")
        if (problem := pattern_problem(p["masks"])) is not None:
            problems.append(f"photos.{name}.masks: {problem}")
    return problems


# ---- the slice of config each stage depends on ---------------------------------------------

def sample_params(config: dict, dataset: str, index: int | None = None) -> dict:
    """A dataset's sampling settings; with `index`, one scene's (else the scene runner adds it).
    A re-render's: where its scenes come from (the scene runner picks each scene's source)."""
    ds = config["datasets"][dataset]
    if "rerender_of" in ds:
        out = {"dataset": dataset, "source": {"dataset": ds["rerender_of"]["dataset"],
                                              "indices": source_indices(config, dataset)}}
        if index is not None:
            out = rerender_scene_params(out, int(index))
        return out
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
    if ds["shape_library"]:  # (left out at 0, its default: scenes made before it existed stay up to date)
        out["shape_library"] = ds["shape_library"]
    if index is not None:
        out["index"] = int(index)
    return out


def rerender_scene_params(params: dict, index: int) -> dict:
    """One re-rendered scene's sample params: its own index and its source scene's."""
    src = params["source"]
    if not 0 <= index < len(src["indices"]):
        raise PsdError(f"{params['dataset']} has {len(src['indices'])} scenes; there is no scene {index}")
    return {"dataset": params["dataset"], "index": index,
            "source": {"dataset": src["dataset"], "index": src["indices"][index]}}


def simulate_params(config: dict, dataset: str | None = None) -> dict:
    """The physics settings; a re-render copies its source's settled poses instead."""
    if dataset is not None and "rerender_of" in config["datasets"][dataset]:
        return {"copy_from_source": True}
    return copy.deepcopy(config["physics"])


def render_params(config: dict, dataset: str | None = None) -> dict:
    """A dataset's render slice (the top-level one without a dataset); the Cycles settings only
    when that backend renders (so editing them does not rerun the fast backend's renders)."""
    out = copy.deepcopy(dataset_render(config, dataset) if dataset else config["render"])
    if out["backend"] != "cycles":
        out.pop("cycles", None)
    for sub in SHARE_DRAWS:  # off (probability 0): their settings rerun nothing
        if not out.get(sub, {}).get("probability", 0):
            out.pop(sub, None)
    if out["backend"] == "cycles":  # render.occlusion shades the tiny backend only
        out.pop("occlusion", None)
    return without_default_occlusion(out)


def without_default_occlusion(render: dict) -> dict:
    """A render slice without render.occlusion where it is the default (crevice): the slices of
    before the setting stay as they were, so no render of before reruns."""
    if render.get("occlusion") == "crevice":
        del render["occlusion"]
    return render


def label_params(config: dict, dataset: str | None = None) -> dict:
    """The labels' settings; for a dataset whose camera sees the whole table (render.view_fraction
    [1, 1]) without `particles`: every particle's centre lies in view, so the particles in view and
    the bed's are the same, and the label jobs of before the setting are not rerun."""
    out = copy.deepcopy(config["labels"])
    if dataset is not None and min(dataset_render(config, dataset)["view_fraction"]) >= 1:
        out.pop("particles", None)
    return out


def compare_params(config: dict) -> dict:
    """The render settings, Cycles' included, for rendering scenes with both backends (render.occlusion
    only where it is not the default, as in render_params: the comparisons of before it do not rerun)."""
    return without_default_occlusion(copy.deepcopy(config["render"]))


def ceiling_reference(config: dict, dataset: str) -> dict | None:
    """Where a dataset's ceilings fit their read-outs when not by cross-validation on its own
    scenes: a re-render's source dataset, in the splits the re-render does not take (e.g. the 124
    training scenes for a re-render of the 14 test scenes). None for other datasets, and for a
    re-render that takes every split of its source."""
    ds = config["datasets"][dataset]
    if "rerender_of" not in ds:
        return None
    source = ds["rerender_of"]["dataset"]
    others = sorted(dataset_splits(config, source) - set(rerender_splits(ds)))
    return {"dataset": source, "splits": others} if others else None


def ceiling_params(config: dict, dataset: str) -> dict:
    """What a dataset's ceiling depends on besides its manifests."""
    return {"bounds": list(config["datasets"][dataset]["size"]["bounds"]),
            "visible_min_px": config["labels"]["visible_min_px"], "reference": ceiling_reference(config, dataset)}


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


def evaluation_datasets(config: dict) -> list[str]:
    """The datasets every model is evaluated on: those with a test split, and those without one
    that no model trains on (evaluated whole). Never a dataset of training scenes only: a
    re-render of training splits, or more training scenes (e.g. `split: {train: 0.85, val: 0.15}`
    in train.datasets), which would be scored on the scenes the models learnt."""
    trained = set(trained_datasets(config))
    return [d for d, ds in config["datasets"].items() if "test" in dataset_splits(config, d)
            or ("rerender_of" not in ds and d not in trained)]


def photo_params(config: dict, name: str) -> dict:
    """A photo set's slice: its settings and name (what its evaluation depends on besides the
    model and the files)."""
    return {"name": name, **copy.deepcopy(config["photos"][name])}


def main_training_dataset(config: dict) -> str:
    """The first of train.datasets: the benchmark's images, the backend comparison's scenes."""
    return config["train"]["datasets"][0]


# train.<arch> settings that change the model's meta only (how predict reads with it), not what it learns: runs
# that differ in them are one recipe (the training's fingerprint, report.same_recipe, bench/seed_spread.py)
META_ONLY_SETTINGS = ("auto_scale",)
# train.<arch> settings added after models were trained, and their values that change nothing: in a training's
# slice only when set otherwise (`train_params`)
SETTINGS_OFF = {"auto_scale": False, "min_visible_share": 0.0, "surface_texture": 0.0, "grain_colour": 0.0,
                "trunk_stages": 2, "calibration_datasets": None}
# train.<arch> settings that change what a trained network's maps are made into (the instance estimator's calibration
# after training: its views, its sieve-size method, its read-out, the scenes it is fitted on), not the network: runs
# that differ only in them share their network (bench/seed_spread.py --recalibrate-from)
CALIBRATION_SETTINGS = ("tta", "sieve_method", "readout", "calibration_datasets")


def settings_set(settings: dict) -> dict:
    """train.<arch> settings without those of SETTINGS_OFF at their off value: what a slice or a training's
    fingerprint holds, so that adding such a setting changes neither for the runs that do not set it."""
    def off(k, v) -> bool:
        return k in SETTINGS_OFF and v == SETTINGS_OFF[k] and isinstance(v, bool) == isinstance(SETTINGS_OFF[k], bool)

    return {k: v for k, v in settings.items() if not off(k, v)}


def training_recipe(params: dict) -> dict:
    """A `train_params` slice without the settings that change the model's meta only (META_ONLY_SETTINGS),
    and without those of SETTINGS_OFF left off (`settings_set`)."""
    out = dict(params)
    if isinstance(out.get("settings"), dict):
        out["settings"] = {k: v for k, v in settings_set(out["settings"]).items() if k not in META_ONLY_SETTINGS}
    return out


def network_recipe(params: dict) -> dict:
    """A `train_params` slice without the settings that change no trained network's weights
    (META_ONLY_SETTINGS, CALIBRATION_SETTINGS)."""
    out = training_recipe(params)
    if isinstance(out.get("settings"), dict):
        out["settings"] = {k: v for k, v in out["settings"].items() if k not in CALIBRATION_SETTINGS}
    return out


def train_params(config: dict, arch: str) -> dict:
    t = config["train"]
    keys = ("datasets", "pretrained", "epochs", "batch_size", "lr", "weight_decay", "lr_factor", "lr_patience",
            "lr_schedule", "early_stopping_patience", "precision", "device", "aux_loss_weight", "augment",
            "scale_augment", "photometric", "size_cells")
    out = {k: t[k] for k in keys}
    if t.get("crop"):  # in the slice only when on: the slices of before it (and with it off) stay as they
        out["crop"] = int(t["crop"])  # were, so no trained model's params change and nothing retrains
    size = t["input_size"].get(arch, default_input_size(arch))
    out.update(arch=arch, seed=config["seed"], input_size=int(size))
    if isinstance(t.get(arch), dict):  # an estimator's own settings, train.<arch>: only its slice has
        out["settings"] = copy.deepcopy(t[arch])  # them (editing train.instances retrains no CNN)
        epochs = out["settings"].pop("epochs", None)
        if epochs is not None:  # its own length (train.<arch>.epochs) overrides train.epochs
            out["epochs"] = int(epochs)
        datasets = out["settings"].pop("datasets", None)
        if datasets is not None:  # its own training data (train.<arch>.datasets) overrides train.datasets
            out["datasets"] = list(datasets)
        # SETTINGS_OFF in the slice only when on, as train.crop: the slices of before them stay as they were,
        out["settings"] = settings_set(out["settings"])  # and nothing retrains
    return out

