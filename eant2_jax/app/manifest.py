"""A reproduction's settings: its arms, and ``reproduce.json``, the manifest `reproduce`
writes first into its directory so that ``eant2 resume DIR`` can finish it.

A manifest is data read from a directory that may have come from anyone: it is read with a
size cap (a regular file only, never through a link), parsed as strict JSON and checked
field by field, by type and range, before anything runs (`check_manifest`); any problem is
one `ManifestError` naming the field. Its task is rebuilt by `resume_task` only when it is
a registered task (`eant2_jax.tasks.is_registered`): no module or file a manifest names is
ever imported (docs/reliability.md, "Trust" and "Manifests").
"""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path
from typing import Any

from ..config import EANT2Config
from ..jsonio import loads, read_upto, short
from ..rundir import RunDirError
from .arms import arm_config, arm_overrides

__all__ = [
    "CONDITION",
    "LIMITS",
    "MANIFEST",
    "MANIFEST_VERSION",
    "ManifestError",
    "arm_config",
    "arm_order",
    "check_condition",
    "check_manifest",
    "read_json",
    "read_manifest",
    "resume_task",
]

MANIFEST = "reproduce.json"
CONDITION = "condition.json"  # the condition experiment's result, written whole at its end
MANIFEST_VERSION = 1

# Ranges of a manifest's integer fields (inclusive). They bound what one reproduction may
# ask for (a run per arm and seed, each generation a program; the condition experiment
# records [2 inits, iters] condition numbers); `reproduce` checks the same limits.
LIMITS = {
    "runs": (1, 10_000),
    "generations": (0, 2**31 - 1),
    "seed": (0, 2**32 - 1),
    "devices": (1, 4096),
    "workers_per_device": (1, 1024),
    "condition_iters": (1, 1_000_000),
    "condition_inits": (1, 100),
}
_MAX_PRUNERS = 32
_MAX_BYTES = {MANIFEST: 1 << 20, CONDITION: 1 << 29}
_REQUIRED = ("task_meta", "runs", "generations", "pruners", "config", "seed", "devices",
             "workers_per_device", "condition", "condition_iters", "condition_inits",
             "condition_dtype")  # fmt: skip
# arm_runs: {arm: runs} where an arm's count differs from ``runs``; arm_overrides: {arm:
# the fields it set}, checked against this version's registry (`eant2_jax.app.arms`).
_OPTIONAL = ("version", "lockstep", "arm_runs", "arm_overrides")


class ManifestError(RunDirError):
    """A reproduction's ``reproduce.json`` (or ``condition.json``) that is missing, not
    whole or not valid: one line naming the file and the field."""


