"""A TensorNEAT training run's state between processes, so that a run longer than one device
call goes on where the last call stopped (bench/field_tensorneat.py, ``rundir``).

The state is TensorNEAT's ``Pipeline`` state after a generation: a pytree of arrays, saved as
its leaves in one ``.npz`` (written beside, then moved over the last one: a kill leaves the
old file or the new, never half of one) with the generations it has run and a digest of the
run's settings. It is read back without pickle into the structure of the state a fresh
``Pipeline.setup()`` makes for the same settings: a file of other settings, another
structure, shape or dtype is refused, naming what differs. The step that continues from it
is the compiled step of an uninterrupted run, on the same arrays: the same run to the bit.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import BenchInputError

__all__ = ["load", "save", "settings_digest"]

FILE = "state.npz"


def settings_digest(settings: dict[str, Any]) -> str:
    """What a saved state belongs to: the run's environment, seed and TensorNEAT settings."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def _leaf(x) -> tuple[np.ndarray, str]:
    """A state leaf as saved: its array (a typed key's data) and its key implementation."""
    import jax

    if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
        return np.asarray(jax.random.key_data(x)), str(jax.random.key_impl(x))
    return np.asarray(x), ""


def _spec(x) -> tuple[tuple[int, ...], np.dtype, str]:
    """What `_leaf` would save of ``x``: shape, dtype and key implementation, without
    copying it to the host."""
    import jax

    if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
        data = jax.eval_shape(jax.random.key_data, x)
        return data.shape, np.dtype(data.dtype), str(jax.random.key_impl(x))
    return tuple(np.shape(x)), np.dtype(x.dtype), ""


def save(rundir: str | Path, state, generation: int, digest: str) -> None:
    """Save ``state`` after ``generation`` generations of the run ``digest`` names."""
    import jax

    folder = Path(rundir)
    folder.mkdir(parents=True, exist_ok=True)
    leaves = [_leaf(x) for x in jax.tree.leaves(state)]
    arrays = {f"leaf{i}": a for i, (a, _) in enumerate(leaves)}
    tmp = folder / "state.tmp.npz"
    np.savez(tmp, generation=np.int64(generation), digest=np.array(digest),
             keys=np.array(json.dumps([impl for _, impl in leaves])), **arrays)  # fmt: skip
    tmp.replace(folder / FILE)


def load(rundir: str | Path, template, digest: str) -> tuple[Any, int] | None:
    """``(state, generations run)`` from ``rundir``, in ``template``'s structure (the state a
    fresh setup of the same run makes); None when no state was saved there."""
    import jax
    import jax.numpy as jnp

    path = Path(rundir) / FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
        generation, saved = int(data["generation"]), str(data["digest"])
        impls = json.loads(str(data["keys"]))
    except (OSError, ValueError, KeyError) as e:
        raise BenchInputError(f"TensorNEAT state {path}: cannot read it ({e})") from None
    if saved != digest:
        raise BenchInputError(f"TensorNEAT state {path} belongs to a run of other settings")
    if generation < 0:
        raise BenchInputError(f"TensorNEAT state {path}: generation {generation} < 0")
    want, treedef = jax.tree.flatten(template)
    names = [f"leaf{i}" for i in range(len(want))]
    if len(impls) != len(want) or sorted(data) != sorted(["generation", "digest", "keys", *names]):
        raise BenchInputError(f"TensorNEAT state {path}: {len(impls)} arrays, the run has "
                              f"{len(want)}")  # fmt: skip
    leaves = []
    for i, (t, impl) in enumerate(zip(want, impls, strict=True)):
        a, (shape, dtype, t_impl) = data[names[i]], _spec(t)
        if impl != t_impl or a.shape != shape or a.dtype != dtype:
            raise BenchInputError(
                f"TensorNEAT state {path}: array {i} is {impl or a.dtype}{list(a.shape)}, the "
                f"run's is {t_impl or dtype}{list(shape)}"
            )
        leaves.append(jax.random.wrap_key_data(a, impl=impl) if impl else jnp.asarray(a))
    return jax.tree.unflatten(treedef, leaves), generation
