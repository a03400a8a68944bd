"""Activation functions: every JAX form against its NumPy reference, and the user registry.

Tolerance of the elementwise check (float32 JAX on float32 inputs, float64 NumPy on the same
values): the scaled activations round their argument (``5a``, at most 60 after clamping) in
float32, half an ulp of 60 = 1.9e-6 absolute, and ``exp`` of an argument up to 60 carries
its relative error times 60 (60 * 6e-8 = 3.6e-6 relative); both are below 1e-5, hence
``rtol = atol = 1e-5``. The network check uses test_evaluate's tolerance (1e-4 of the
genome's output scale), stated there.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from compiles import count_compiles
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from strategies import fewer_examples
from test_evaluate import assert_close, reference

import eant2_jax
from eant2_jax.genome import Genome
from eant2_jax.kernels import activations
from eant2_jax.kernels import network as kn

# At least the activations neat-python and TensorNEAT offer (issue 17), and the first four.
REQUIRED = {"identity", "tanh", "sigmoid", "relu", "sin", "gauss", "abs", "clamped"}
REQUIRED |= {"softplus", "elu", "selu", "lelu", "square", "cube", "log", "exp"}
BUILTIN = sorted(activations.BUILTIN)
# A recurrent genome with forward jumpers, two outputs and depth 3.
GENOMES = [
    "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4",
    "N4/2*0.8 N5/2*-0.6 N6/1*1.1 I1*0.9 R5*0.4 I0*0.7 N7/2*0.5 B*-0.3 I2*1.2",
]


def test_builtins_cover_neat_python():
    assert REQUIRED <= set(activations.names())
    assert set(BUILTIN) == set(activations.names())  # no user entry left behind


@pytest.mark.slow
@pytest.mark.parametrize("name", BUILTIN)
@fewer_examples(0.3)
@given(
    x=hnp.arrays(
        np.float32,
        64,  # one shape: one program per name
        elements=st.floats(-80, 80, width=32)
        | st.sampled_from([0.0, 1e-7, -3.4, 3.4, 12.0, -12.0, 60.0, -60.0]),
    )
)
def test_jax_matches_numpy(name, x):
    act = activations.get(name)
    got = np.asarray(act.jax(jnp.asarray(x)), np.float64)
    want = act.numpy(x.astype(np.float64))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", BUILTIN)
def test_source_is_the_same_function(name):
    """The exportable source of each built-in computes what its JAX function computes."""
    import jax

    act = activations.get(name)
    a = jnp.linspace(-5.0, 5.0, 101)
    got = eval(act.source, {"jnp": jnp, "jax": jax, "a": a})  # noqa: S307
    np.testing.assert_array_equal(np.asarray(got), np.asarray(act.jax(a)))


# The built-ins two by two, one program each: every name once, as the hidden or the output
# activation (the last one with the first). The compiled path resolves both names through
# the same registry lookup and applies them independently (test_evaluate's
# test_each_activation_as_hidden_and_as_output), so a name's role adds no path of its own.
PAIRS = list(zip(BUILTIN[0::2], [*BUILTIN[1::2], BUILTIN[0]], strict=True))
assert {name for pair in PAIRS for name in pair} == set(BUILTIN)


@pytest.mark.slow
@pytest.mark.parametrize(("hidden", "output"), PAIRS)
def test_network_matches_reference(hidden, output):
    """The compiled path resolves every name through the registry and computes what the
    reference computes with that name's NumPy function."""
    batch = [Genome.parse(g) for g in GENOMES]
    seed = sum(map(ord, hidden + output))
    x = np.random.default_rng(seed).uniform(-1.5, 1.5, size=(4, 3, 3)).astype(np.float32)
    got = eant2_jax.evaluate(batch, x, hidden=hidden, output=output)
    assert_close(got, reference(batch, x, hidden, output))


# ------------------------------------------------------------------------------ the registry
@pytest.fixture
def user_names():
    """Names registered by a test, removed afterwards (the registry is process-wide)."""
    added: list[str] = []
    yield added
    for name in set(added) - activations.BUILTIN:
        activations.ACTIVATIONS.pop(name, None)


def _softsign(xp):
    return lambda a: a / (1.0 + xp.abs(a))


@pytest.mark.slow
def test_register_runs_in_the_kernels_and_compiles_once(user_names):
    user_names.append("softsign")
    eant2_jax.register_activation("softsign", _softsign(jnp), _softsign(np))
    batch = [Genome.parse(g) for g in GENOMES]
    x = np.random.default_rng(0).normal(size=(3, 2, 3)).astype(np.float32)
    got = eant2_jax.evaluate(batch, x, hidden="softsign", output="tanh")
    assert_close(got, reference(batch, x, "softsign", "tanh"))
    with count_compiles() as c:  # the name is static: the same name, the same program
        eant2_jax.evaluate(batch, x + 1, hidden="softsign", output="tanh")
    assert c.of("rollout_batch") == 0


@pytest.mark.slow
def test_overwrite_drops_programs_of_the_old_function(user_names):
    user_names.append("mine")
    eant2_jax.register_activation("mine", lambda a: 2.0 * a, lambda a: 2.0 * a)
    g, x = "N0/1*1 I0*1", np.ones((1, 1, 1))
    assert float(eant2_jax.evaluate(g, x, hidden="tanh", output="mine").ravel()[0]) == 2.0
    eant2_jax.register_activation("mine", lambda a: 3.0 * a, lambda a: 3.0 * a, overwrite=True)
    assert float(eant2_jax.evaluate(g, x, hidden="tanh", output="mine").ravel()[0]) == 3.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("tanh", jnp.tanh, np.tanh), "built in"),
        (("two words", jnp.tanh, np.tanh), "identifier"),
        (("half", lambda a: a / 2, lambda a: a / 3), "disagree at a = -4"),
        (("total", jnp.sum, np.sum), "elementwise"),
    ],
)
def test_register_refuses(args, message, user_names):
    user_names.append(args[0])
    with pytest.raises(ValueError, match=message):
        eant2_jax.register_activation(*args)
    assert args[0] == "tanh" or args[0] not in activations.ACTIVATIONS


def test_register_twice_needs_overwrite(user_names):
    user_names.append("twice")
    eant2_jax.register_activation("twice", jnp.tanh, np.tanh)
    with pytest.raises(ValueError, match="already registered"):
        eant2_jax.register_activation("twice", jnp.tanh, np.tanh)


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown activation 'gelu'; known: abs, clamped, cube"):
        kn.activation("gelu")