def read_json(path: str | Path, *, strict: bool = True) -> Any:
    """A JSON file of a reproduction, read as data: a regular file (not through a link),
    at most its cap in bytes, strict JSON (``strict=False`` allows the non-finite numbers
    ``condition.json`` holds). Any problem is a one-line `ManifestError`."""
    path = Path(path)
    cap = _MAX_BYTES.get(path.name, 1 << 20)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        raise ManifestError(f"{path}: cannot read it ({e.strerror})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ManifestError(f"{path}: not a regular file")
        data = read_upto(fd, cap)
    except OSError as e:
        raise ManifestError(f"{path}: cannot read it ({e.strerror})") from None
    finally:
        os.close(fd)
    if len(data) > cap:
        raise ManifestError(f"{path}: more than {cap} bytes")
    return loads(data, str(path), strict=strict, error=ManifestError)


def _int(m: dict, name: str, where: str) -> int:
    value = m[name]
    low, high = LIMITS[name]
    if isinstance(value, bool) or not isinstance(value, int):
        raise ManifestError(f"{where}: {name} must be an integer, got {short(value)}")
    if not low <= value <= high:
        raise ManifestError(f"{where}: {name} must be in [{low}, {high}], got {short(value)}")
    return value


def _bool(m: dict, name: str, where: str) -> bool:
    if not isinstance(m[name], bool):
        raise ManifestError(f"{where}: {name} must be true or false, got {short(m[name])}")
    return m[name]


def _task_meta(meta: Any, where: str) -> dict:
    if not isinstance(meta, dict) or set(meta) != {"task", "task_options"}:
        raise ManifestError(
            f"{where}: task_meta must be an object with task and task_options, got {short(meta)}"
        )
    if not isinstance(meta["task"], str) or not 0 < len(meta["task"]) <= 1000:
        raise ManifestError(f"{where}: task_meta.task must be a task's name, got "
                            f"{short(meta['task'])}")  # fmt: skip
    if not isinstance(meta["task_options"], dict):
        raise ManifestError(
            f"{where}: task_meta.task_options must be an object, got {short(meta['task_options'])}"
        )
    return {"task": meta["task"], "task_options": dict(meta["task_options"])}


def _pruners(pruners: Any, where: str) -> list[str]:
    if not isinstance(pruners, list) or len(pruners) > _MAX_PRUNERS:
        raise ManifestError(
            f"{where}: pruners must be a list of at most {_MAX_PRUNERS} arms, got {short(pruners)}"
        )
    for p in pruners:
        if not isinstance(p, str):
            raise ManifestError(f"{where}: pruners must name arms, got {short(p)}")
        try:
            arm_config(EANT2Config(), p)
        except ValueError as e:
            raise ManifestError(f"{where}: pruners: {e}") from None
    arms = [p for p in pruners if p != "none"]
    twice = sorted({p for p in arms if arms.count(p) > 1})
    if twice:
        raise ManifestError(f"{where}: pruners: arm {twice[0]!r} given twice")
    return list(pruners)


def _arm_runs(m: dict, arms: list[str], where: str) -> dict[str, int]:
    """Each arm's run count: ``arm_runs``' where given, else ``runs``."""
    given = m.get("arm_runs", {})
    if not isinstance(given, dict):
        raise ManifestError(f"{where}: arm_runs must be an object, got {short(given)}")
    out = {arm: m["runs"] for arm in arms}
    for arm, n in given.items():
        if arm not in out:
            raise ManifestError(f"{where}: arm_runs names {short(arm)}, not an arm of pruners")
        out[arm] = _int({"runs": n}, "runs", f"{where}: arm_runs.{arm}")
    if m["seed"] + max(out.values()) > 2**32:
        raise ManifestError(f"{where}: seed + runs must be at most 2**32")
    return out


def _arm_recorded(m: dict, arms: list[str], where: str) -> None:
    """``arm_overrides``, when recorded, must be what this version's registry sets for each
    arm: a reproduction resumes with the arms it started with, or not at all."""
    if "arm_overrides" not in m:
        return
    rec = m["arm_overrides"]
    if not isinstance(rec, dict) or set(rec) != set(arms):
        raise ManifestError(f"{where}: arm_overrides must be an object with one entry per arm")
    for arm in arms:
        if rec[arm] != arm_overrides(arm):
            raise ManifestError(
                f"{where}: arm_overrides.{arm} is {short(rec[arm])}, but this version's arm "
                f"{arm} sets {short(arm_overrides(arm))}"
            )


def _config(config: Any, where: str) -> EANT2Config:
    try:
        return EANT2Config.from_dict(config, complete=True)
    except (ValueError, TypeError, OverflowError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ManifestError(f"{where}: config: {first}") from None


def check_manifest(m: Any, where: str) -> dict:
    """The settings of a manifest, each checked by type and range, as keyword arguments of
    `eant2_jax.app.experiments.reproduce` (``config`` an `EANT2Config`, ``lockstep``
    False when absent: reproductions written before lock-step ran each run alone).

    Raises:
      ManifestError: one line naming ``where`` and the first field found wrong.
    """
    if not isinstance(m, dict):
        raise ManifestError(f"{where}: not a reproduce.json (not a JSON object)")
    missing = [k for k in _REQUIRED if k not in m]
    if m.get("version") != MANIFEST_VERSION or isinstance(m.get("version"), bool) or missing:
        more = f" (missing: {', '.join(missing)})" if missing else ""
        raise ManifestError(
            f"{where}: not a reproduce.json of version {MANIFEST_VERSION} with "
            f"{', '.join(_REQUIRED)}{more}"
        )
    unknown = sorted(set(m) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise ManifestError(f"{where}: unknown field {short(unknown[0])}")
    out: dict = {"task_meta": _task_meta(m["task_meta"], where)}
    for name in ("runs", "generations", "seed", "workers_per_device"):
        out[name] = _int(m, name, where)
    for name in ("condition_iters", "condition_inits"):
        out[name] = _int(m, name, where)
    if out["seed"] + out["runs"] > 2**32:
        raise ManifestError(f"{where}: seed + runs must be at most 2**32")
    out["devices"] = "all" if m["devices"] == "all" else _int(m, "devices", where)
    out["pruners"] = _pruners(m["pruners"], where)
    arms = arm_order(out["pruners"])
    out["arm_runs"] = _arm_runs(m, arms, where)
    _arm_recorded(m, arms, where)
    out["condition"] = _bool(m, "condition", where)
    out["lockstep"] = _bool(m, "lockstep", where) if "lockstep" in m else False
    if m["condition_dtype"] not in ("float32", "float64"):
        got = short(m["condition_dtype"])
        raise ManifestError(f"{where}: condition_dtype must be float32 or float64, got {got}")
    out["condition_dtype"] = m["condition_dtype"]
    out["config"] = _config(m["config"], where)
    return out


def arm_order(pruners: list[str]) -> list[str]:
    """The arms of a manifest's ``pruners`` in the order they are reported: as given, then
    ``none`` (always one of them)."""
    return [p for p in pruners if p != "none"] + ["none"]


def read_manifest(out: str | Path) -> dict:
    """`check_manifest` of ``out/reproduce.json``, read with `read_json`.

    Raises:
      ManifestError: ``out`` holds no readable, valid manifest (one line).
    """
    path = Path(out) / MANIFEST
    if not path.exists() and not path.is_symlink():
        raise ManifestError(f"{out}: not a reproduction (no {MANIFEST})")
    try:
        m = read_json(path)
    except ManifestError as e:
        raise ManifestError(f"{out}: not a reproduction ({e})") from None
    return check_manifest(m, str(path))


def resume_task(task_meta: dict, where: str):
    """The task a manifest records, rebuilt only when it is a registered task or a task of a
    registered family: a ``module:factory`` or ``file.py`` spec read from a file is never
    imported (pass the task to `eant2_jax.app.experiments.resume_reproduction` instead).

    Raises:
      ManifestError: the task is not registered, or its options do not build it.
    """
    from .. import tasks

    spec = task_meta["task"]
    if not tasks.is_registered(spec):
        raise ManifestError(
            f"{where}: task_meta.task {short(spec)} is not a registered task; a reproduction "
            "of a user task is resumed only with that task given again (its code is never "
            "imported from a file's say-so)"
        )
    try:
        return tasks.make(spec, **task_meta["task_options"])
    except (ValueError, TypeError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ManifestError(f"{where}: task_meta: {first}") from None


def _numbers(value: Any, depth: int) -> bool:
    """A non-empty list of numbers (``depth`` 1) or of such lists (``depth`` 2)."""
    if not isinstance(value, list) or not value:
        return False
    if depth == 2:
        return all(_numbers(v, 1) for v in value)
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)


def check_condition(d: Any, where: str) -> dict:
    """A ``condition.json`` read back (a resumed reproduction reuses it): the fields the
    report and the claims read, checked by type. ManifestError naming the field, else
    ``d``."""
    if not isinstance(d, dict):
        raise ManifestError(f"{where}: not a condition experiment's result (not an object)")
    checks = {
        "before": lambda v: _numbers(v, 2) or _numbers(v, 1),
        "after": lambda v: _numbers(v, 2) or _numbers(v, 1),
        "peak_before": lambda v: _numbers(v, 1),
        "peak_after": lambda v: _numbers(v, 1),
        "size_before": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
        "size_after": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
        "genome_before": lambda v: isinstance(v, str),
        "genome_after": lambda v: isinstance(v, str),
        "dtype": lambda v: v in ("float32", "float64"),
        "max_condition": lambda v: isinstance(v, int | float) and not isinstance(v, bool)
        and not math.isnan(v),
    }  # fmt: skip
    for name, ok in checks.items():
        if name not in d or not ok(d[name]):
            raise ManifestError(
                f"{where}: {name} is missing or not what the condition experiment writes "
                f"(delete the file to run the experiment again)"
            )
    return d
