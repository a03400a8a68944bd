"""Configuration fields declared once: each field of a configuration carries its spec.

A field is declared with `option`: its default, its type (the field's annotation), its
check, whether it is static (shapes a compiled program) or traced, the version that added
it with the value older run directories ran with, and its help. Everything else is
generated from those specs by `Configured`, the base of `eant2_jax.ExploitConfig` and
`eant2_jax.EANT2Config`:

* validation on construction, one line naming the field (type, integer range, check);
* the JSON round trip, `Configured.to_dict` / `Configured.from_dict` (typed through
  `eant2_jax.jsonio.typed_fields`), where a file written before a field existed reads as
  that field's old default;
* the class docstring's attribute list (`document`) and the command line's help
  (`Configured.describe`).

Adding a field is one `option(...)` line in its class (tests/test_configspec.py shows it).
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from .jsonio import short, typed_fields

__all__ = ["INT32_MAX", "Check", "Configured", "Spec", "document", "option"]

# Integers a configuration hands to the device end up in int32 arrays (JAX's default
# integer): a larger one would overflow only once a program is traced, after a run
# directory was created. Every integer field is checked against this unless its spec says
# it stays on the host.
INT32_MAX = 2**31 - 1
_NO = object()  # "not of this kind"
_ATOMS = ("bool", "int", "float", "str", "None")


class Check(NamedTuple):
    """A field's check: ``test(value)`` must hold; ``want`` says what it asks, for errors."""

    test: Callable[[Any], bool]
    want: str


def at_least(lo: float) -> Check:
    return Check(lambda v: v >= lo, f">= {lo}")


def above(lo: float) -> Check:
    return Check(lambda v: v > lo and math.isfinite(v), f"> {lo} and finite")


def between(lo: float, hi: float, *, open_low: bool = False) -> Check:
    if open_low:
        return Check(lambda v: lo < v <= hi, f"in ({lo}, {hi}]")
    return Check(lambda v: lo <= v <= hi, f"in [{lo}, {hi}]")


