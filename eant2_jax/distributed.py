"""Scale-out through JAX's own distribution: meshes, shardings, ``jax.distributed``.

The batched exploitation is sharded along its STRUCTURE axis on a 1-D mesh (axis ``"s"``):
each device holds whole structures — their CMA-ES states, layouts, candidates and
evaluations — so the big tensors (covariances ``[S, P, P]``, candidate networks
``[S, popsize, ...]``, the task's per-move data) never move between devices, and each
device runs the engine's loop over its own structures (`eant2_jax.exploitation.split_chunk`):
nothing crosses devices within a chunk. Results are those of a single-device run with the
same key (up to float reduction order): a structure's random numbers depend on its own key
and index only, and no reduction runs across structures.

Several processes (hosts) join with `initialize`; every process then runs the same
host-side EANT2 loop (same key, same decisions) and the mesh spans all processes' devices.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

__all__ = [
    "AXIS",
    "P",
    "constrain",
    "gather",
    "initialize",
    "make_mesh",
    "place",
    "replicate",
    "shard",
    "size",
]

AXIS = "s"


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> bool:
    """Join a multi-process run with ``jax.distributed.initialize``.

    Arguments left as None are read from the environment: ``EANT2_COORDINATOR``
    (``host:port`` of process 0), ``EANT2_NUM_PROCESSES`` and ``EANT2_PROCESS_ID``. With
    none of them set anywhere this is a no-op (a single process). On CPU, collectives go
    through gloo.

    Returns:
      True if a multi-process runtime was initialised.
    """
    coordinator_address = coordinator_address or os.environ.get("EANT2_COORDINATOR")
    if num_processes is None and "EANT2_NUM_PROCESSES" in os.environ:
        num_processes = int(os.environ["EANT2_NUM_PROCESSES"])
    if process_id is None and "EANT2_PROCESS_ID" in os.environ:
        process_id = int(os.environ["EANT2_PROCESS_ID"])
    if coordinator_address is None and num_processes is None and process_id is None:
        return False
    if coordinator_address is None or num_processes is None or process_id is None:
        raise ValueError(
            "multi-process runs need the coordinator address, the number of processes and "
            "this process's id (EANT2_COORDINATOR, EANT2_NUM_PROCESSES, EANT2_PROCESS_ID)"
        )
    # Only CPU collectives read this setting; GPUs use NCCL whatever it says.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address, num_processes, process_id)
    return True


def make_mesh(devices: int | str | Sequence[jax.Device] | None) -> Mesh | None:
    """A 1-D mesh over the structure axis.

    Args:
      devices: None (no mesh: JAX's default device), ``"all"`` (every device of every
        process), a count ``N`` (the first N devices), or explicit devices.

    Returns:
      The mesh, or None for a single device.
    """
    if devices is None:
        return None
    everything = jax.devices()
    if isinstance(devices, str):
        if devices != "all":
            raise ValueError(f"devices must be 'all', a count or a list, got {devices!r}")
        chosen = everything
    elif isinstance(devices, int | np.integer):
        if not 1 <= devices <= len(everything):
            raise ValueError(f"devices={devices}: this runtime has {len(everything)} device(s)")
        chosen = everything[: int(devices)]
    else:
        chosen = list(devices)
        if not chosen:
            raise ValueError("devices: empty list")
    if len(chosen) == 1 and jax.process_count() == 1:
        return None
    return Mesh(np.array(chosen), (AXIS,))


def size(mesh: Mesh | None) -> int:
    """Number of devices of a mesh (1 without one)."""
    return 1 if mesh is None else mesh.devices.size


def shard(tree, mesh: Mesh | None):
    """Place a pytree whose leaves have a leading structure axis, split along it."""
    if mesh is None:
        return tree
    split = NamedSharding(mesh, P(AXIS))
    return _put_tree(tree, lambda a: split)


def replicate(tree, mesh: Mesh | None):
    """Place a pytree whole on every device of the mesh."""
    if mesh is None:
        return tree
    whole = NamedSharding(mesh, P())
    return _put_tree(tree, lambda a: whole)


def place(tree, mesh: Mesh | None, rows: int):
    """Split the leaves whose leading axis has length ``rows``; replicate the others."""
    if mesh is None:
        return tree
    return _put_tree(tree, _placement(mesh, rows))


def constrain(tree, mesh: Mesh | None, rows: int):
    """Inside a jitted function: `place`'s rule as sharding constraints, so that a program
    makes its outputs where `place` would put them (nothing moves afterwards)."""
    if mesh is None:
        return tree
    rule = _placement(mesh, rows)
    return jax.tree.map(lambda a: jax.lax.with_sharding_constraint(a, rule(a)), tree)


def _placement(mesh: Mesh, rows: int):
    """`place`'s rule: a leaf whose leading axis has length ``rows`` is split along it."""
    split, whole = NamedSharding(mesh, P(AXIS)), NamedSharding(mesh, P())
    return lambda a: split if np.ndim(a) >= 1 and np.shape(a)[0] == rows else whole


def _put_tree(tree, sharding_of):
    """Every leaf of ``tree`` placed by ``sharding_of(leaf)`` (`_put_all`)."""
    leaves, treedef = jax.tree.flatten(tree)
    return jax.tree.unflatten(treedef, _put_all(leaves, [sharding_of(a) for a in leaves]))


def _put_all(leaves: list, specs: list[NamedSharding]) -> list:
    """Every leaf placed by its sharding. In one process, the arrays go in ONE
    ``jax.device_put`` (its copies batched, not one call and wait per leaf); keys and
    multi-process placement go leaf by leaf (`_put`)."""
    if jax.process_count() > 1:
        return [_put(a, s) for a, s in zip(leaves, specs, strict=True)]
    plain = [i for i, a in enumerate(leaves) if not _is_key(a)]
    placed = jax.device_put([leaves[i] for i in plain], [specs[i] for i in plain])
    out = [_put(a, s) if _is_key(a) else None for a, s in zip(leaves, specs, strict=True)]
    for i, a in zip(plain, placed, strict=True):
        out[i] = a
    return out


def _is_key(a) -> bool:
    return isinstance(a, jax.Array) and jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key)


def _put(a, sharding: NamedSharding):
    if isinstance(a, jax.Array) and a.sharding == sharding:
        return a  # placed already (made on the mesh: `tuning.prepare`)
    if _is_key(a):
        return jax.random.wrap_key_data(
            _put(jax.random.key_data(a), sharding), impl=jax.random.key_impl(a)
        )
    if jax.process_count() == 1:
        return jax.device_put(a, sharding)
    # Multi-process: every process holds the same global value (same key, same decisions),
    # so each one contributes the shards its own devices own.
    a = np.asarray(a)
    return jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])


def gather(tree):
    """Bring a pytree to the host as NumPy arrays, from any sharding or process."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    def get(a):
        if isinstance(a, jax.Array) and not a.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(a, tiled=True))
        return np.asarray(a)

    return jax.tree.map(get, tree)
