"""The trainer's terms: everything optional about a training step, behind one small protocol.

The core (trainer.py) owns the model, its optimiser, densification, the schedule, checkpoints and the loop. A
term is one module here with one class registered under its train.toml table. Per step the core

1. asks every term which cameras it needs (``cameras``; a term may also correct the cameras the others asked
   for: ``adjust_cameras``, pose refinement), renders them all in ONE rasterizer call (a pose asked for twice
   is rendered once) and hands each term its images (``Step.images(term)``);
2. asks every term, in registry order, for its loss (``loss``: a weighted scalar tensor or None) and its log
   values; the core sums the losses and runs one backward pass;
3. lets every term step its own optimiser (``after_backward``) and record what it tracks over steps
   (``after_step``).

A term also has its own trained tensors (``parameters``, covered by the non-finite guard), its checkpoint state
(``save``/``load`` into the checkpoint's payload), what it adds to model.pt (``model_extras``) and what it
writes into the run folder (``write``). ``build`` returns None where the term is off for this run.

A new term is one module and one table: subclass Term, give it a ``table`` and a ``Settings`` dataclass (the
table's keys) and ``register`` it (see tests/test_train_terms.py for a term defined outside the package).
"""
from __future__ import annotations

import dataclasses
import importlib

from ...errors import ConfigError

# the built-in terms' modules, in the order the step evaluates them (events before the EDI prior, which reads
# the event term's floor and threshold map of this step; the pose, response and HDR terms before the blur term
# they shape)
BUILTIN = ("poses", "response", "hdr", "blur", "threshold_map", "events", "edi_prior")

_REGISTRY: dict[str, type] = {}


class Term:
    """The protocol (every method has a do-nothing default)."""

    table = ""            # its train.toml table
    builtin = False       # settings in TrainConfig's flat fields (layout.LAYOUT) rather than cfg.terms
    Settings = None       # a frozen dataclass of the table's keys (terms registered outside the package)

    def __init__(self, trainer):
        self.trainer = trainer

    # ---------------------------------------------------------------- set-up
    @classmethod
    def build(cls, trainer):
        """The term for this run, or None where it is off (default: on when its table is in the config)."""
        return cls(trainer) if cls.table in trainer.cfg.terms else None

    @classmethod
    def settings_from(cls, table: dict, name: str):
        """The table's settings, checked (unknown keys and wrong types: one-line ConfigError naming them)."""
        from ...config import from_dict

        if cls.Settings is None:
            if table:
                raise ConfigError(f"unknown config key {name}.{next(iter(table))} ([{name}] takes no keys)")
            return None
        return from_dict(cls.Settings, table, name)

    @property
    def settings(self):
        """This run's settings of the term (its table, as its Settings class)."""
        return self.settings_from(self.trainer.cfg.terms.get(self.table, {}), self.table)

    # ---------------------------------------------------------------- the step
    def cameras(self, step):
        """(m, 4, 4) world->camera matrices this term needs rendered this step, or None."""
        return None

    def adjust_cameras(self, step, poses):
        """The view's cameras as this term would have them rendered (pose refinement corrects them)."""
        return poses

    def loss(self, step):
        """(weighted loss tensor or None, {log key: float}) for this step."""
        return None, {}

    def after_backward(self, step) -> dict:
        """After the backward pass and the guard: step this term's optimiser; returns log values."""
        return {}

    def after_step(self, step) -> dict:
        """After the model's update (no gradients): update tracked statistics; returns log values."""
        return {}

    # ---------------------------------------------------------------- state and outputs
    def parameters(self) -> list:
        """Tensors this term trains that the non-finite guard checks."""
        return []

    def save(self, payload: dict) -> None:
        """Put this term's state into the checkpoint payload."""

    def load(self, payload: dict, path) -> None:
        """Restore this term's state from a checkpoint payload."""

    def model_extras(self) -> dict:
        """Entries this term adds to model.pt."""
        return {}

    def write(self, run_dir) -> None:
        """Write this term's outputs into the run folder (called with model.pt)."""


def register(cls: type) -> type:
    """Add a term class under its table (a decorator). A table the core uses (layout.LAYOUT) is refused."""
    from ..layout import LAYOUT

    if not cls.table or not cls.table.isidentifier():
        raise ValueError(f"a term needs a table name, got {cls.table!r}")
    if not cls.builtin and (cls.table in LAYOUT or cls.table == "view"):
        raise ValueError(f"[{cls.table}] is a built-in table")
    if cls.Settings is not None and not dataclasses.is_dataclass(cls.Settings):
        raise ValueError(f"{cls.__name__}.Settings must be a dataclass")
    _REGISTRY[cls.table] = cls
    return cls


def unregister(table: str) -> None:
    _REGISTRY.pop(table, None)


def _load_builtin() -> None:
    for name in BUILTIN:
        if name not in _REGISTRY:
            importlib.import_module(f"{__name__}.{name}")


def all_terms() -> list[type]:
    """Every term class: the built-in ones in BUILTIN order, then those registered from outside."""
    _load_builtin()
    return [_REGISTRY[n] for n in BUILTIN] + [c for n, c in _REGISTRY.items() if n not in BUILTIN]


def registered() -> dict[str, type]:
    """{table: class} of the terms registered from outside the package (their tables live in cfg.terms)."""
    _load_builtin()
    return {n: c for n, c in _REGISTRY.items() if not c.builtin}
