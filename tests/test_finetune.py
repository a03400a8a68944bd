"""Gradient fine-tuning (eant2_jax.finetune) against plain references.

* the batched, padded gradient equals ``jax.grad`` of each network's cost written gene by
  gene (the stack semantics in jax.numpy, unpadded), and a central finite difference of the
  NumPy float64 interpreter (`eant2_jax.interpret`);
* padding weights and padding rows stay exactly 0, and a row's gradient there is 0;
* several structures in one batch give what each gives alone (with an optimiser that looks
  at the whole vector, clipping by global norm);
* the same key gives the same weights to the bit; the result is never worse than the start.

Sizes are XOR-sized and every test shares a handful of compiled programs (one bucket, one
task shape, one optimiser object).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bench.common import random_genome
from eant2_jax import EANT2Config, ExploitConfig, compile_genomes, cost, interpret, strategy, tasks
from eant2_jax.compiler import Bucket
from eant2_jax.finetune import finetune, init, run_chunk, value_and_grad
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.kernels import activations

N_IN, N_OUT, T, M = 3, 2, 2, 5
BUCKET = Bucket(neurons=8, genes=24, sweeps=4)
ROWS = 4
STEPS = 20
CLIPPED = optax.chain(optax.clip_by_global_norm(0.05), optax.sgd(0.5))


def _task(seed: int) -> tasks.Regression:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (T, M, N_IN))
    y = np.stack([np.sin(2 * x[..., 0]) * x[..., 1], x[..., 2] ** 2], -1)
    return tasks.regression(x, y)


def _genomes(seed: int, count: int = 3) -> list[Genome]:
    """Fresh random structures of different sizes that fit `BUCKET` (recurrent and forward
    jumpers included)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        g = random_genome(rng, int(rng.integers(8, 18)), n_inputs=N_IN, n_outputs=N_OUT)
        if g.n_params <= BUCKET.genes and g.n_neurons <= BUCKET.neurons and g.depth() <= 4:
            out.append(g)
    return out


def _reference_cost(genome: Genome, w: jax.Array, task: tasks.Regression) -> jax.Array:
    """The task's mean squared error of ONE unpadded network, gene by gene: the stack
    semantics of eant2_jax.genome in jax.numpy (differentiable in ``w`` [n_params])."""
    act_h = activations.get(task.hidden).jax
    act_o = activations.get(task.output).jax
    x = task.inputs
    roots = set(genome.roots)
    prev = {nid: jnp.zeros(x.shape[1]) for nid in genome.neuron_ids}
    ys = []
    for t in range(x.shape[0]):
        current, stack = {}, []
        for i in reversed(range(len(genome))):
            gene = genome[i]
            if gene.kind == GeneKind.INPUT:
                stack.append(w[i] * x[t, :, gene.ref])
            elif gene.kind == GeneKind.BIAS:
                stack.append(w[i] * jnp.ones(x.shape[1]))
            elif gene.kind == GeneKind.FORWARD:
                stack.append(w[i] * current[gene.ref])
            elif gene.kind == GeneKind.RECURRENT:
                stack.append(w[i] * prev[gene.ref])
            else:
                a = sum(stack.pop() for _ in range(gene.arity))
                current[gene.ref] = (act_o if i in roots else act_h)(a)
                stack.append(w[i] * current[gene.ref])
        ys.append(jnp.stack(stack[::-1], axis=-1))
        prev = current
    return jnp.mean(jnp.square(jnp.stack(ys) - task.targets))


_value_and_grad = jax.jit(value_and_grad)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 12])
def test_gradient_matches_unpadded_reference(seed):
    task, genomes = _task(seed), _genomes(seed)
    batch = compile_genomes(genomes, N_IN, bucket=BUCKET, min_rows=ROWS)
    costs, grads = _value_and_grad(batch.layout, batch.weights, task, jax.random.key(0))
    costs, grads = np.asarray(costs), np.asarray(grads)
    for i, g in enumerate(genomes):
        w = jnp.asarray(g.weights, jnp.float32)
        ref_cost, ref_grad = jax.value_and_grad(_reference_cost, argnums=1)(g, w, task)
        # float32 sums in another order: ~1e-6 relative; 1e-5 keeps a margin.
        np.testing.assert_allclose(costs[i], ref_cost, rtol=1e-5)
        np.testing.assert_allclose(grads[i, : g.n_params], ref_grad, rtol=1e-4, atol=1e-6)
        assert np.all(grads[i, g.n_params :] == 0)  # padding genes: exactly 0
    assert np.all(grads[len(genomes) :] == 0)  # padding rows


@pytest.mark.slow
def test_gradient_matches_numpy_finite_difference():
    task, (g, *_) = _task(21), _genomes(21)
    x, y = np.asarray(task.inputs, np.float64), np.asarray(task.targets, np.float64)

    def cost(w):
        return np.mean(np.square(interpret(g, x, weights=w) - y))

    batch = compile_genomes([g], N_IN, bucket=BUCKET, min_rows=ROWS)
    _, grads = _value_and_grad(batch.layout, batch.weights, task, jax.random.key(0))
    # At the float32 weights the program saw, in float64: central differences, h = 1e-5
    # (truncation ~h^2, rounding ~1e-16 / h: both far below float32's ~1e-7 relative).
    w0 = np.asarray(batch.weights[0, : g.n_params], np.float64)
    h = 1e-5
    fd = np.array([(cost(w0 + h * e) - cost(w0 - h * e)) / (2 * h) for e in np.eye(len(w0))])
    np.testing.assert_allclose(np.asarray(grads[0, : g.n_params]), fd, rtol=1e-3, atol=1e-6)


