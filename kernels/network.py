"""Dense evaluation of one compiled EANT2 network: build, one step, a whole sequence.

A compiled network has ``H`` neuron slots in topological order (every neuron after the
neurons it reads at the current step) and ``P`` gene slots. Its parameters live in one flat
buffer laid out as::

    [ w_in (H * n_in) | bias (H) | w_ff (H * H) | w_rec (H * H) | w_out (n_out * H) | trash (1) ]

and every gene adds its weight into one entry of that buffer (``Layout.slot``); padding genes
point at the trash entry. Several genes may share an entry (a neuron reading the same input
twice): their weights add, exactly as the stack semantics add them.

One step of the network on one example:

    base = w_in @ x + bias + w_rec @ h_prev          # inputs, biases, recurrent jumpers
    h    = act(base);  repeat `sweeps - 1` times:  h = act(base + w_ff @ h)
    y    = w_out @ h

Non-finite inputs follow the stack semantics exactly: a NaN or infinite value reaches only
the neurons that read it (through a gene, even one of weight 0), never through the zeros of
the dense matrices (see ``_dot``), as in `eant2_jax.reference.interpret`.

``w_ff`` is strictly lower-triangular in slot order (a neuron only reads earlier slots), so
after ``d`` sweeps every neuron of depth <= d is exact and stays exact: ``sweeps`` must be at
least the network's depth (the longest chain of neurons). No Python loop over neurons or genes
and no per-node ``lax.cond``: a step is ``sweeps + 2`` small dense products (the first sweep
starts from h = 0, so it is ``act(base)``); short ones are written as unrolled element-wise
sums (``_dot``), which XLA fuses with the activations.

Everything here is written for ONE network and ONE example; batch with ``jax.vmap``. This
module imports nothing from the rest of eant2_jax.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import struct

from . import activations, netfused

__all__ = [
    "Layout",
    "Network",
    "activation",
    "buffer_size",
    "network",
    "rollout",
    "step",
]

# Exact float32 products: on GPUs the default precision of a float32 dot may use TF32
# (~1e-3 relative error), which would break equality with the reference interpreter. These
# products are tiny, so the cost is nil.
_PRECISION = jax.lax.Precision.HIGHEST


def activation(name: str) -> Callable[[jax.Array], jax.Array]:
    """The JAX activation function called ``name`` (built in or registered, see
    `eant2_jax.kernels.activations`); ValueError listing the known ones."""
    return activations.get(name).jax


def buffer_size(n_neurons: int, n_inputs: int, n_outputs: int) -> int:
    """Length of the flat parameter buffer, trash entry included."""
    h = n_neurons
    return h * n_inputs + h + 2 * h * h + n_outputs * h + 1


@struct.dataclass
class Layout:
    """The structure of one compiled network (no weights).

    Attributes:
      slot: ``int32[P]`` entry of the flat buffer each gene adds its weight to.
      gene_mask: ``bool[P]`` true for real genes, false for padding.
      is_root: ``bool[H]`` neuron slots that are network outputs (use the output activation).
      neuron_mask: ``bool[H]`` true for real neurons.
      depth: ``int32[]`` the network's depth (informative; ``sweeps`` is what runs).
      n_inputs, n_outputs, sweeps: static sizes shared by every network of a batch.
    """

    slot: jax.Array
    gene_mask: jax.Array
    is_root: jax.Array
    neuron_mask: jax.Array
    depth: jax.Array
    n_inputs: int = struct.field(pytree_node=False)
    n_outputs: int = struct.field(pytree_node=False)
    sweeps: int = struct.field(pytree_node=False)


@struct.dataclass
class Network:
    """Dense tensors of one network, ready to run.

    Attributes:
      w_in: ``[H, n_in]`` weights of network inputs into neurons.
      bias: ``[H]`` bias of each neuron (sum of its bias genes).
      w_ff: ``[H, H]`` current-step weights, ``w_ff[i, j]``: neuron j into neuron i (j < i).
      w_rec: ``[H, H]`` previous-step weights (recurrent jumpers).
      w_out: ``[n_out, H]`` output selection: root r's own weight at its neuron's slot.
      is_root, neuron_mask: ``bool[H]`` as in `Layout`.
      reads: for ``w_in``, ``w_rec``, ``w_ff`` and ``w_out``: ``(mask, weights)``, the entries
        some gene sets (a connection; its weight may still be 0) and the weights a
        non-finite source is multiplied by (NaN where the genes' own products give NaN).
        None (a network built by hand): plain dense products, where a non-finite input
        reaches every neuron.
      sweeps: static number of dense sweeps per step (>= depth).
    """

    w_in: jax.Array
    bias: jax.Array
    w_ff: jax.Array
    w_rec: jax.Array
    w_out: jax.Array
    is_root: jax.Array
    neuron_mask: jax.Array
    sweeps: int = struct.field(pytree_node=False)
    reads: tuple[tuple[jax.Array, jax.Array], ...] | None = None


def network(layout: Layout, params: jax.Array) -> Network:
    """Scatter a parameter vector into the dense tensors of one network.

    Args:
      layout: the network's structure.
      params: ``[P]`` one weight per gene slot, in gene order (padding entries are ignored).

    Returns:
      The `Network`. Differentiable in ``params``; jit/vmap friendly.
    """
    h = layout.is_root.shape[-1]
    n_in, n_out = layout.n_inputs, layout.n_outputs
    # For non-finite sources: the stack semantics add w_i * v gene by gene, so an entry set
    # by a gene of weight 0, or by genes of both signs, gives NaN for v = +-inf where the
    # summed weight would not; NaN marks those entries in the weights used for such values.
    flat, used, poison = _gather_genes(layout, params, buffer_size(h, n_in, n_out))
    sizes = (h * n_in, h, h * h, h * h, n_out * h)
    offsets = [0]
    for s in sizes:
        offsets.append(offsets[-1] + s)
    part = [flat[offsets[i] : offsets[i + 1]] for i in range(len(sizes))]
    w_nf = jnp.where(used, jnp.where(poison, jnp.nan, flat), 0.0).astype(flat.dtype)
    shapes = ((h, n_in), (h,), (h, h), (h, h), (n_out, h))

    def pair(i):
        a, b = offsets[i], offsets[i + 1]
        return used[a:b].reshape(shapes[i]), w_nf[a:b].reshape(shapes[i])

    return Network(
        reads=(pair(0), pair(3), pair(2), pair(4)),
        w_in=part[0].reshape(h, n_in),
        bias=part[1],
        w_ff=part[2].reshape(h, h),
        w_rec=part[3].reshape(h, h),
        w_out=part[4].reshape(n_out, h),
        is_root=layout.is_root,
        neuron_mask=layout.neuron_mask,
        sweeps=layout.sweeps,
    )


def _gather_genes(
    layout: Layout, params: jax.Array, size: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The flat buffer and two flags per entry: ``(flat, used, poison)``, each ``[size]``.

    ``flat``: each entry the sum of the weights of the genes that point at it. ``used``:
    some gene points at it. ``poison``: one of those genes has weight 0, or they have both
    signs (`network`'s non-finite rule).

    Not a scatter-add: a float scatter-add with repeated indices is non-deterministic on GPUs
    (atomic adds in any order), and XLA's deterministic mode (``--xla_gpu_deterministic_ops``)
    turns it into a sort. Here the genes that share an entry are summed first, onto the first
    of them (a masked ``[P, P]`` sum over a matrix that depends on the layout only, so vmapped
    over a structure's candidates it is built once), and a scatter with unique indices
    (deterministic by construction, left alone by that mode) writes one value per entry. The
    flags are reduced over the same groups and written by the same scatter, as columns next
    to the sums: one scatter per network instead of four (the flags were scatter-adds of
    their own, each a GPU kernel with its buffer's initialisation and copy on every engine
    iteration). Padding genes (all pointing at the trash entry) write nothing, so the trash
    entry stays 0.
    """
    values = jnp.where(layout.gene_mask, params, jnp.zeros_like(params))
    p = values.shape[-1]
    genes = jnp.arange(p)
    same = (layout.slot[:, None] == layout.slot[None, :]) & layout.gene_mask[None, :]
    first = layout.gene_mask & ~jnp.any(same & (genes[None, :] < genes[:, None]), axis=1)
    summed = jnp.sum(jnp.where(same, values[None, :], jnp.zeros_like(values)[None, :]), axis=1)

    def any_in_group(cond):
        return jnp.any(same & cond[None, :], axis=1)

    poison = any_in_group(params == 0) | (any_in_group(params > 0) & any_in_group(params < 0))
    columns = jnp.stack([summed, first.astype(values.dtype), poison.astype(values.dtype)], -1)
    # Every gene gets its own index: the first of each entry its entry, the others a distinct
    # index past the end, which mode="drop" discards, so the promise of unique indices holds.
    target = jnp.where(first, layout.slot, size + genes)
    out = (
        jnp.zeros((size, 3), values.dtype)
        .at[target]
        .set(columns, mode="drop", unique_indices=True, indices_are_sorted=False)
    )
    return out[:, 0], out[:, 1] > 0, out[:, 2] > 0


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
        return _step(net, x, h_prev, hidden, output)
    leaves, treedef = jax.tree.flatten((net, x, h_prev))
    return _finite_first(treedef, hidden, output, _gpu_terms(net))(*leaves)


def _gpu_terms(net: Network) -> int:
    """How many product terms one step of ``net`` runs on one example (the non-finite rule's
    work is a few element-wise operations per term), or 0 where a GPU keeps the rule inline
    whatever the batch: networks of at most `_UNROLL_MAX` neurons (`_GPU_BRANCH_MIN`)."""
    h, n_in = net.w_in.shape[-2:]
    if h <= _UNROLL_MAX:
        return 0
    return h * n_in + net.sweeps * h * h + net.w_out.shape[-2] * h


def _step(
    net: Network,
    x: jax.Array,
    h_prev: jax.Array,
    hidden: str,
    output: str,
    *,
    check: bool = False,
    compact: bool = False,
):
    """`step`'s ``(y, h)``; with ``check``, also whether every value that entered a product
    was finite (``(y, h, finite)``). Without it the program is exactly the one before the
    check existed (GPU programs, and their float32 results, stay as they were measured).
    ``compact`` writes every product as a dot (`_dot`): the same values up to rounding, a
    fraction of the program to compile, slower to run on small networks."""
    act_h, act_o = activation(hidden), activation(output)
    read_in, read_rec, read_ff, read_out = net.reads or (None,) * 4
    dot = functools.partial(_dot, compact=compact)
    base = dot(net.w_in, read_in, x) + net.bias + dot(net.w_rec, read_rec, h_prev)

    def settle(a):
        o = jnp.where(net.is_root, act_o(a), act_h(a))
        # Padding neurons stay at exactly 0 (sigmoid(0) would be 0.5).
        return jnp.where(net.neuron_mask, o, jnp.zeros_like(o))

    def sweep(_, h):
        return settle(base + dot(net.w_ff, read_ff, h))

    def checked(i, carry):
        h, finite = carry
        return sweep(i, h), finite & jnp.all(jnp.isfinite(h))

    # The first sweep reads h = 0, so it is settle(base): after it the neurons of depth 1 are
    # exact, and after `sweeps` >= depth sweeps every neuron is, from any start (``_dot``
    # keeps a value away from the rows that do not read it). Not written as a sweep over a
    # zero h: batched over networks and examples that zero is a large constant, and XLA's
    # constant folding spent 21.6 s of a 25.1 s compile (200 servo structures, CPU) on the
    # finiteness test of ``_dot`` over it.
    finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(h_prev)) if check else None
    if net.sweeps == 0:
        h = jnp.zeros_like(base)
    elif check:
        h, finite = jax.lax.fori_loop(1, net.sweeps, checked, (settle(base), finite), unroll=True)
    else:
        h = jax.lax.fori_loop(1, net.sweeps, sweep, settle(base), unroll=True)
    y = dot(net.w_out, read_out, h)
    return (y, h) if finite is None else (y, h, finite & jnp.all(jnp.isfinite(h)))


