"""Genome files: a genome in text form, with a header that says how to run it.

A genome file is the genome's text form (`eant2_jax.genome`) preceded by one header
line, a ``#`` comment holding a JSON object (written here over several lines, in the file on
one)::

    # eant2-genome {"format": 1, "hidden": "sigmoid", "output": "identity", "n_inputs": 2,
                    "n_outputs": 1, "task": "xor", "task_options": {"hidden": "sigmoid"}}
    N0/4*1.3 N1/3*-2.1 I0*0.8 I1*-0.7 B*0.2 I0*1.1 I1*0.9 B*-0.5

Fields: ``format`` (1), ``hidden`` and ``output`` (activation names), ``n_inputs`` (the
width of the input vector the network reads, which may exceed the inputs its genes name),
``n_outputs``, and ``task`` / ``task_options`` (the task's name and options when known,
else null). ``Genome.parse`` skips comments, so every reader of the bare text form reads
these files too; a file without the header (as written before the header existed) is still
a genome file, whose activations the caller must then name.

`load` returns a `LoadedNetwork`: the network, callable on inputs, evaluated
by the same kernels as the run that wrote it. Host side, except the call itself.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from .compiler import networks
from .genome import Genome
from .kernels import activations
from .kernels import network as kn

__all__ = ["FORMAT", "GenomeFile", "GenomeFileError", "LoadedNetwork", "load"]

FORMAT = 1
HEADER = "# eant2-genome "


class GenomeFileError(ValueError):
    """A genome file whose header is malformed or does not match its genes."""


@dataclasses.dataclass(frozen=True)
class GenomeFile:
    """A genome and what is needed to run it (the header's fields).

    Attributes:
      genome: the network.
      hidden, output: activation names of hidden and root neurons (None: not recorded, a
        file without a header).
      n_inputs: width of the input vector (None: not recorded; ``genome.n_inputs`` then).
      task: the task's name, if known; task_options: its options, if known.
    """

    genome: Genome
    hidden: str | None = None
    output: str | None = None
    n_inputs: int | None = None
    task: str | None = None
    task_options: dict | None = None

    def __post_init__(self):
        if not isinstance(self.genome, Genome):
            raise TypeError(f"GenomeFile.genome must be a Genome, got {type(self.genome)}")
        if (self.hidden is None) != (self.output is None):
            raise GenomeFileError("a genome file names both activations or neither")
        if self.n_inputs is not None and (
            not isinstance(self.n_inputs, int) or self.n_inputs < self.genome.n_inputs
        ):
            raise GenomeFileError(
                f"n_inputs {self.n_inputs!r} is below the {self.genome.n_inputs} inputs "
                "the genome reads"
            )

    @property
    def n_outputs(self) -> int:
        return self.genome.n_outputs

    @property
    def has_header(self) -> bool:
        """Whether the activations are recorded (a file written with a header)."""
        return self.hidden is not None

    @classmethod
    def from_task(
        cls,
        genome: Genome,
        task: Any,
        *,
        name: str | None = None,
        options: dict | None = None,
    ) -> GenomeFile:
        """The file of a genome evolved on ``task`` (its activations and input width)."""
        return cls(
            genome,
            hidden=task.hidden,
            output=task.output,
            n_inputs=int(task.n_inputs),
            task=name,
            task_options=None if options is None else dict(options),
        )

    def header(self) -> dict:
        """The header's JSON object."""
        return {
            "format": FORMAT,
            "hidden": self.hidden,
            "output": self.output,
            "n_inputs": self.n_inputs,
            "n_outputs": self.n_outputs,
            "task": self.task,
            "task_options": self.task_options,
        }

    def to_text(self) -> str:
        """The file's text: the header line (if the activations are known), then the genes."""
        genes = str(self.genome) + "\n"
        if not self.has_header:
            return genes
        return HEADER + json.dumps(self.header(), separators=(", ", ": ")) + "\n" + genes

    @classmethod
    def parse(cls, text: str, *, source: str = "genome file") -> GenomeFile:
        """Read a file's text; ``source`` names it in errors. A file without a header is
        accepted (its activations are None)."""
        first = text.lstrip().split("\n", 1)[0]
        try:
            genome = Genome.parse(text)
        except ValueError as e:
            raise GenomeFileError(f"{source}: {e}") from None
        if not first.startswith(HEADER.rstrip()):
            return cls(genome)
        try:
            head = json.loads(first[len(HEADER.rstrip()) :])
        except json.JSONDecodeError as e:
            raise GenomeFileError(f"{source}: header is not valid JSON: {e}") from None
        if not isinstance(head, dict) or head.get("format") != FORMAT:
            raise GenomeFileError(f"{source}: header is not of format {FORMAT}")
        for key in ("hidden", "output"):
            if not isinstance(head.get(key), str):
                raise GenomeFileError(f"{source}: header has no activation name {key!r}")
        if head.get("n_outputs", genome.n_outputs) != genome.n_outputs:
            raise GenomeFileError(
                f"{source}: header says {head['n_outputs']} outputs, the genome has "
                f"{genome.n_outputs}"
            )
        options = head.get("task_options")
        try:
            return cls(
                genome,
                hidden=head["hidden"],
                output=head["output"],
                n_inputs=head.get("n_inputs"),
                task=head.get("task"),
                task_options=options if isinstance(options, dict) else None,
            )
        except GenomeFileError as e:
            raise GenomeFileError(f"{source}: {e}") from None

    @classmethod
    def read(cls, path: str | os.PathLike) -> GenomeFile:
        """Read a genome file (with or without a header)."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as e:
            raise GenomeFileError(f"cannot read {p}: {e.strerror}") from None
        except UnicodeDecodeError as e:
            raise GenomeFileError(f"{p}: not UTF-8 text (byte {e.start})") from None
        return cls.parse(text, source=str(p))

    def write(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the file; refuses to replace an existing one unless ``overwrite``."""
        p = Path(path)
        with open(p, "w" if overwrite else "x", encoding="utf-8") as f:
            f.write(self.to_text())
        return p

    def with_activations(self, hidden: str | None, output: str | None) -> GenomeFile:
        """This file with the given activations: they fill a missing header and must agree
        with a present one (a mismatch is the bug headers exist to prevent)."""
        if self.has_header:
            for key, want in (("hidden", hidden), ("output", output)):
                if want is not None and want != getattr(self, key):
                    raise GenomeFileError(
                        f"the file's {key} activation is {getattr(self, key)!r}, not {want!r}"
                    )
            return self
        if hidden is None or output is None:
            raise GenomeFileError(
                "the file has no header naming its activations (it was written before "
                "genome files had one); pass hidden= and output=, e.g. hidden='tanh', "
                "output='identity' (the task's options of the run)"
            )
        return dataclasses.replace(self, hidden=hidden, output=output)


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
        from .export import to_json

        return to_json(self.spec)

    def to_jax(self):
        from .export import to_jax

        return to_jax(self.spec)

    def to_jax_source(self) -> str:
        from .export import to_jax_source

        return to_jax_source(self.spec)

    def formula(self, **kw) -> str:
        from .export import formula

        return formula(self.spec, **kw)


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
