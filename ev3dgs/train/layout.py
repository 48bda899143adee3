"""train.toml: the trainer's settings as one TOML file, core keys at the top and one table per term.

    iterations = 3000           # the core: model, optimiser, densification, schedule, checkpoints
    seed = 0
    [blur]                      # always on: the blur rendering loss over the exposure's sub-poses
    subposes = 5
    [events]                    # a term: present = on, absent = off
    norm = "noise"
    huber = 3.0

A table that switches a term (SWITCHES) turns it on by being there, even empty; keys left out keep their
defaults; ``"auto"`` stands for a setting the trainer resolves itself (from the scene or the event norm).
Tables of terms registered outside the package (terms.register) are checked by the term's own settings class.
In memory the settings stay one flat TrainConfig (LAYOUT maps each TOML key to its field), so Python callers
and the flat config.json of older runs read the same object.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import typing

from ..config import _coerce
from ..errors import ConfigError

# (table, key) -> TrainConfig field; table "" is the top level (the core)
LAYOUT: dict[str, dict[str, str]] = {
    "": {k: k for k in ("scene", "iterations", "seed", "backend", "device", "threads", "checkpoint_every",
                        "readback_every", "naive", "oracle", "sh_degree", "sh_interval", "init_points",
                        "init_opacity", "schedule_length")},
    "blur": {"subposes": "subposes", "subpose_px": "subpose_px", "space": "blur_space",
             "ssim_lambda": "ssim_lambda"},
    "densify": {"enabled": "densify", "from": "densify_from"},
    "events": {"weight": "event_weight", "norm": "event_norm", "mismatch": "event_mismatch",
               "pairs": "event_pairs", "floor": "event_floor", "huber": "event_huber", "domain": "event_domain",
               "frame_noise": "frame_noise", "learn_thresholds": "learn_thresholds"},
    "threshold_map": {"weights": "map_weights"},
    "edi_prior": {"weight": "edi_prior", "anneal": "edi_anneal"},
    "hdr": {},
    "response": {},
    "poses": {"lr": "pose_lr", "lr_final": "pose_lr_final", "start": "pose_start", "warmup": "pose_warmup",
              "max_rotation": "pose_max_rotation", "max_translation": "pose_max_translation",
              "gauge": "pose_gauge", "frame": "pose_frame"},
}
# tables whose presence switches a term on (the field it sets True); [edi_prior] is on by its weight
SWITCHES = {"events": "event_loss", "threshold_map": "threshold_map", "hdr": "hdr", "response": "learn_response",
            "poses": "refine_poses"}
# tables that are always there (the core's parts): absent = their defaults
ALWAYS = ("blur", "densify")
# the run's facts, not settings: written, never read back as settings
VIEW_KEYS = {"every": int, "host": str, "port": int}   # [view]: the --view browser viewer (not the model)

FIELD_KEY = {field: (f"{table}.{key}" if table else key) for table, keys in LAYOUT.items()
             for key, field in keys.items()}
FIELD_KEY.update({field: table for table, field in SWITCHES.items()})


def _field_types(cls) -> dict:
    return typing.get_type_hints(cls)


def _value(value, tp, key: str):
    """A TOML value as the field's type; "auto" is None where the field allows it."""
    optional = type(None) in typing.get_args(tp)
    if optional and value == "auto":
        return None
    try:
        return _coerce(value, tp, key)
    except ConfigError as e:
        text = str(e).replace(": expected ", ": expected \"auto\" or ", 1) if optional else str(e)
        raise ConfigError(text) from None


