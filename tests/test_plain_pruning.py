"""Pruning's plain cases (docs/protocol.md, section 5; docs/pruning.md, "Plain cases").

Through `optimize(genome, task, key=..., pruner="covariance")` with every other option at
its default, on four small noiseless regressions whose redundancy is known: an input with no
effect, a duplicated bias, two parallel connections, a duplicated hidden neuron. Each case
on the protocol's reported seeds 6000-6019 (the rule was chosen on seeds 100-199): a seed
holds if the redundant connection is gone from the returned network and nothing it needs
is; the protocol asks for at least 18 of 20, a claim measured on one machine: another CPU
model rounds differently and its searches take other paths (docs/algorithm.md,
"Determinism and keys"; docs/pruning.md, section 11), so elsewhere the suite asks for three
in four. Nothing needed may ever be lost, on any machine. And: ``add_bias`` never gives a
neuron a second bias.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest
from docs_outputs import recording_machine
from hypothesis import given
from hypothesis import strategies as st
from strategies import genomes

from eant2_jax import optimize
from eant2_jax.exploration import OPERATORS, initial_genome, mutate
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.tasks import regression

SEEDS = range(6000, 6020)  # docs/protocol.md: the plain cases' reported seeds
HELD = 18  # of 20: the protocol's 90%, on the machine the docs were recorded on
FLOOR = 15  # of 20, on another CPU model (docs/pruning.md, section 11)
N_SAMPLES = 64


def _inputs(genome: Genome, i: int) -> list[tuple[GeneKind, int]]:
    """``(kind, ref)`` of each direct input of the neuron at gene ``i``."""
    return [(genome[k].kind, genome[k].ref) for k in genome.children(i)]


def _neurons(genome: Genome, hidden: bool) -> list[int]:
    """Gene indices of the hidden (or root) neurons."""
    return [
        i
        for i, g in enumerate(genome)
        if g.kind == GeneKind.NEURON and (genome.parent[i] >= 0) == hidden
    ]


def _count(genome: Genome, kind: GeneKind, ref: int) -> int:
    return sum(1 for g in genome if g.kind == kind and g.ref == ref)


I0, I1, BIAS = (GeneKind.INPUT, 0), (GeneKind.INPUT, 1), (GeneKind.BIAS, -1)


# Each check: (the redundancy is gone, nothing needed is lost) of the returned network.
def _no_effect(g: Genome) -> tuple[bool, bool]:
    return _count(g, GeneKind.INPUT, 2) == 0, {I0, I1} <= set(_inputs(g, 0))


def _bias(g: Genome) -> tuple[bool, bool]:
    (hidden,) = _neurons(g, hidden=True)  # the output reads it alone: it cannot go
    reads = _inputs(g, hidden)
    return reads.count(BIAS) <= 1, {I0, BIAS} <= set(reads)


def _parallel(g: Genome) -> tuple[bool, bool]:
    reads = _inputs(g, 0)
    return reads.count(I0) <= 1, {I0, I1} <= set(reads)


def _duplicate(g: Genome) -> tuple[bool, bool]:
    hidden = _neurons(g, hidden=True)
    return len(hidden) <= 1, any(sorted(_inputs(g, i)) == [I0, I1] for i in hidden)


@functools.cache
def plain_cases(output: str) -> dict[str, tuple]:
    """``name: (task, genome text, check)``: targets the genome represents exactly (no
    noise), 64 samples of three standard normal inputs."""
    x = np.random.default_rng(0).normal(size=(N_SAMPLES, 3))
    f = np.tanh if output == "tanh" else (lambda v: v)
    x0, x1 = x[:, :1], x[:, 1:2]
    cases = {
        "no_effect": (f(x0 - x1), "N0/3*1 I0*0.5 I1*-0.5 I2*0.3", _no_effect),
        "bias": (f(np.tanh(x0 + 0.5)), "N0/1*1 N1/3*1 I0*0.5 B*0.2 B*0.3", _bias),
        "parallel": (f(1.5 * x0 - x1), "N0/3*1 I0*0.7 I0*0.8 I1*-0.5", _parallel),
        "duplicate": (
            f(1.2 * np.tanh(x0 + x1)),
            "N0/2*1 N1/2*0.6 I0*1.0 I1*1.0 N2/2*0.5 I0*0.9 I1*1.1",
            _duplicate,
        ),
    }
    return {
        name: (regression(x, y, hidden="tanh", output=output), text, check)
        for name, (y, text, check) in cases.items()
    }


def test_the_checks_see_the_redundancy():
    """Each start network fails its own check (the redundancy is there) but keeps what is
    needed; its obvious reduction passes (the checks can fail and can pass)."""
    reduced = {
        "no_effect": "N0/2*1 I0*1 I1*-1",
        "bias": "N0/1*1 N1/2*1 I0*1 B*0.5",
        "parallel": "N0/2*1 I0*1.5 I1*-1",
        "duplicate": "N0/1*1.2 N1/2*1 I0*1 I1*1",
    }
    for name, (_, text, check) in plain_cases("identity").items():
        assert check(Genome.parse(text)) == (False, True), name
        assert check(Genome.parse(reduced[name])) == (True, True), name
    assert _no_effect(Genome.parse("N0/1*1 I0*1")) == (True, False)
    assert _duplicate(Genome.parse("N0/2*1 N1/1*1 I0*1 N2/1*1 I1*1"))[1] is False


@pytest.mark.slow
@pytest.mark.parametrize("output", ["identity", "tanh"])
@pytest.mark.parametrize("name", ["no_effect", "bias", "parallel", "duplicate"])
def test_plain_case_is_pruned_with_defaults(name, output):
    task, text, check = plain_cases(output)[name]
    held, lost = [], []
    for seed in SEEDS:
        res = optimize(text, task, key=jax.random.key(seed), pruner="covariance")
        gone, kept = check(res.genome)
        if not kept:
            lost.append((seed, str(res.genome)))
        if gone and kept:
            held.append(seed)
    assert not lost, lost  # nothing needed is ever removed
    # HELD on the recording machine, FLOOR elsewhere. Which machine this is (`eant2 demo` in
    # a fresh process) matters only for a count between the two: asked only then.
    missed = (name, output, sorted(set(SEEDS) - set(held)))
    if len(held) < HELD:
        assert not recording_machine() and len(held) >= FLOOR, missed


# ------------------------------------------------------------------------------- add_bias
def _biases(genome: Genome) -> dict[int, int]:
    """Neuron id -> how many bias genes it reads directly."""
    return {
        genome[i].ref: _inputs(genome, i).count(BIAS)
        for i in _neurons(genome, hidden=True) + _neurons(genome, hidden=False)
    }


@given(genomes(n_inputs=3, max_neurons=6), st.integers(0, 2**32 - 1))
def test_add_bias_never_gives_a_neuron_a_second_bias(parent, seed):
    """On random genomes (some neurons reading one bias or several): the child's new bias
    goes to a neuron that had none, every other count is unchanged, and there is no child
    exactly when every neuron has a bias already."""
    rng = np.random.default_rng(seed)
    before = _biases(parent)
    for _ in range(5):
        child = mutate(rng, parent, "add_bias", n_inputs=3, next_id=99)
        if child is None:
            assert all(n >= 1 for n in before.values())
            continue
        after = _biases(child)
        (grown,) = [n for n in after if after[n] != before[n]]
        assert before[grown] == 0 and after[grown] == 1


@given(st.integers(0, 2**32 - 1))
def test_mutation_walks_keep_one_bias_per_neuron(seed):
    """From a minimal start, 40 mutations of random operators (as a run draws them): no
    neuron ever reads two biases."""
    rng = np.random.default_rng(seed)
    g, next_id = initial_genome(rng, 3, 1), 1
    for _ in range(40):
        op = OPERATORS[int(rng.integers(len(OPERATORS)))]
        child = mutate(rng, g, op, n_inputs=3, next_id=next_id)
        if child is not None:
            g, next_id = child, next_id + (op == "add_subnetwork")
        assert max(_biases(g).values()) <= 1, str(g)