@pytest.mark.slow
def test_padding_stays_zero_and_batch_equals_one_at_a_time():
    task, genomes = _task(31), _genomes(31)
    together = finetune(
        genomes, task, key=jax.random.key(3), optimizer=CLIPPED, steps=STEPS,
        bucket=BUCKET, min_rows=ROWS,
    )  # fmt: skip
    batch = compile_genomes(genomes, N_IN, bucket=BUCKET, min_rows=ROWS)
    st = init(batch.weights, CLIPPED)
    st, _ = run_chunk(st, batch.layout, task, jax.random.key(3), optimizer=CLIPPED, steps=STEPS)
    mask = np.asarray(batch.layout.gene_mask)
    for w in (st.weights, st.best_weights):
        assert np.all(np.asarray(w)[~mask] == 0)  # padding genes and padding rows
    assert np.any(np.asarray(st.weights)[mask] != np.asarray(batch.weights)[mask])
    for i, g in enumerate(genomes):
        alone = finetune(
            [g], task, key=jax.random.key(3), optimizer=CLIPPED, steps=STEPS,
            bucket=BUCKET, min_rows=ROWS,
        )  # fmt: skip
        # The same program, another row: per-row arithmetic, so the same bits.
        np.testing.assert_array_equal(alone.genomes[0].weights, together.genomes[i].weights)
        assert alone.costs[0] == together.costs[i]
        np.testing.assert_array_equal(alone.history[:, 0], together.history[:, i])


@pytest.mark.slow
def test_deterministic_and_never_worse():
    task, genomes = _task(41), _genomes(41)
    # CLIPPED: the program the test above compiled (the default optimiser is the slow
    # tests' and the driver's).
    kwargs = dict(key=jax.random.key(5), optimizer=CLIPPED, steps=STEPS, bucket=BUCKET,
                  min_rows=ROWS)  # fmt: skip
    a = finetune(genomes, task, **kwargs)
    b = finetune(genomes, task, **kwargs)
    for ga, gb in zip(a.genomes, b.genomes, strict=True):
        np.testing.assert_array_equal(ga.weights, gb.weights)
    assert a.costs == b.costs
    assert all(c <= s for c, s in zip(a.costs, a.start_costs, strict=True))
    assert sum(c < s for c, s in zip(a.costs, a.start_costs, strict=True)) >= 2
    assert a.history.shape == (STEPS, len(genomes))
    np.testing.assert_allclose(a.history[0], a.start_costs, rtol=0)
    for g, tuned in zip(genomes, a.genomes, strict=True):
        assert tuned.structure_key() == g.structure_key()
    # The cost reported is the task's cost of the genome returned.
    np.testing.assert_allclose(a.costs, cost(a.genomes, task, key=jax.random.key(0)), rtol=1e-5)


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({"steps": 0}, ValueError, "steps must be an integer >= 1"),
        ({"steps": 2.5}, ValueError, "steps must be an integer >= 1"),
        ({"chunk": True}, ValueError, "chunk must be an integer >= 1"),
        ({"optimizer": "adam"}, TypeError, "optimizer must be an optax GradientTransformation"),
    ],
)
def test_bad_arguments_one_line(kwargs, error, words):
    with pytest.raises(error, match=words) as info:
        finetune(_genomes(51, 1), _task(51), key=jax.random.key(0), **kwargs)
    assert "\n" not in str(info.value)


@pytest.mark.slow
def test_nonfinite_row_skips_its_steps():
    task, genomes = _task(61), _genomes(61, 2)
    batch = compile_genomes(genomes, N_IN, bucket=BUCKET, min_rows=ROWS)
    weights = batch.weights.at[0, 0].set(jnp.inf)
    st = init(weights, CLIPPED)
    st, costs = run_chunk(st, batch.layout, task, jax.random.key(3), optimizer=CLIPPED, steps=STEPS)
    assert not np.any(np.isfinite(np.asarray(costs)[:, 0]))
    np.testing.assert_array_equal(np.asarray(st.weights[0]), np.asarray(weights[0]))
    assert np.isinf(float(st.best_cost[0]))
    assert np.all(np.isfinite(np.asarray(costs)[:, 1]))


@pytest.mark.slow
def test_servo_kinematic_gradient_lowers_its_cost():
    task = tasks.make("servo", n_starts=16)
    rng = np.random.default_rng(71)
    genomes = [random_genome(rng, n, n_inputs=10, n_outputs=3) for n in (36, 44)]
    res = finetune(genomes, task, key=jax.random.key(0), steps=30)
    assert all(c < s for c, s in zip(res.costs, res.start_costs, strict=True))


@pytest.mark.slow
def test_driver_recipe():
    """docs/finetune.md's driver: the stage between strategy.exploit and strategy.tell."""
    task, key, steps = tasks.xor(), jax.random.key(0), 30
    config = EANT2Config(population=4, exploit=ExploitConfig(max_iters=40, pruner="covariance"))
    state, brood = None, strategy.init(key, task, config)
    for _ in range(2):
        tuned = strategy.exploit(brood, task, config)
        polished = finetune(
            tuned.genomes, task, steps=steps, key=jax.random.fold_in(key, 10**6 + brood.generation)
        )
        # The stage starts where CMA-ES ended (the same cost up to another program's
        # rounding) and never ends above it.
        np.testing.assert_allclose(polished.start_costs, tuned.costs, rtol=1e-5, atol=1e-12)
        assert all(p <= s for p, s in zip(polished.costs, polished.start_costs, strict=True))
        tuned = tuned._replace(
            genomes=polished.genomes,
            costs=polished.costs,
            evaluations=[e + steps + 1 for e in tuned.evaluations],
        )
        state, _, _, _ = strategy.tell(key, state, brood, tuned, config)
        brood = strategy.ask(key, state, task, config)
