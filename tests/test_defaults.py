"""The config schema is the one source of every setting's default.

Each settings dataclass has one field per property of its schema section (bar the few that a
config slice derives), of the schema's type, and no default of its own; the stages get the
validated slice, whose defaults the schema filled in, and build their dataclass from it.
"""

from __future__ import annotations

import dataclasses
import types
import typing

import pytest
import yaml

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.learn.instances.training import InstanceSettings
from psdfactory.learn.train import TrainParams
from psdfactory.scene.labels import LabelParams
from psdfactory.scene.physics import PhysicsParams, QualityBounds
from psdfactory.scene.render.cycles import CyclesParams
from psdfactory.scene.render.distractors import DistractorParams
from psdfactory.scene.render.look import RenderParams
from psdfactory.scene.render.markings import MarkingParams
from psdfactory.scene.sampling import SampleParams
from psdfactory.scene.shapes import ShapeParams

SCHEMA = yaml.safe_load(psd_config.SCHEMA.read_text())


def resolve(node: dict) -> dict:
    """A schema node with its $ref (into #/definitions) merged in."""
    if "$ref" not in node:
        return node
    name = node["$ref"].rsplit("/", 1)[-1]
    return {**resolve(SCHEMA["definitions"][name]), **{k: v for k, v in node.items() if k != "$ref"}}


def section(*path: str) -> dict:
    """The schema node of a config section: ("physics", "quality"), or ("<dataset>", ...)."""
    node = resolve(SCHEMA["definitions"]["dataset"]) if path[0] == "<dataset>" else SCHEMA
    for key in path[path[0] == "<dataset>":]:
        node = resolve(node["properties"][key])
    return node


def properties(node: dict, flatten: tuple[str, ...] = ()) -> dict[str, dict]:
    """name → schema node of a section's settings; the objects named in `flatten` give one
    setting per property, named `<object>_<property>` (as SampleParams has them)."""
    out = {}
    for k, v in node["properties"].items():
        v = resolve(v)
        if k in flatten:
            out.update({f"{k}_{sub}": resolve(s) for sub, s in v["properties"].items()})
        else:
            out[k] = v
    return out


def python_type(node: dict, nested: type | None = None):
    """The type annotation a dataclass field holding this schema node has."""
    if "enum" in node:
        (t,) = {type(v) for v in node["enum"]}
        return t
    kind = node["type"]
    if isinstance(kind, list):  # e.g. ["array", "null"]: a field that holds None where the setting is absent
        (kind,) = [k for k in kind if k != "null"]
    if kind == "object":
        return nested if "properties" in node else dict
    if kind == "array":
        item = python_type(resolve(node["items"]))
        n = node.get("minItems")
        return tuple[(item,) * n] if n is not None and n == node.get("maxItems") else tuple[item, ...]
    return {"number": float, "integer": int, "boolean": bool, "string": str}[kind]


def defaults(node: dict) -> dict:
    """The defaults that validation fills in for a section (nested sections included)."""
    out = {}
    for k, v in node["properties"].items():
        v = resolve(v)
        if v.get("type") == "object" and "properties" in v:
            out[k] = defaults(v)
        elif "default" in v:
            out[k] = v["default"]
    return out


# dataclass, its schema section, settings flattened into fields, fields a slice derives (not in
# the section), the section's settings that no field holds (each with where it goes instead)
CASES = [
    (PhysicsParams, ("physics",), (), {}, {}),
    (QualityBounds, ("physics", "quality"), (), {}, {}),
    (RenderParams, ("render",), (), {}, {}),
    (CyclesParams, ("render", "cycles"), (), {}, {}),
    (DistractorParams, ("render", "distractors"), (), {}, {}),
    (MarkingParams, ("render", "markings"), (), {}, {}),
    (LabelParams, ("labels",), (), {}, {}),
    (TrainParams, ("train",), (),
     {"arch": "one of train.architectures", "seed": "the top-level seed",
      "input_size": "train.input_size[arch] or config.default_input_size(arch)"},
     {"architectures": "one training job per architecture", "input_size": "TrainParams.input_size (its arch's)",
      "instances": "InstanceSettings, in the slice of arch 'instances' only"}),
    (InstanceSettings, ("train", "instances"), (), {},
     {"epochs": "TrainParams.epochs of the slice of arch 'instances' (null: train.epochs)",
      "datasets": "TrainParams.datasets of the slice of arch 'instances' (null: train.datasets)"}),
    (SampleParams, ("<dataset>",), ("size", "placement"),
     {"seed": "the top-level seed", "dataset": "the dataset's name", "index": "the scene's index"},
     {"n_scenes": "how many scenes", "shard_size": "the manifest", "split": "the manifest",
      "rerender_of": "a re-render takes its scenes elsewhere", "render": "RenderParams"}),
]
# the type of a field that holds a whole section (shape_params: the overrides that
# ShapeParams.for_family takes, a plain mapping)
NESTED = {(PhysicsParams, "quality"): QualityBounds, (RenderParams, "cycles"): CyclesParams,
          (RenderParams, "distractors"): DistractorParams, (RenderParams, "markings"): MarkingParams,
          (SampleParams, "shape_params"): dict}


