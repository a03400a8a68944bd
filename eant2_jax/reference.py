"""A plain NumPy interpreter of the linear genome: clear, slow, obviously right.

It walks the genes from last to first with a stack, exactly as the semantics in
`eant2_jax.genome` say, once per time step. Every fast path of the package is tested
against it. Only the M independent streams are vectorised (each stack entry is an ``[M]``
array); the walk itself is the textbook one.
"""

from __future__ import annotations

import numpy as np

from .genome import GeneKind, Genome
from .kernels import activations

__all__ = ["interpret"]


def interpret(
    genome: Genome,
    inputs: np.ndarray,
    *,
    hidden: str = "tanh",
    output: str = "identity",
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Run ``genome`` over a sequence, in float64.

    Args:
      genome: the network.
      inputs: ``[T, M, n_in]`` with ``n_in >= genome.n_inputs``; M independent streams, each
        with its own recurrent state.
      hidden: activation name of hidden neurons.
      output: activation name of root (output) neurons.
      weights: optional ``[n_params]`` weight vector replacing the genome's own.

    Returns:
      ``[T, M, n_out]`` network outputs, output 0 the leftmost root.
    """
    x = np.asarray(inputs, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"inputs must have shape [T, M, n_in], got {x.shape}")
    if x.shape[2] < genome.n_inputs:
        raise ValueError(f"genome reads {genome.n_inputs} inputs, data has {x.shape[2]}")
    w = genome.weights if weights is None else np.asarray(weights, dtype=np.float64)
    # Each activation's NumPy reference sits beside its JAX form in one table.
    act_hidden, act_out = activations.get(hidden).numpy, activations.get(output).numpy
    roots = set(genome.roots)
    T, M, _ = x.shape
    prev = {nid: np.zeros(M) for nid in genome.neuron_ids}  # outputs at step t-1
    ys = np.zeros((T, M, genome.n_outputs))
    for t in range(T):
        current: dict[int, np.ndarray] = {}
        stack: list[np.ndarray] = []
        for i in reversed(range(len(genome))):
            gene = genome[i]
            if gene.kind == GeneKind.INPUT:
                stack.append(w[i] * x[t, :, gene.ref])
            elif gene.kind == GeneKind.BIAS:
                stack.append(w[i] * np.ones(M))
            elif gene.kind == GeneKind.FORWARD:
                stack.append(w[i] * current[gene.ref])
            elif gene.kind == GeneKind.RECURRENT:
                stack.append(w[i] * prev[gene.ref])
            else:  # neuron
                a = np.zeros(M)
                for _ in range(gene.arity):
                    a = a + stack.pop()
                o = (act_out if i in roots else act_hidden)(a)
                current[gene.ref] = o
                stack.append(w[i] * o)
        # The stack top is the leftmost root: output 0.
        ys[t] = np.stack(stack[::-1], axis=-1)
        prev = current
    return ys