def flat_settings(data: dict, cls, registry: dict) -> dict:
    """TrainConfig keyword arguments from a train.toml dict (see the module doc). Unknown keys and tables and
    values of the wrong type are one-line ConfigErrors naming the dotted key."""
    types = _field_types(cls)
    flat: dict = {field: False for field in SWITCHES.values()}
    flat["edi_prior"] = 0.0
    terms: dict = {}
    for name, value in data.items():
        if name in LAYOUT[""]:
            flat[name] = _value(value, types[name], name)
            continue
        if name == "view":
            continue   # the viewer's settings: read by the command, not the model's (view_settings)
        if not isinstance(value, dict):
            tables = ", ".join(t for t in LAYOUT if t)
            raise ConfigError(f"unknown config key {name} (top-level keys: {', '.join(LAYOUT[''])}; "
                              f"tables: {tables}{', ' if registry else ''}{', '.join(registry)})")
        if name in registry:   # a term registered outside the package: its own settings class checks it
            terms[name] = dataclasses.asdict(registry[name].settings_from(value, name))
            continue
        if name not in LAYOUT:
            raise ConfigError(f"unknown config table [{name}] (known: {', '.join(t for t in LAYOUT if t)}"
                              f"{', ' if registry else ''}{', '.join(registry)})")
        if name in SWITCHES:
            flat[SWITCHES[name]] = True
        for key, v in value.items():
            if key not in LAYOUT[name]:
                known = ", ".join(LAYOUT[name]) or "none"
                raise ConfigError(f"unknown config key {name}.{key} (known in [{name}]: {known})")
            field = LAYOUT[name][key]
            flat[field] = _value(v, types[field], f"{name}.{key}")
        if name == "edi_prior" and "weight" not in value:
            raise ConfigError("[edi_prior] needs weight (the prior's weight per unit of chi-square, e.g. 0.05)")
    flat["terms"] = terms
    return flat


def view_settings(data: dict) -> dict:
    """The [view] table (every, host, port), checked; {} when absent."""
    table = data.get("view", {})
    if not isinstance(table, dict):
        raise ConfigError("view: expected a table ([view] every, host, port)")
    out = {}
    for key, v in table.items():
        if key not in VIEW_KEYS:
            raise ConfigError(f"unknown config key view.{key} (known in [view]: {', '.join(VIEW_KEYS)})")
        out[key] = _coerce(v, VIEW_KEYS[key], f"view.{key}")
    if not 0 <= out.get("port", 0) <= 65535:
        raise ConfigError(f"view.port must be a TCP port in [0, 65535], got {out['port']}")
    return out


def nested(cfg) -> dict:
    """The train.toml dict of a TrainConfig (the inverse of flat_settings): every setting written, "auto" for
    those the trainer resolves; switched-off terms' tables left out."""
    out: dict = {}
    for table, keys in LAYOUT.items():
        if table in SWITCHES and not getattr(cfg, SWITCHES[table]):
            continue
        if table == "edi_prior" and not cfg.edi_prior:
            continue
        values = {key: ("auto" if getattr(cfg, field) is None else getattr(cfg, field)) for key, field in keys.items()}
        if table == "":
            out.update({k: v for k, v in values.items() if not (k == "schedule_length" and v == "auto")})
        else:
            out[table] = values
    for name, settings in (cfg.terms or {}).items():
        out[name] = dict(settings)
    return out


def parse_set(item: str) -> tuple[list[str], object]:
    """``--set events.huber=3``: (["events", "huber"], 3). The value is read as TOML (3, 0.5, true, "x", [1, 2]);
    a bare word that is not TOML is a string (``--set events.norm=count``)."""
    key, sep, text = item.partition("=")
    path = key.strip().split(".")
    if not sep or not all(p.strip() for p in path) or len(path) > 2:
        raise ConfigError(f"--set {item}: expected KEY=VALUE or TABLE.KEY=VALUE (e.g. --set events.huber=3)")
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    return [p.strip() for p in path], value


def former_flags() -> dict[str, tuple[str, bool]]:
    """{former `ev3dgs train` flag: (its train.toml key, whether it was a switch)} for the flags that became
    config keys (docs/commands/ev3dgs-train.md lists them)."""
    from .config import CLI_FLAGS

    out = {}
    for field, key in FIELD_KEY.items():
        flag = "--" + field.replace("_", "-")
        if flag not in CLI_FLAGS and field not in ("scene", "schedule_length", "naive", "oracle"):
            out[flag] = (key, key in SWITCHES)
    out.update({"--learn-response": ("response", True), "--threshold-map": ("threshold_map", True),
                "--hdr": ("hdr", True), "--edi-prior": ("edi_prior.weight", False),
                "--densify-from": ("densify.from", False), "--view-every": ("view.every", False),
                "--view-host": ("view.host", False), "--view-port": ("view.port", False),
                "--learn-thresholds": ("events.learn_thresholds", False)})
    for never in ("--densify", "--init-opacity", "--ssim-lambda"):   # config keys that never were flags
        out.pop(never, None)
    out.pop("--event-loss", None)
    out.pop("--refine-poses", None)
    return out


