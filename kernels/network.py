"""One step of one compiled EANT2 network, and a whole sequence of steps.

The network's dense tensors (`Network`, built by `network` from a `Layout` and a parameter
vector) come from `eant2_jax.kernels.netbuild`; its products, which keep a non-finite value
away from the neurons that do not read it, from `eant2_jax.kernels.netdot`. Both are
re-exported here. One step on one example:

    base = w_in @ x + bias + w_rec @ h_prev          # inputs, biases, recurrent jumpers
    h    = act(base);  repeat `sweeps - 1` times:  h = act(base + w_ff @ h)
    y    = w_out @ h

``w_ff`` is strictly lower-triangular in slot order (a neuron only reads earlier slots), so
after ``d`` sweeps every neuron of depth <= d is exact and stays exact: ``sweeps`` must be at
least the network's depth (the longest chain of neurons). No Python loop over neurons or genes
and no per-node ``lax.cond``: a step is ``sweeps + 2`` small dense products (the first sweep
starts from h = 0, so it is ``act(base)``). Up to `SWEEPS_UNROLLED` sweeps are written out one
after another; more run as one loop, so that the program of a deep network does not grow with
its depth (docs/genome.md, Deep networks).

`step` is written for ONE network and ONE example; batch it with ``jax.vmap``. Over the
vmapped batch it runs plain products first and the non-finite rule only where a value needs
it (`step_inline` is the step with the rule in every product); on a GPU a batch of small
networks runs as one kernel (`eant2_jax.kernels.netfused`). This module imports nothing from
the rest of eant2_jax.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from . import activations, netfused

# The build's names, importable from here as before the split (documented in netbuild).
from .netbuild import Layout as Layout
from .netbuild import Network as Network
from .netbuild import buffer_size as buffer_size
from .netbuild import network as network
from .netdot import UNROLL_MAX as UNROLL_MAX
from .netdot import dot

__all__ = ["activation", "rollout", "step", "step_inline"]

# Up to this many sweeps a step writes them out one after another; above, it runs them as
# one loop, a program whose size does not depend on the depth (written out, a 1,000-deep
# chain compiled for minutes: issue 40). The buckets of the engine's runs and benchmarks so
# far have had at most 32 sweeps: their programs, so their results to the bit, are the ones
# written out as before (docs/genome.md, Deep networks).
SWEEPS_UNROLLED = 64


def activation(name: str) -> Callable[[jax.Array], jax.Array]:
    """The JAX activation function called ``name`` (built in or registered, see
    `eant2_jax.kernels.activations`); ValueError listing the known ones."""
    return activations.get(name).jax


def step(
    net: Network,
    x: jax.Array,
    h_prev: jax.Array,
    *,
    hidden: str = "tanh",
    output: str = "identity",
) -> tuple[jax.Array, jax.Array]:
    """One time step of one network on one example.

    Args:
      net: the network.
      x: ``[n_in]`` inputs at this step.
      h_prev: ``[H]`` neuron outputs at the previous step (zeros at the first).
      hidden: activation name of hidden neurons.
      output: activation name of root (output) neurons.

    Returns:
      ``(y [n_out], h [H])``: the outputs and every neuron's output at this step.
    """
    if net.reads is None:
        return step_inline(net, x, h_prev, hidden=hidden, output=output)
    leaves, treedef = jax.tree.flatten((net, x, h_prev))
    return _finite_first(treedef, hidden, output, _gpu_terms(net))(*leaves)


def _gpu_terms(net: Network) -> int:
    """How many product terms one step of ``net`` runs on one example (the non-finite rule's
    work is a few element-wise operations per term), or 0 where a GPU keeps the rule inline
    whatever the batch: networks of at most `UNROLL_MAX` neurons (`GPU_BRANCH_MIN`)."""
    h, n_in = net.w_in.shape[-2:]
    if h <= UNROLL_MAX:
        return 0
    return h * n_in + net.sweeps * h * h + net.w_out.shape[-2] * h


def step_inline(
    net: Network,
    x: jax.Array,
    h_prev: jax.Array,
    *,
    hidden: str = "tanh",
    output: str = "identity",
    check: bool = False,
    compact: bool = False,
    unroll: bool | None = None,
) -> tuple[jax.Array, ...]:
    """One step of one network on one example, with no branch over the batch: `step`'s
    values with the non-finite rule in every product (`netdot.dot`), or plain products for
    a network without ``reads``.

    Args:
      net: the network.
      x: ``[n_in]`` inputs at this step.
      h_prev: ``[H]`` neuron outputs at the previous step (zeros at the first).
      hidden: activation name of hidden neurons.
      output: activation name of root (output) neurons.
      check: also return whether every value that entered a product was finite. Without it
        the program is exactly the one before the check existed (GPU programs, and their
        float32 results, stay as they were measured).
      compact: write every product as a dot (`netdot.dot`'s compact form): the same values
        up to rounding, a fraction of the program to compile, slower on small networks.
      unroll: the sweeps written out one after another (True) or as one loop (False);
        None: written out up to `SWEEPS_UNROLLED` sweeps, a loop above.

    Returns:
      ``(y [n_out], h [H])``, and with ``check`` also ``finite``: ``(y, h, finite)``.
    """
    act_h, act_o = activation(hidden), activation(output)
    read_in, read_rec, read_ff, read_out = net.reads or (None,) * 4
    product = functools.partial(dot, compact=compact)
    base = product(net.w_in, read_in, x) + net.bias + product(net.w_rec, read_rec, h_prev)

    def settle(a):
        o = jnp.where(net.is_root, act_o(a), act_h(a))
        # Padding neurons stay at exactly 0 (sigmoid(0) would be 0.5).
        return jnp.where(net.neuron_mask, o, jnp.zeros_like(o))

    def sweep(_, h):
        return settle(base + product(net.w_ff, read_ff, h))

    def checked(i, carry):
        h, finite = carry
        return sweep(i, h), finite & jnp.all(jnp.isfinite(h))

    # The first sweep reads h = 0, so it is settle(base): after it the neurons of depth 1 are
    # exact, and after `sweeps` >= depth sweeps every neuron is, from any start (``dot``
    # keeps a value away from the rows that do not read it). Not written as a sweep over a
    # zero h: batched over networks and examples that zero is a large constant, which XLA's
    # constant folding would test element by element at compile time (docs/design.md, "No
    # test of a constant zero state").
    if unroll is None:
        unroll = net.sweeps <= SWEEPS_UNROLLED
    # The same holds for the test of h_prev, zeros at a first step: the barrier hides the
    # constant from XLA's folding; the values are the same.
    finite = None
    if check:
        h_seen = jax.lax.optimization_barrier(h_prev)
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(h_seen))
    if net.sweeps == 0:
        h = jnp.zeros_like(base)
    elif check:
        first = (settle(base), finite)
        h, finite = jax.lax.fori_loop(1, net.sweeps, checked, first, unroll=unroll)
    else:
        h = jax.lax.fori_loop(1, net.sweeps, sweep, settle(base), unroll=unroll)
    y = product(net.w_out, read_out, h)
    return (y, h) if finite is None else (y, h, finite & jnp.all(jnp.isfinite(h)))


# The non-finite rule is most of a step's work wherever the step is not launch-bound: per
# term of every product a finiteness test, two selects and a second product
# (`netdot.dot`, unrolled). So a step runs plain products over the whole batch first, and
# runs the rule (over the whole batch again) only when some value that entered a product was
# not finite: with finite values both give the same sums, term by term in the same order.
#
# On a GPU the branch's predicate is read by the host at every step, which a small batch
# does not pay back: there the branch is taken only for networks of more than `UNROLL_MAX`
# neurons and from `GPU_BRANCH_MIN` product terms per step over the whole batch; otherwise
# the rule stays inline (the same program as before the branch existed). The measurements:
# docs/design.md, "The non-finite rule after plain products".
@functools.cache
def _finite_first(treedef, hidden: str, output: str, terms: int):
    """``(y, h)`` of `step` from the leaves of ``(net, x, h_prev)``: plain products over the
    whole batch, the non-finite rule only where some batch value needs it (`_batched`).
    ``terms``: `_gpu_terms` of one example."""

    def one(form: str, *leaves):
        net, x, h_prev = jax.tree.unflatten(treedef, leaves)
        if form == "plain":
            plain = net.replace(reads=None)
            return step_inline(plain, x, h_prev, hidden=hidden, output=output, check=True)
        # "rare" is the branch that runs when some value was not finite. On a CPU it is
        # written with dots (`netdot.dot`'s compact form), compiled in a fraction of the unrolled
        # rule's time (every engine program compiles it; it almost never runs). On a GPU it
        # stays unrolled: every new dot shape is autotuned there (docs/design.md).
        compact = form == "rare" and jax.default_backend() == "cpu"
        return step_inline(net, x, h_prev, hidden=hidden, output=output, compact=compact)

    def fused(levels, rule, *leaves):
        return _fused_batch(treedef, levels, leaves, rule, hidden, output)

    @jax.custom_jvp
    def first(*leaves):
        return _batched(one, (), terms, fused)(*leaves)

    @first.defjvp
    def first_jvp(primals, tangents):
        # Differentiation takes the rule's own path (no branch, nothing custom inside).
        return jax.jvp(functools.partial(one, "rule"), primals, tangents)

    return first


@functools.cache
def _batched(
    one: Callable,
    levels: tuple[tuple[int, tuple[bool, ...]], ...],
    terms: int,
    fused: Callable | None = None,
):
    """``one`` over a batch whose vmapped axes are ``levels`` (outermost first; per level,
    its size and which arguments carry that axis), branching once for the whole batch. Each
    enclosing vmap adds its level in front (`jax.custom_batching.custom_vmap`), so the call
    outside all of them sees every axis; arguments that a level does not batch (a network's
    weights, shared by its examples) stay unbroadcast. ``fused(levels, rule, *leaves)``:
    where a GPU keeps the rule inline, the whole batch as one kernel (`_fused_batch`), or
    None where it does not apply."""

    def over_batch(form):
        f = functools.partial(one, form)
        for _, batched in reversed(levels):
            f = jax.vmap(f, in_axes=tuple(0 if b else None for b in batched))
        return f

    @jax.custom_batching.custom_vmap
    def run(*leaves):
        on_cpu = jax.default_backend() == "cpu"
        examples = math.prod(size for size, _ in levels)
        if not on_cpu and (terms == 0 or examples * terms < GPU_BRANCH_MIN):
            rule = over_batch("rule")
            out = None if fused is None else fused(levels, rule, *leaves)
            return rule(*leaves) if out is None else out
        y, h, finite = over_batch("plain")(*leaves)

        def rare(leaves):
            return over_batch("rare")(*leaves)

        def keep(_):
            return y, h

        # The passthrough branch first: XLA elides its copies only there (openxla/xla#46314;
        # `eant2_jax.exploitation._cond_rare`). XLA:CPU keeps lax.cond's indexed form (the
        # false branch first), XLA:GPU makes its predicated form (the true branch first).
        if on_cpu:
            return jax.lax.cond(~jnp.all(finite), rare, keep, leaves)
        return jax.lax.cond(jnp.all(finite), keep, rare, leaves)

    @run.def_vmap
    def run_vmap(axis_size, in_batched, *leaves):
        level = (axis_size, tuple(in_batched))
        return _batched(one, (level, *levels), terms, fused)(*leaves), (True, True)

    return run


def _fused_batch(treedef, levels, leaves, rule: Callable, hidden: str, output: str):
    """`step`'s ``(y, h)`` over the whole vmapped batch as one CUDA kernel
    (`netfused.step_batch`), from the leaves of ``(net, x, h_prev)`` whose vmapped axes are
    ``levels`` (`_batched`); ``rule(*leaves)`` (the rule inline, as XLA fusions) where the
    program is lowered for another platform; None where that kernel does not apply.

    It applies where the levels that batch the network come first (the structures, their
    candidates) and the others batch only its examples (a task's starts, episodes), to
    float32 networks of `FUSED_NEURONS` neuron slots with `netfused.ACTIVATIONS`."""
    if not FUSED or not {hidden, output} <= netfused.ACTIVATIONS:
        return None
    net, x, h_prev = jax.tree.unflatten(treedef, leaves)
    if not FUSED_NEURONS[0] <= net.bias.shape[-1] <= FUSED_NEURONS[1]:
        return None
    if any(a.dtype != jnp.float32 for a in (net.w_in, x, h_prev)):
        return None
    k = len(leaves) - 2  # the network's leaves, then x and h_prev
    on_net = [any(batched[:k]) for _, batched in levels]
    outer = next((i for i, b in enumerate(on_net) if not b), len(levels))
    if any(on_net[outer:]):
        return None
    sizes = [size for size, _ in levels]
    n_nets, n_examples = math.prod(sizes[:outer]), math.prod(sizes[outer:])
    if n_nets * n_examples == 0:
        return None

    def spread(a, i, span):
        # Leaf i with one axis for each level in `span` (size 1 where it is not batched).
        for at, level in enumerate(span):
            if not levels[level][1][i]:
                a = jnp.expand_dims(a, at)
        return a

    def per_net(a, i):
        # [n_nets, *one network's shape]
        own = a.shape[sum(batched[i] for _, batched in levels) :]
        return jnp.broadcast_to(spread(a, i, range(outer)), (*sizes[:outer], *own)).reshape(
            n_nets, *own
        )

    def per_example(a, i):
        # [n_nets or 1, n_examples, features]
        shared = not any(levels[level][1][i] for level in range(outer))
        span = range(outer, len(levels)) if shared else range(len(levels))
        a = spread(a, i, span)
        shape = [sizes[level] for level in span]
        a = jnp.broadcast_to(a, (*shape, a.shape[-1]))
        return a.reshape(1 if shared else n_nets, n_examples, a.shape[-1])

    def kernel(*leaves):
        nets = [per_net(a, i) for i, a in enumerate(leaves[:k])]
        net = jax.tree.unflatten(treedef, [*nets, *leaves[k:]])[0]
        y, h = netfused.step_batch(
            net.w_in, net.bias, net.w_ff, net.w_rec, net.w_out, net.reads, net.is_root,
            net.neuron_mask, per_example(leaves[k], k), per_example(leaves[k + 1], k + 1),
            sweeps=net.sweeps, hidden=hidden, output=output,
        )  # fmt: skip
        return y.reshape(*sizes, y.shape[-1]), h.reshape(*sizes, h.shape[-1])

    # Chosen when the program is lowered: a CPU program of a GPU machine (or a program
    # exported for several platforms) keeps the rule.
    return jax.lax.platform_dependent(*leaves, cuda=kernel, default=rule)


# Off the CPU the step branches (`_batched`) only for networks of more than `UNROLL_MAX`
# neurons (their products over neurons are dots) and from this many product terms per step
# over the batch (`_gpu_terms` times the examples): unrolled products keep the rule inline,
# and a dot-product network gains from the branch once the rule costs more than the host's
# read of its predicate (docs/design.md, "When a GPU branches").
GPU_BRANCH_MIN = 1 << 26


# On a GPU the rule's inline path runs as one kernel (`netfused`) where it applies: for
# buckets of 8 to `UNROLL_MAX` neuron slots. Below 8 slots the kernel gains nothing and its
# compile only adds to every new engine program's (docs/design.md, "One fused kernel").
FUSED = True
FUSED_NEURONS = (8, UNROLL_MAX)


def rollout(
    net: Network,
    xs: jax.Array,
    *,
    hidden: str = "tanh",
    output: str = "identity",
    h0: jax.Array | None = None,
) -> jax.Array:
    """Run one network over a sequence of one stream, carrying the recurrent state.

    Args:
      net: the network.
      xs: ``[T, n_in]`` inputs.
      hidden: activation name of hidden neurons.
      output: activation name of root (output) neurons.
      h0: ``[H]`` initial neuron outputs (default zeros: "0.0 at the first step").

    Returns:
      ``[T, n_out]`` outputs.
    """
    if h0 is None:
        h0 = jnp.zeros(net.bias.shape, xs.dtype)

    def body(h, x):
        y, h = step(net, x, h, hidden=hidden, output=output)
        return h, y

    _, ys = jax.lax.scan(body, h0, xs)
    return ys
