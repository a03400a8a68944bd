"""A genome file as a network ready to run: `load` and `LoadedNetwork`.

The network is evaluated by the same kernels and compiled by the same route as the run
that wrote the file (docs/genome.md, "Loading a network"). Host side, except the call
itself. The file is read by `eant2_jax.genomefile` (bounded, regular files only); its
exports come from `eant2_jax.export`.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from . import export
from .compiler import networks
from .genome import Genome
from .genomefile import GenomeFile, GenomeFileError
from .kernels import activations
from .kernels import network as kn

__all__ = ["LoadedNetwork", "load"]


@functools.partial(jax.jit, static_argnames=("hidden", "output"))
def _rollout(net: kn.Network, xs: jax.Array, *, hidden: str, output: str) -> jax.Array:
    """``[T, M, n_in] -> [T, M, n_out]``: one network over M streams (a task's predict)."""
    run = functools.partial(kn.rollout, net, hidden=hidden, output=output)
    return jax.vmap(run, in_axes=1, out_axes=1)(xs)


@functools.partial(jax.jit, static_argnames=("hidden", "output"))
def _step(net: kn.Network, x: jax.Array, h: jax.Array, *, hidden: str, output: str):
    """``([M, n_in], [M, H]) -> ([M, n_out], [M, H])``: one step of M streams."""
    one = functools.partial(kn.step, net, hidden=hidden, output=output)
    return jax.vmap(one)(x, h)


class LoadedNetwork:
    """A network ready to run: a genome file's genome, activations and input width.

    Calls run through the same kernels (``eant2_jax.kernels.network``) and the same
    compilation route (``eant2_jax.compiler.networks``) as a run's tasks, in float32.

    * ``net(x)`` with ``x`` of shape ``[n_in]`` is one step from the zero state (``[n_out]``);
      ``[M, n_in]``: M independent examples, one step each (``[M, n_out]``);
      ``[T, M, n_in]``: M streams of T steps, the recurrent state carried along each stream
      and zero before the first step, as `eant2_jax.evaluate` (``[T, M, n_out]``).
    * ``net.step(x, state)`` for closed-loop use: ``x`` ``[n_in]`` or ``[M, n_in]``, ``state``
      from `initial_state`; returns ``(y, state)``.
    """

    def __init__(self, spec: GenomeFile):
        if not spec.has_header:
            raise GenomeFileError("LoadedNetwork needs the activations (a file with a header)")
        activations.get(spec.hidden), activations.get(spec.output)  # clear error if unknown
        self.spec = spec
        self.n_inputs = spec.n_inputs if spec.n_inputs is not None else spec.genome.n_inputs
        self.n_outputs = spec.genome.n_outputs
        nets = networks([spec.genome], self.n_inputs)
        self._net = jax.tree.map(lambda a: a[0], nets)

    @property
    def genome(self) -> Genome:
        return self.spec.genome

    def __repr__(self) -> str:
        s = self.spec
        return (
            f"LoadedNetwork({s.genome.n_params} parameters, {self.n_inputs} inputs, "
            f"{self.n_outputs} outputs, hidden={s.hidden!r}, output={s.output!r}, "
            f"task={s.task!r})"
        )

    def _inputs(self, x: ArrayLike, ndims: tuple[int, ...]) -> np.ndarray:
        a = np.asarray(x)
        if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
            raise TypeError(f"inputs must be real numbers, got dtype {a.dtype}")
        if a.ndim not in ndims or a.shape[-1] != self.n_inputs:
            shapes = {1: "[n_in]", 2: "[M, n_in]", 3: "[T, M, n_in]"}
            raise ValueError(
                f"inputs must have shape {' or '.join(shapes[n] for n in ndims)} with "
                f"n_in = {self.n_inputs}, got shape {a.shape}"
            )
        return a.astype(np.float32)

    def __call__(self, x: ArrayLike) -> jax.Array:
        a = self._inputs(x, (1, 2, 3))
        xs = a.reshape((1,) * (4 - a.ndim - 1) + a.shape) if a.ndim < 3 else a
        ys = _rollout(self._net, jnp.asarray(xs), hidden=self.spec.hidden, output=self.spec.output)
        return ys.reshape(*a.shape[:-1], self.n_outputs)

    def initial_state(self, streams: int | None = None) -> jax.Array:
        """The state before the first step: zeros ``[H]`` (or ``[streams, H]``)."""
        h = self._net.bias.shape[-1]
        return jnp.zeros((h,) if streams is None else (streams, h), jnp.float32)

    def step(self, x: ArrayLike, state: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One step: ``x`` ``[n_in]`` or ``[M, n_in]``, ``state`` of the matching shape."""
        a = self._inputs(x, (1, 2))
        s = jnp.asarray(state, jnp.float32)
        if s.shape != (*a.shape[:-1], self._net.bias.shape[-1]):
            raise ValueError(
                f"state must have shape {(*a.shape[:-1], self._net.bias.shape[-1])} "
                f"(from initial_state), got {s.shape}"
            )
        y, h = _step(
            self._net,
            jnp.asarray(a.reshape(-1, a.shape[-1])),
            s.reshape(-1, s.shape[-1]),
            hidden=self.spec.hidden,
            output=self.spec.output,
        )
        return y.reshape(*a.shape[:-1], self.n_outputs), h.reshape(s.shape)

    # Exports (eant2_jax.export), for convenience.
    def to_json(self) -> dict:
        return export.to_json(self.spec)

    def to_jax(self):
        return export.to_jax(self.spec)

    def to_jax_source(self) -> str:
        return export.to_jax_source(self.spec)

    def formula(self, **kw) -> str:
        return export.formula(self.spec, **kw)

    def to_onnx(self, path: str | os.PathLike | None = None):
        """The ONNX model (`eant2_jax.export_onnx.to_onnx`); with ``path``, also written
        there as a new file (`eant2_jax.export_onnx.save`: never replaces a file, never
        follows a link)."""
        from . import export_onnx

        model = export_onnx.to_onnx(self.spec)
        if path is not None:
            export_onnx.save(model, path)
        return model

    def to_sympy(self):
        """The network as sympy equations and expressions (`eant2_jax.export_sympy`)."""
        from .export_sympy import to_sympy

        return to_sympy(self.spec)

    def to_latex(self, **kw) -> str:
        """LaTeX of `to_sympy` (`SympyNetwork.latex`'s options)."""
        return self.to_sympy().latex(**kw)


def load(
    path: str | os.PathLike, *, hidden: str | None = None, output: str | None = None
) -> LoadedNetwork:
    """Load a genome file as a callable network.

    Args:
      path: a genome file (a run directory's ``best.genome``, or any file of the format).
      hidden: activation name of hidden neurons; needed only for a file without a header
        (one written before genome files had one), and must agree with the header otherwise.
      output: activation name of root (output) neurons; likewise.

    Returns:
      The `LoadedNetwork`.
    """
    return LoadedNetwork(GenomeFile.read(path).with_activations(hidden, output))