def former_flag_message(flag: str) -> str | None:
    """The one-line hint for a flag `ev3dgs train` no longer has, or None."""
    name = flag.split("=", 1)[0]
    hit = former_flags().get(name)
    if hit is None:
        return None
    key, switch = hit
    how = f"--set {key}=true" if switch or key == "events.learn_thresholds" else f"--set {key}=VALUE"
    where = f"a [{key}] table" if switch else f"{key}"
    return (f"{name} is a config key now: {how} (or {where} in the --config file; docs/commands/ev3dgs-train.md "
            "lists every former flag)")


def apply_set(data: dict, items: list[str]) -> dict:
    """``data`` with every --set item applied (a key of an absent term's table turns the term on;
    ``--set TABLE=true`` / ``=false`` switches a term's table on with its defaults / off)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for item in items:
        path, value = parse_set(item)
        if len(path) == 1 and (path[0] in SWITCHES or path[0] == "edi_prior") and isinstance(value, bool):
            if value:
                out.setdefault(path[0], {})
            else:
                out.pop(path[0], None)
            continue
        if len(path) == 1:
            if isinstance(out.get(path[0]), dict):
                raise ConfigError(f"--set {item}: [{path[0]}] is a table; set one of its keys "
                                  f"(--set {path[0]}.KEY=VALUE)")
            out[path[0]] = value
        else:
            table = out.setdefault(path[0], {})
            if not isinstance(table, dict):
                raise ConfigError(f"--set {item}: {path[0]} is not a table")
            table[path[1]] = value
    return out


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write {v!r} as TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ValueError(f"cannot write {type(v).__name__} as TOML")


def dumps(data: dict, comments: dict | None = None) -> str:
    """A train.toml dict as TOML text (top-level keys, then one table each); ``comments``: {dotted key: text}
    written after the value (what "auto" resolved to)."""
    comments = comments or {}
    lines = []

    def put(key, value, dotted):
        note = f"   # {comments[dotted]}" if dotted in comments else ""
        lines.append(f"{key} = {_toml_value(value)}{note}")

    for k, v in data.items():
        if not isinstance(v, dict):
            put(k, v, k)
    for k, v in data.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            for kk, vv in v.items():
                put(kk, vv, f"{k}.{kk}")
    return "\n".join(lines) + "\n"


def variant_overrides(variant: dict) -> dict:
    """TrainConfig keyword overrides from a variant written in train.toml's shape (the studies' variants):
    core keys at the top, ``{table: {key: value}}`` for a term's keys (its table present: the term on),
    ``{table: False}`` for a term switched off (``{"events": False}``: the blur term alone). Unknown keys are
    one-line ConfigErrors, as in a train.toml."""
    out: dict = {}
    for name, value in variant.items():
        if name in LAYOUT[""]:
            out[name] = value
            continue
        if name not in LAYOUT or name == "":
            raise ConfigError(f"unknown config key {name} in a variant")
        if value is False:
            if name == "edi_prior":
                out["edi_prior"] = 0.0
            elif name in SWITCHES:
                out[SWITCHES[name]] = False
            else:
                raise ConfigError(f"[{name}] cannot be switched off")
            continue
        if not isinstance(value, dict):
            raise ConfigError(f"{name}: expected a table or false in a variant")
        if name in SWITCHES and name != "events":   # [events] is on by default: only False says something
            out[SWITCHES[name]] = True
        for key, v in value.items():
            if key not in LAYOUT[name]:
                raise ConfigError(f"unknown config key {name}.{key} (known in [{name}]: {', '.join(LAYOUT[name])})")
            out[LAYOUT[name][key]] = v
    return out
