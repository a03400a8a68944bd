"""``--peer-runs DIR`` of ``python -m bench field --protocol``: TensorNEAT's finished training
runs shared between calls that would train it again on the same seeds with the same settings
(docs/protocol.md section 6: the batch-width candidates of a choice seed).

``DIR/{env}-s{seed}-tensorneat.json`` is the run's JSON as its training process wrote it
(with the orchestrator's ``process_s``) and ``peer_settings``: everything its run depends on
(`settings`). A later call with the same DIR judges that run in place of training TensorNEAT
again, with its measured wall times (it is the same deterministic run), only where the
settings equal its own; a file made with other settings is refused, the settings that differ
named. Only runs that finished are shared: ``done``, no ``error``, and not stopped at the
orchestrator's ``--deadline-s`` (where such a run stops depends on the wall clock, not on its
settings). A file here is data: read as JSON alone, never imported, executed or unpickled.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from bench.common import BenchInputError, hash_sources
from bench.field_settings import ENVS

__all__ = ["METHOD", "find", "finished", "publish", "settings", "source_digest"]

METHOD = "tensorneat"  # the method whose runs are shared (eant2_jax's is what a trial varies)
_TRAINER = Path(__file__).resolve().with_name("field_tensorneat.py")


def source_digest(src: str | Path) -> str:
    """SHA-256 of TensorNEAT's source (the ``.py`` files of ``src/tensorneat``, by relative
    path) and of the bench code that drives it (``bench/field_tensorneat.py``)."""
    h = hashlib.sha256()
    hash_sources(h, Path(src) / "tensorneat")
    h.update(_TRAINER.read_bytes())
    return h.hexdigest()


def settings(env: str, seed: int, *, pop: int, generations: int, src: str | Path,
             device: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """What a TensorNEAT training run depends on, as its shared file records it.

    Args:
      env, seed: the environment (a key of `ENVS`) and the seed.
      pop, generations: the run's population and generations (the frozen ones, or a trial's
        ``--budget``/``--tensorneat-pop``).
      src: the folder holding TensorNEAT's package (`source_digest`).
      device: the orchestrator's `bench.common.environment` (its device kind and jax
        version: the wall times are the device's).
    """
    frozen = {k: v for k, v in ENVS[env].items() if k != "eant2"}  # TensorNEAT's and both's
    return json.loads(json.dumps({
        "method": METHOD, "env": env, "seed": seed, "frozen": frozen, "pop_size": pop,
        "generations": generations, "source_sha256": source_digest(src),
        "device_kind": device.get("device_kind"), "jax_version": device.get("jax_version"),
    }))  # fmt: skip


def finished(run: dict[str, Any]) -> bool:
    """Whether a training run may be shared: done, no error, not stopped at a deadline."""
    return bool(run.get("done")) and not run.get("error") and not run.get("deadline")


def _path(folder: str | Path, env: str, seed: int) -> Path:
    return Path(folder) / f"{env}-s{seed}-{METHOD}.json"


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def find(folder: str | Path, env: str, seed: int, want: dict[str, Any]) -> dict[str, Any] | None:
    """The shared run of ``env`` and ``seed`` made with the settings ``want``, marked
    ``reused_from`` (its file); None where the folder holds none.

    Raises:
      BenchInputError: the file is not a finished run's JSON object written by `publish`, or
        was made with other settings (those that differ named, the file's and this call's).
    """
    path = _path(folder, env, seed)
    if not path.is_file():
        return None
    try:
        run = json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError) as e:
        raise BenchInputError(f"--peer-runs: {path} is not a JSON run file ({e})") from None
    if not isinstance(run, dict) or not isinstance(run.get("peer_settings"), dict):
        raise BenchInputError(f"--peer-runs: {path} holds no peer_settings (not a shared run)")
    if not finished(run):
        raise BenchInputError(f"--peer-runs: {path} is not a finished run (done, no error)")
    there, here = _flat(run.pop("peer_settings")), _flat(want)
    differ = [f"{k} {there.get(k)!r} in the file, {here.get(k)!r} asked"
              for k in sorted(set(there) | set(here)) if there.get(k) != here.get(k)]  # fmt: skip
    if differ:
        raise BenchInputError(f"--peer-runs: {path} was made with other TensorNEAT settings "
                              f"({'; '.join(differ)}); give another folder")  # fmt: skip
    run["reused_from"] = str(path)
    return run


def publish(folder: str | Path, run: dict[str, Any], want: dict[str, Any]) -> Path | None:
    """Copy a finished run (not itself a reused one) into ``folder`` with its settings
    ``want``, unless the folder holds that run already; the file written, or None."""
    if not finished(run) or run.get("reused_from"):
        return None
    path = _path(folder, want["env"], want["seed"])
    if path.exists():
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps({**run, "peer_settings": want}))
    os.replace(tmp, path)  # whole or not at all: a killed call leaves no half file
    return path
