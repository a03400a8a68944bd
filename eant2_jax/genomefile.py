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

Reading (`GenomeFile.read`, `read_text`) trusts nothing the file says about itself: the
path must lead to a regular file (a symbolic link to one is fine; ``/dev/zero``, a FIFO or
a directory are refused without blocking), at most `MAX_BYTES` + 1 bytes are read whatever
its size claims, the text must be UTF-8 whose lines end as `eant2_jax.genome.split_lines`
says, and the header must be JSON nested at most `eant2_jax.jsonio.MAX_DEPTH` deep, with
the field types above. Every problem is one `GenomeFileError` line.

`eant2_jax.loaded.load` turns a file into a network callable on inputs, and
`eant2_jax.export` into JSON, standalone JAX source or a formula; both build on this
module, which is host-side Python and imports neither.
"""

from __future__ import annotations

import dataclasses
import json
import os
import stat
from pathlib import Path
from typing import Any

from . import jsonio
from .genome import MAX_ID, Genome, GenomeError, split_lines

__all__ = ["FORMAT", "HEADER", "MAX_BYTES", "GenomeFile", "GenomeFileError", "read_text"]

FORMAT = 1
HEADER = "# eant2-genome "
# The most bytes a genome file may hold (about 4 million genes): a reader reads one more to
# know, whatever the file system says of the file's size.
MAX_BYTES = 64 * 2**20


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
        for key in ("hidden", "output"):
            name = getattr(self, key)
            # Activation names are Python identifiers (kernels.activations.register).
            if name is not None and not (isinstance(name, str) and name.isidentifier()):
                raise GenomeFileError(f"{key} activation {jsonio.short(name)} is not a name")
        n = self.n_inputs
        if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n > MAX_ID):
            raise GenomeFileError(f"n_inputs must be an integer up to {MAX_ID}, got {n!r:.40}")
        if n is not None and n < self.genome.n_inputs:
            raise GenomeFileError(
                f"n_inputs {n!r} is below the {self.genome.n_inputs} inputs the genome reads"
            )
        if self.task is not None and not isinstance(self.task, str):
            raise GenomeFileError(f"task must be a string or null, got {jsonio.short(self.task)}")
        if self.task_options is not None and not isinstance(self.task_options, dict):
            raise GenomeFileError(
                f"task_options must be an object or null, got {jsonio.short(self.task_options)}"
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
        accepted (its activations are None).

        Raises:
          GenomeFileError: one line naming ``source`` and what is wrong (the genes, a line
            end, the header's JSON or one of its fields).
        """
        if not isinstance(text, str):
            raise TypeError(f"GenomeFile.parse expects a str, got {type(text).__name__}")
        try:
            lines = split_lines(text)  # the genes are read by the same rule, in Genome.parse
            genome = Genome.parse(text)
        except GenomeError as e:
            raise GenomeFileError(f"{source}: {e}") from None
        first = next((line.lstrip() for line in lines if line.strip()), "")
        if not first.startswith(HEADER.rstrip()):
            return cls(genome)
        head = jsonio.loads(
            first[len(HEADER.rstrip()) :], f"{source}: header", strict=False, error=GenomeFileError
        )
        fmt = head.get("format") if isinstance(head, dict) else None
        if not isinstance(fmt, int) or isinstance(fmt, bool) or fmt != FORMAT:
            raise GenomeFileError(f"{source}: header is not of format {FORMAT}")
        for key in ("hidden", "output"):
            if not isinstance(head.get(key), str):
                raise GenomeFileError(f"{source}: header has no activation name {key!r}")
        n_out = head.get("n_outputs", genome.n_outputs)
        if not isinstance(n_out, int) or isinstance(n_out, bool) or n_out != genome.n_outputs:
            raise GenomeFileError(
                f"{source}: header says {jsonio.short(n_out)} outputs, the genome has "
                f"{genome.n_outputs}"
            )
        try:
            return cls(
                genome,
                hidden=head["hidden"],
                output=head["output"],
                n_inputs=head.get("n_inputs"),
                task=head.get("task"),
                task_options=head.get("task_options"),
            )
        except GenomeFileError as e:
            raise GenomeFileError(f"{source}: header: {e}") from None

    @classmethod
    def read(cls, path: str | os.PathLike) -> GenomeFile:
        """Read a genome file (with or without a header), bounded as `read_text` says."""
        return cls.parse(read_text(path), source=str(Path(path)))

    def write(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the file; refuses to replace an existing one unless ``overwrite``.

        Neither way follows a link at ``path``: a new file is created exclusively (an
        existing name, a dangling link included, is refused), and a replacement is a
        temporary file renamed over the name (`eant2_jax.jsonio.write_atomic`), so a link
        there is replaced, not written through, and a kill leaves the old file or the new.
        """
        p = Path(path)
        if overwrite:
            jsonio.write_atomic(p, self.to_text())
            return p
        with open(p, "x", encoding="utf-8") as f:
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


def read_text(path: str | os.PathLike, *, limit: int = MAX_BYTES) -> str:
    """The text of a genome file, read within bounds (module docstring).

    The path is opened without blocking (a FIFO with no writer would block a plain open)
    and must then be a regular file; at most ``limit + 1`` bytes are read, so a file that
    claims size 0 (``/proc``) or grows while read cannot exhaust memory.

    Raises:
      GenomeFileError: unreadable, not a regular file, over ``limit`` bytes, or not UTF-8.
    """
    p = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(p, flags)
    except (OSError, ValueError) as e:  # ValueError: a NUL in the path
        raise GenomeFileError(f"cannot read {p}: {getattr(e, 'strerror', None) or e}") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise GenomeFileError(f"{p}: not a regular file (a genome file must be one)")
        data = jsonio.read_upto(fd, limit)
    except OSError as e:
        raise GenomeFileError(f"cannot read {p}: {e.strerror or e}") from None
    finally:
        os.close(fd)
    if len(data) > limit:
        raise GenomeFileError(f"{p}: more than {limit:,} bytes, more than a genome file may hold")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise GenomeFileError(f"{p}: not UTF-8 text (byte {e.start})") from None