def one_of(*choices: str) -> Check:
    return Check(lambda v: v in choices, f"one of {', '.join(choices)}")


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a field is, beyond its name and annotation (see `option`)."""

    help: str
    check: Check | None = None
    static: bool = False
    added: str | None = None
    old: Any = None
    convert: Callable[[Any], Any] | None = None
    want: str = ""
    none: Any = None
    limit: int = INT32_MAX


def option(
    default: Any = dataclasses.MISSING,
    help: str = "",  # noqa: A002 -- argparse's word
    *,
    check: Check | None = None,
    static: bool = False,
    added: str | None = None,
    old: Any = None,
    convert: Callable[[Any], Any] | None = None,
    want: str = "",
    none: Any = None,
    limit: int = INT32_MAX,
    factory: Callable[[], Any] | None = None,
) -> Any:
    """Declare a configuration field with its spec.

    Args:
      default: the default value (or ``factory``, a function making it).
      help: what the field means; its first sentence is the command line's help.
      check: a `Check` on the typed value (None passes where the annotation allows it).
      static: the field shapes the compiled program (not a pytree leaf): a new value
        compiles a new program. Otherwise a number is traced into the program.
      added: the version (and commit) that added the field; run directories written
        before it lack it and read as ``old``, the value that reproduces what they did.
      convert: for a field whose annotation is not one of int, float, str, bool (with
        ``| None``): a function returning the normal value or raising TypeError or
        ValueError; ``want`` then says what it takes.
      none: what None stands for once validated: a value (written back as None) or a
        function of the validated configuration.
      limit: the largest magnitude of an integer field (default int32's).
    """
    spec = Spec(help, check, static, added, old, convert, want, none, limit)
    metadata = {"pytree_node": not static, "spec": spec}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def _kinds(f: dataclasses.Field) -> tuple[str, ...]:
    t = f.type
    text = t if isinstance(t, str) else getattr(t, "__name__", str(t))
    return tuple(part.strip() for part in text.split("|"))


def _as(kind: str, v: Any) -> Any:
    """``v`` as ``kind`` (one Python type per kind, so equal configs trace alike), or _NO."""
    if kind == "bool":
        return v if isinstance(v, bool) else _NO
    if isinstance(v, bool) or kind not in ("int", "float"):
        return v if kind == "str" and isinstance(v, str) else _NO
    if not isinstance(v, int | float | np.integer | np.floating):
        return _NO
    if kind == "float":
        return float(v)
    if isinstance(v, int | np.integer):
        return int(v)
    return int(v) if math.isfinite(v) and float(v) == int(v) else _NO


_PHRASE = {"int": "an integer", "float": "a number", "str": "a string", "bool": "bool"}


def _phrase(kinds: tuple[str, ...]) -> str:
    words = [_PHRASE.get(k, k) for k in kinds if k != "None"]
    return " or ".join(words) + (" (or None)" if "None" in kinds else "")


def spec_of(f: dataclasses.Field) -> Spec:
    spec = f.metadata.get("spec")
    if spec is None:
        raise TypeError(f"field {f.name!r} was not declared with configspec.option")
    return spec


def normal(owner: str, f: dataclasses.Field, v: Any) -> Any:
    """The field's value in its one Python type, checked; a ValueError naming the field."""
    spec, kinds, where = spec_of(f), _kinds(f), f"{owner}.{f.name}"
    if v is None and "None" in kinds:
        return None
    if spec.convert is not None:
        try:
            out = spec.convert(v)
        except (TypeError, ValueError):
            raise ValueError(f"{where} must be {spec.want}, got {v!r:.60}") from None
    else:
        out = next((x for x in (_as(k, v) for k in kinds) if x is not _NO), _NO)
        if out is _NO:
            raise ValueError(f"{where} must be {_phrase(kinds)}, got {v!r:.60}")
        if type(out) is int and not -spec.limit - 1 <= out <= spec.limit:
            bound = f"at most {spec.limit}" if out > 0 else f"at least {-spec.limit - 1}"
            raise ValueError(f"{where} must be {bound}, got {out}")
    if spec.check is not None and not spec.check.test(out):
        tail = " (or None)" if "None" in kinds else ""
        raise ValueError(f"{where} must be {spec.check.want}{tail}, got {v!r:.60}")
    return out


def _nested(f: dataclasses.Field) -> type | None:
    """The configuration class of a field holding one (judged by its default)."""
    if f.default_factory is not dataclasses.MISSING:
        proto = f.default_factory()
    else:
        proto = f.default
    return type(proto) if isinstance(proto, Configured) else None


def _plain(spec: Spec, v: Any) -> Any:
    """A value as JSON holds it."""
    if isinstance(v, Configured):
        return v.to_dict()
    if spec.none is not None and not callable(spec.none) and v == spec.none:
        return None
    return list(v) if isinstance(v, tuple) else v


class Configured:
    """The base of a configuration whose fields are all declared with `option`."""

    def __post_init__(self):
        owner = type(self).__name__
        fields = dataclasses.fields(self)
        for f in fields:
            object.__setattr__(self, f.name, normal(owner, f, getattr(self, f.name)))
        for f in fields:
            spec = spec_of(f)
            if spec.none is not None and getattr(self, f.name) is None:
                value = spec.none(self) if callable(spec.none) else spec.none
                object.__setattr__(self, f.name, value)
        self.check_across()

    def check_across(self) -> None:
        """Checks between fields, after each field's own (none by default)."""

    def to_dict(self) -> dict:
        """JSON-ready fields (a value None stands for is written as None)."""
        return {f.name: _plain(spec_of(f), getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: Any, *, complete: bool = False):
        """Inverse of `to_dict`; unknown keys are a ValueError naming them.

        Args:
          d: the dict (a nested configuration is required: without it, pruning would
            silently take its default).
          complete: also require every field `to_dict` writes, so that no missing key
            silently takes today's default; a field added after the file was written
            takes the value of its spec's ``old`` (what that version did).
        """
        name = cls.__name__
        if not isinstance(d, dict):
            raise ValueError(f"a {name} configuration must be an object, got {short(d)}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - set(fields))
        if unknown:
            raise ValueError(
                f"unknown {name} option(s): {', '.join(map(str, unknown))}; known: "
                f"{', '.join(sorted(fields))}"
            )
        given, later = dict(d), {}
        if complete:
            later = {n: spec_of(f).old for n, f in fields.items() if spec_of(f).added}
            missing = sorted(set(fields) - set(given) - set(later))
            if missing:
                raise ValueError(f"{name} option(s) missing: {', '.join(missing)}")
            given = {**{n: v for n, v in later.items() if n not in given}, **given}
        atomic = _atomic_view(cls)
        typed = typed_fields(atomic, {k: v for k, v in given.items() if k in _ATOMIC[cls]}, name)
        for n, f in fields.items():
            inner = _nested(f)
            if inner is None:
                continue
            if not isinstance(given.get(n), dict):
                raise ValueError(f"the configuration has no {n!r} object")
            typed[n] = inner.from_dict(given[n], complete=complete)
        rest = {k: v for k, v in given.items() if k not in typed}
        return cls(**typed, **rest)

    @classmethod
    def from_options(cls, options: dict):
        """``cls(**options)``, with a ValueError naming any unknown option."""
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = [name for name in options if name not in known]
        if unknown:
            hints = []
            for name in unknown:
                close = difflib.get_close_matches(name, known, n=1)
                hints.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
            raise ValueError(
                f"unknown option {', '.join(hints)}; the options are the fields of "
                f"{cls.__name__}: {', '.join(known)}"
            )
        return cls(**options)

    def describe(self, prefix: str = "") -> list[tuple[str, str, Any, str]]:
        """Every field as ``(dotted name, type, value as JSON, first sentence of help)``,
        a nested configuration's fields under its field's name (``exploit.sigma0``)."""
        rows = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Configured):
                rows += value.describe(f"{prefix}{f.name}.")
                continue
            spec = spec_of(f)
            rows.append(
                (prefix + f.name, " | ".join(_kinds(f)), _plain(spec, value), first_sentence(spec))
            )
        return rows

    @classmethod
    def locate(cls, path: str) -> tuple[type, dataclasses.Field]:
        """The class and field a dotted name (``exploit.sigma0``) names; a ValueError
        suggests the nearest name."""
        owner, names = cls, path.split(".")
        for i, part in enumerate(names):
            fields = {f.name: f for f in dataclasses.fields(owner)}
            f = fields.get(part)
            inner = None if f is None else _nested(f)
            if f is None or (inner is None) != (i == len(names) - 1):
                known = [row[0] for row in cls().describe()]
                close = difflib.get_close_matches(path, known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(f"unknown option {path!r}{hint}; eant2 config lists them")
            if inner is not None:
                owner = inner
        return owner, f


_ATOMIC: dict[type, frozenset[str]] = {}
_VIEWS: dict[type, type] = {}


def _atomic_view(cls: type) -> type:
    """A dataclass of ``cls``'s fields of one JSON kind (with ``| None``), the ones
    `jsonio.typed_fields` types; the others go through their spec's ``convert``."""
    if cls not in _VIEWS:
        atomic = []
        for f in dataclasses.fields(cls):
            kinds = _kinds(f)
            plain = [k for k in kinds if k != "None"]
            if spec_of(f).convert is None and len(plain) == 1 and set(kinds) <= set(_ATOMS):
                atomic.append((f.name, " | ".join(kinds), dataclasses.field(default=None)))
        _VIEWS[cls] = dataclasses.make_dataclass(f"{cls.__name__}JSON", atomic)
        _ATOMIC[cls] = frozenset(name for name, _, _ in atomic)
    return _VIEWS[cls]


def first_sentence(spec: Spec) -> str:
    text = " ".join(spec.help.split())
    end = text.find(". ")
    return (text if end < 0 else text[: end + 1]).replace("``", "").replace("`", "")


def document(cls: type) -> type:
    """Append an ``Attributes:`` section, generated from the fields' specs, to the class
    docstring (what the docs page and ``help()`` show)."""
    lines = ["", "Attributes:"]
    for f in dataclasses.fields(cls):
        spec = spec_of(f)
        parts = ["*static*."] if spec.static else []
        parts.append(" ".join(spec.help.split()))
        if spec.added:
            parts.append(f"Added in {spec.added}; older run directories read as {spec.old!r}.")
        text = " ".join(parts)
        words, line = text.split(), f"  {f.name}:"
        for word in words:
            if len(line) + 1 + len(word) > 92:
                lines.append(line)
                line = "    " + word
            else:
                line += " " + word
        lines.append(line)
    cls.__doc__ = inspect.cleandoc(cls.__doc__ or "") + "\n" + "\n".join(lines) + "\n"
    return cls