# The non-finite rule is most of a step's work wherever the step is not launch-bound: per
# term of every product a finiteness test, two selects and a second product
# (``_dot_unrolled``). On XLA:CPU, which runs it element by element, the XOR engine
# iteration (24 structures, 4 neurons, 4 sweeps; 2-core VM, in-process A/B of the compiled
# chunk) took 0.80 ms with the rule inline, 0.56 ms with plain products alone and 0.59-0.64
# ms with this branch. So a step runs plain products over the whole batch first, and runs
# the rule (over the whole batch again) only when some value that entered a product was not
# finite: with finite values both give the same sums, term by term in the same order.
#
# On a GPU the branch's predicate is read by the host at every step, which a small batch
# does not pay back: there the branch is taken only for networks of more than `_UNROLL_MAX`
# neurons and from `_GPU_BRANCH_MIN` product terms per step over the whole batch; otherwise
# the rule stays inline (the same program as before the branch existed). See
# `_GPU_BRANCH_MIN` for the measurements.
@functools.cache
def _finite_first(treedef, hidden: str, output: str, terms: int):
    """``(y, h)`` of `step` from the leaves of ``(net, x, h_prev)``: plain products over the
    whole batch, the non-finite rule only where some batch value needs it (`_batched`).
    ``terms``: `_gpu_terms` of one example."""

    def one(form: str, *leaves):
        net, x, h_prev = jax.tree.unflatten(treedef, leaves)
        if form == "plain":
            return _step(net.replace(reads=None), x, h_prev, hidden, output, check=True)
        # "rare" is the branch that runs when some value was not finite. On a CPU it is
        # written with dots (`_dot`'s compact form), compiled in a fraction of the unrolled
        # rule's time (every engine program compiles it; it almost never runs). On a GPU
        # every new dot shape is autotuned: the first call of a 16-neuron servo chunk took
        # 20.3 s with the compact form against 10.1 s unrolled (H100, `python -m bench
        # generation --parts scaling`).
        compact = form == "rare" and jax.default_backend() == "cpu"
        return _step(net, x, h_prev, hidden, output, compact=compact)

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
        if not on_cpu and (terms == 0 or examples * terms < _GPU_BRANCH_MIN):
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
    float32 networks of `_FUSED_NEURONS` neuron slots with `netfused.ACTIVATIONS`."""
    if not _FUSED or not {hidden, output} <= netfused.ACTIVATIONS:
        return None
    net, x, h_prev = jax.tree.unflatten(treedef, leaves)
    if not _FUSED_NEURONS[0] <= net.bias.shape[-1] <= _FUSED_NEURONS[1]:
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


# Off the CPU the step branches (`_batched`) only for networks of more than `_UNROLL_MAX`
# neurons (their products over neurons are dots) and from this many product terms per step
# over the batch (`_gpu_terms` times the examples). An H100, 20 random servo structures,
# 1023 starts, the covariance pruner, ms per engine iteration, the rule inline against this
# branch (2026-11-24, scratch A/B; the chunk's float32 results were the same bits):
#
#   genes  bucket (P, H, sweeps)  terms per step  inline  branch
#   40     (48, 6, 4)             6.8e7           0.72    0.76
#   50     (64, 8, 6)             1.5e8           0.67    2.10
#   56     (64, 12, 6)            3.2e8           1.27    1.06
#   80     (96, 16, 8)            6.9e8           1.49    1.11
#
# With unrolled products (up to 12 neurons) whether XLA fuses the plain sweeps into one
# another, recomputing them, is its heuristics' call: 8 neurons ran three times slower, 12
# neurons faster, while the rule's finiteness tests keep each sweep apart; so unrolled
# products keep the rule inline. A 16-neuron network gains from the branch once the rule
# costs more than the host's read of its predicate (one per step): ~0.37 ms of rule against
# ~0.02 ms of read at 6.9e8 terms; 2^26 keeps a margin.
_GPU_BRANCH_MIN = 1 << 26


# Products whose contraction is at most this long (inputs or neurons read) are written as an
# unrolled sum of element-wise products instead of a dot. Batched over networks and
# examples, a dot of such tiny matrices is a batched GEMM of its own that XLA does not fuse
# with what follows: on a 2-core CPU one Eigen call per network, and the XOR cost of 288
# networks (6 neurons) took 2.2 ms as dots against 0.95 ms unrolled. On an H100 (`python -m
# bench generation --parts scaling --scaling-pruner covariance`, 20 servo structures,
# 2026-11-24) an engine iteration at 40 genes (6 neurons, 10 inputs) took 0.95-0.96 ms
# with this bound against 1.03-1.06 ms with dots; unrolling 16 neurons (80 genes) compiled
# the program in 14 s instead of 30 s but ran it 27% slower (3.05 against 2.40 ms), so 16
# stays a dot.
_UNROLL_MAX = 12


# On a GPU the rule's inline path runs as one kernel (`netfused`) where it applies: for
# buckets of 8 to `_UNROLL_MAX` neuron slots. An H100 (2026-11-25): generation 6's servo
# batch (24 structures of bucket (64, 8, 4), scratch A/B of the engine's chunk) took
# 0.51-0.54 ms per engine iteration with the kernel against 0.74 ms inline; 20 random servo
# structures of 40 genes (bucket (48, 6, 4), `python -m bench generation --parts scaling`)
# 0.518 against 0.515 ms: no gain at 6 slots. There the kernel's compile would only join
# every new engine program's, `eant2 run servo`'s first buckets (4 and 6 slots) included:
# with the kernel at those sizes its cold start took 12.3 s against 11.4 s (medians of 3,
# rounds overlapping); without, 13.8 s against 13.7 s (5 rounds, a slower host).
_FUSED = True
_FUSED_NEURONS = (8, _UNROLL_MAX)


def _dot(
    w: jax.Array,
    reads: tuple[jax.Array, jax.Array] | None,
    v: jax.Array,
    *,
    compact: bool = False,
) -> jax.Array:
    """``w @ v`` as the stack semantics compute it: a non-finite ``v[j]`` reaches exactly the
    rows that read it (a dense product would make ``0 * nan`` of every other row NaN). With
    a finite ``v`` it is the sum of ``w[:, j] * v[j]`` (in the order of ``j`` for short
    contractions, `_UNROLL_MAX`; as XLA's dot orders it otherwise). ``compact``: always a
    dot, and the non-finite terms as one pass without a branch of their own."""
    k = v.shape[-1]
    if 0 < k <= _UNROLL_MAX and not compact:
        return _dot_unrolled(w, reads, v)
    if reads is None:
        return jnp.dot(w, v, precision=_PRECISION)
    read, w_nf = reads
    finite = jnp.isfinite(v)
    y = jnp.dot(w, jnp.where(finite, v, jnp.zeros_like(v)), precision=_PRECISION)
    terms = _nonfinite_terms_plain if compact else _nonfinite_terms
    return jnp.where(jnp.all(finite), y, y + terms(read, w_nf, v))


def _nonfinite_terms_plain(read: jax.Array, w_nf: jax.Array, v: jax.Array) -> jax.Array:
    """The terms of the non-finite entries of ``v`` (any leading batch dims): ``w_nf[i, j] *
    v[j]`` summed over the non-finite ``v[j]`` that row ``i`` reads; 0 where there is none.

    Both factors are masked, not only the product: a NaN in an unselected branch of a
    where would still make the gradient NaN.
    """
    finite = jnp.isfinite(v)
    take = read & ~finite[..., None, :]
    w_take = jnp.where(take, w_nf, jnp.zeros_like(w_nf))
    v_take = jnp.where(finite, jnp.zeros_like(v), v)
    return jnp.sum(jnp.where(take, w_take * v_take[..., None, :], 0), axis=-1)


# A long product's non-finite terms are a pass over [rows, k] per example (the finite part
# is a dot). Batched over 200 servo structures of 24 neurons (a lock-step `eant2 reproduce`
# batch) that pass took 24 of an engine iteration's 38 ms on an H100 (2026-11-24). Values
# are almost always finite, so over a batch this large the pass runs only when some value of
# the whole batch is not: one branch (on a GPU, one read of its predicate by the host)
# instead; the iteration took 20 ms, and 1.9 ms against 2.3 ms for 20 structures of 16
# neurons. Smaller batches, where the read would cost more than the pass, always run it.
_BRANCH_MIN = 1 << 24


@jax.custom_jvp
def _nonfinite_terms(read: jax.Array, w_nf: jax.Array, v: jax.Array) -> jax.Array:
    """`_nonfinite_terms_plain`, skipped over a whole batch of at least `_BRANCH_MIN`
    entries when every value is finite. The batch is the vmapped one: `_batch_level`
    carries each vmap's axis out to the call outside all of them, which branches once."""
    return _batch_level(())(read, w_nf, v)


@_nonfinite_terms.defjvp
def _nonfinite_terms_jvp(primals, tangents):
    # Differentiation takes the plain pass (no branch, nothing custom to differentiate).
    return jax.jvp(_nonfinite_terms_plain, primals, tangents)


@functools.cache
def _batch_level(shared: tuple[bool, ...]):
    """The branching pass for arguments whose leading axes are vmapped ones: ``v`` has all
    of them, ``read`` and ``w_nf`` (one network's) only those where ``shared`` is False.
    A network's arrays are not broadcast over the examples: a branch's operands are
    materialised, and broadcast they were 10 GB for 200 servo structures."""

    @jax.custom_batching.custom_vmap
    def level(read, w_nf, v):
        index = tuple(None if s else slice(None) for s in shared)  # size 1 where shared
        read, w_nf = read[index], w_nf[index]
        if v.size * read.shape[-2] < _BRANCH_MIN:  # the pass's entries
            return _nonfinite_terms_plain(read, w_nf, v)

        def none(r, w, x):
            return jnp.zeros(jnp.broadcast_shapes(r.shape[:-1], x.shape[:-1] + (1,)), w.dtype)

        def some(r, w, x):
            # The barriers keep XLA from turning this small branch into a select, which
            # would run the pass every time (measured: no gain without them).
            r, w, x = jax.lax.optimization_barrier((r, w, x))
            return jax.lax.optimization_barrier(_nonfinite_terms_plain(r, w, x))

        return jax.lax.cond(jnp.all(jnp.isfinite(v)), none, some, read, w_nf, v)

    @level.def_vmap
    def level_vmap(axis_size, in_batched, read, w_nf, v):
        # An enclosing vmap applies this rule once more with its axis in front, so the call
        # outside all of them sees the whole batch.
        b_read, b_w, b_v = in_batched
        if not b_v:
            v = jnp.broadcast_to(v, (axis_size, *v.shape))
        if b_read != b_w:  # one network's arrays: batched together, or not at all
            read, w_nf = (
                a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
                for a, b in ((read, b_read), (w_nf, b_w))
            )
        return _batch_level((not (b_read or b_w), *shared))(read, w_nf, v), True

    return level


def _dot_unrolled(
    w: jax.Array, reads: tuple[jax.Array, jax.Array] | None, v: jax.Array
) -> jax.Array:
    """`_dot` as ``k`` element-wise terms (one fusion with what follows). The term of a
    non-finite ``v[j]`` is ``w_nf[:, j] * v[j]`` on the rows that read it and 0 elsewhere;
    the product and its factors are masked (as in `_dot`) so that gradients stay finite."""
    if reads is None:
        y = w[:, 0] * v[0]
        for j in range(1, v.shape[-1]):
            y = y + w[:, j] * v[j]
        return y
    read, w_nf = reads
    finite = jnp.isfinite(v)
    v_fin = jnp.where(finite, v, jnp.zeros_like(v))
    v_nf = jnp.where(finite, jnp.zeros_like(v), v)
    y = None
    for j in range(v.shape[-1]):
        take = read[:, j] & ~finite[j]
        w_take = jnp.where(take, w_nf[:, j], jnp.zeros_like(w_nf[:, j]))
        term = w[:, j] * v_fin[j] + jnp.where(take, w_take * v_nf[j], 0)
        y = term if y is None else y + term
    return y


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