@pytest.mark.parametrize("cls, path, flatten, derived, elsewhere", CASES, ids=[c[0].__name__ for c in CASES])
def test_every_field_is_a_schema_setting_of_the_same_type(cls, path, flatten, derived, elsewhere):
    props = properties(section(*path), flatten)
    fields = {f.name for f in dataclasses.fields(cls)}
    assert fields - set(derived) == set(props) - set(elsewhere), "a setting without a field, or a field without one"
    hints = typing.get_type_hints(cls)
    for name in fields - set(derived):
        want = python_type(props[name], NESTED.get((cls, name)))
        got = hints[name]
        if isinstance(got, types.UnionType):  # RenderParams.cycles: None where another backend renders
            got = next(a for a in typing.get_args(got) if a is not type(None))
        assert got == want, f"{cls.__name__}.{name}: {got} in the dataclass, {want} in the schema"


@pytest.mark.parametrize("cls", [c[0] for c in CASES])
def test_no_settings_dataclass_keeps_defaults_of_its_own(cls):
    own = [f.name for f in dataclasses.fields(cls)
           if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING]
    assert not own, f"{cls.__name__} has defaults beside the schema's: {own}"


def test_shape_families_are_the_one_source_of_shape_defaults():
    """shape_params overrides a family's own knobs (shapes.ShapeParams.for_family): the schema
    gives the same names and types, and no defaults."""
    props = properties(section("<dataset>", "shape_params"))
    assert {f.name for f in dataclasses.fields(ShapeParams)} == set(props)
    hints = typing.get_type_hints(ShapeParams)
    for name, node in props.items():
        assert hints[name] == python_type(node), name
        assert "default" not in node, f"shape_params.{name}: its default is the shape family's"


def _plain(v):
    if dataclasses.is_dataclass(v):
        return _plain(dataclasses.asdict(v))
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def test_the_validated_defaults_build_every_dataclass_with_the_schemas_values():
    cfg = psd_config.validate({"datasets": {"train": {"n_scenes": 10}}})
    built = {
        PhysicsParams: PhysicsParams.from_dict(psd_config.simulate_params(cfg)),
        RenderParams: RenderParams.from_dict(psd_config.compare_params(cfg)),  # the Cycles settings too
        LabelParams: LabelParams.from_dict(psd_config.label_params(cfg)),
        TrainParams: TrainParams.from_dict(psd_config.train_params(cfg, "resnet50")),
        InstanceSettings: InstanceSettings.from_dict(psd_config.train_params(cfg, "instances")["settings"]),
        SampleParams: SampleParams.from_dict(psd_config.sample_params(cfg, "train", 3)),
    }
    for cls, path, flatten, _, elsewhere in CASES:
        if cls not in built:
            continue  # nested in another one
        want = defaults(section(*path))
        for k in flatten:
            want.update({f"{k}_{sub}": v for sub, v in want.pop(k).items()})
        got = _plain(built[cls])
        for name in set(want) - set(elsewhere):
            assert got[name] == _plain(want[name]), f"{cls.__name__}.{name}"
    t = built[TrainParams]
    assert (t.arch, t.seed, t.input_size) == ("resnet50", cfg["seed"], psd_config.default_input_size("resnet50"))
    assert built[RenderParams].cycles is not None
    assert RenderParams.from_dict(psd_config.render_params(cfg)).cycles is None  # tiny: no Cycles settings


@pytest.mark.parametrize("cls, key", [(PhysicsParams, "physics"), (LabelParams, "labels"), (TrainParams, "train"),
                                      (CyclesParams, "render.cycles")])
def test_a_slice_without_a_setting_is_an_error_that_names_it(cls, key):
    cfg = psd_config.validate({"datasets": {"train": {"n_scenes": 1}}})
    full = {PhysicsParams: psd_config.simulate_params(cfg), LabelParams: psd_config.label_params(cfg),
            TrainParams: psd_config.train_params(cfg, "resnet50"),
            CyclesParams: psd_config.compare_params(cfg)["cycles"]}[cls]
    name = sorted(full)[-1]
    with pytest.raises(PsdError, match=rf"{key} lacks {name}: pass the validated config's slice"):
        cls.from_dict({k: v for k, v in full.items() if k != name})
    with pytest.raises(PsdError, match=rf"unknown {key} setting: typo"):
        cls.from_dict({**full, "typo": 1})
    sample = psd_config.sample_params(cfg, "train", 0)
    del sample["placement"]
    with pytest.raises(PsdError, match="lack 'placement'"):
        SampleParams.from_dict(sample)
