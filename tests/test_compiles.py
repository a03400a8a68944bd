"""The compile counter of ``tests/compiles.py``: JAX still emits the event it listens to,
with the program's name, once per compilation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import count_compiles, nondeterministic_scatters


def test_counts_each_new_program_once_by_name():
    @jax.jit
    def counted_program(x):
        return x * 2 + 1

    with count_compiles() as c:
        counted_program(np.ones(3, np.float32))
        assert c.of("counted_program") == 1, c.names
        counted_program(np.zeros(3, np.float32))  # same shapes: the cached program
        assert c.of("counted_program") == 1, c.names
        with count_compiles() as inner:  # blocks nest
            counted_program(np.ones(4, np.float32))  # a new shape: a new program
    assert inner.of("counted_program") == 1, inner.names
    assert c.of("counted_program") == c.of("jit(counted_program)") == 2, c.names
    assert c.by_name()["jit(counted_program)"] == 2 and c.seconds > 0
    with count_compiles() as again:
        counted_program(np.ones(4, np.float32))
    assert again.count == 0, again.names
    counted_program(np.ones(5, np.float32))  # outside every block: counted nowhere
    assert c.of("counted_program") == 2 and again.count == 0


@pytest.mark.slow
def test_compilation_cache_keeps_programs_between_processes(tmp_path):
    # In fresh processes (the cache is a global JAX setting): the first compiles and writes
    # every program, the second loads them (JAX counts cache hits through jax.monitoring).
    import subprocess
    import sys

    code = (
        "import jax, jax.numpy as jnp, eant2_jax\n"
        "hits = []\n"
        "jax.monitoring.register_event_listener("
        "lambda e, **k: hits.append(e) if e == '/jax/compilation_cache/cache_hits' else None)\n"
        f"assert eant2_jax.enable_compilation_cache({str(tmp_path / 'c')!r}) is not None\n"
        "jax.jit(lambda x: jnp.sin(x) * 3)(jnp.ones(7)).block_until_ready()\n"
        "print(len(hits))\n"
    )
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-2000:]
    assert first.stdout.strip() == "0" and any((tmp_path / "c").iterdir())
    second = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert second.returncode == 0, second.stderr[-2000:]
    assert int(second.stdout) >= 1


def test_nondeterministic_scatters_finds_them_where_they_hide():
    """The helper the determinism tests rely on sees float scatter-adds inside jit, remat
    and scan, and leaves unique-index and integer scatters alone."""
    idx = jnp.array([0, 1, 1])

    def add(x):
        return jnp.zeros(4).at[idx].add(x)

    nested = jax.jit(lambda x: jax.lax.scan(lambda c, _: (c + jax.checkpoint(add)(x), None),
                                            jnp.zeros(4), None, length=2)[0])  # fmt: skip
    assert nondeterministic_scatters(jax.make_jaxpr(nested)(jnp.ones(3))) == [
        "scatter-add -> float32[4]"
    ]
    unique = lambda x: jnp.zeros(4).at[jnp.arange(3)].set(x, unique_indices=True)  # noqa: E731
    ints = lambda x: jnp.zeros(4, jnp.int32).at[idx].add(x)  # noqa: E731
    assert nondeterministic_scatters(jax.make_jaxpr(unique)(jnp.ones(3))) == []
    assert nondeterministic_scatters(jax.make_jaxpr(ints)(jnp.ones(3, jnp.int32))) == []
