"""A ready-made progress reporter for `eant2_jax.run`, `eant2_jax.resume` and
`eant2_jax.run_many` (opt-in: the library itself never prints).

::

    result = eant2_jax.run(task, key=key, generations=2,
                           callback=eant2_jax.ProgressReporter(2))

prints, on standard error, one line per event (a live line that rewrites itself on a
terminal); from ``docs/examples/point_mass.py``::

    gen 0/2: compiling the exploitation program (6 structures, 8 genes, depth 1, 10 candidates)...
    gen 0/2 | best 0.0217 | size 3 (1 neurons) | pruned 0/0 | 1,001 evals, 166/s | 6.0 s
    gen 1/2: compiling the exploitation program (6 structures, 8 genes, depth 2, 10 candidates)...
    gen 1/2 | best 0.01761 | size 4 (1 neurons) | pruned 0/0 | 7,007 evals, 794/s | 8.8 s

The ``eant2`` command line renders its runs with the same class.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressReporter"]


class ProgressReporter:
    """Renders the loop's progress events (``callback=ProgressReporter(...)``).

    Events (dicts; see `eant2_jax.run`): ``compiling`` (before a program is first
    compiled), ``exploit`` (after each chunk of CMA-ES iterations; shown only on a
    terminal), ``generation`` (a completed generation). Others are ignored.

    Args:
      total: the number of generations, shown as ``gen g/total`` (None: ``gen g``).
      stream: where to write (default: ``sys.stderr`` at the time of each event).
      header: a line printed with the first event, i.e. once the run directory has been
        accepted, so that an error before that is the only line.
      live: rewrite one line in place (default: whether ``stream`` is a terminal).
    """

    def __init__(
        self,
        total: int | None = None,
        stream: TextIO | None = None,
        header: str | None = None,
        live: bool | None = None,
    ):
        self.total = total
        self.header = header
        self._stream = stream
        self.live = live
        self.last: dict | None = None
        self.t0 = time.perf_counter()

    @property
    def stream(self) -> TextIO:
        return sys.stderr if self._stream is None else self._stream

    def _gen(self, g: int) -> str:
        return f"gen {g}" if self.total is None else f"gen {g}/{self.total}"

    def __call__(self, event: dict) -> None:
        live = self.stream.isatty() if self.live is None else self.live
        if self.header is not None:
            print(self.header, file=self.stream, flush=True)
            self.header = None
        kind = event.get("event")
        if kind == "compiling":
            text = (
                f"{self._gen(event['generation'])}: compiling the exploitation program "
                f"({event['structures']} structures, {event['genes']} genes, depth "
                f"{event['sweeps']}, {event['popsize']} candidates)..."
            )
            if live:
                self._line(text)
            else:
                print(text, file=self.stream, flush=True)
        elif kind == "exploit":
            if live:
                best = "" if self.last is None else f" | best {self.last['best_cost']:.4g}"
                self._line(
                    f"{self._gen(event['generation'])} | exploit iter {event['iteration']}"
                    f" ({event['running']} running){best}"
                )
        elif kind == "generation":
            self.last = event
            elapsed = time.perf_counter() - self.t0
            rate = event["evaluations"] / max(elapsed, 1e-9)
            text = (
                f"{self._gen(event['generation'])} | best {event['best_cost']:.4g}"
                f" | size {event['best_size']} ({event['best_neurons']} neurons)"
                f" | pruned {event['prune_accepted']}/{event['prune_attempts']}"
                f" | {event['evaluations']:,} evals, {rate:,.0f}/s | {elapsed:.1f} s"
            )
            if live:
                self._line(text)
                self.stream.write("\n")
                self.stream.flush()
            else:
                print(text, file=self.stream, flush=True)

    def _line(self, text: str) -> None:
        self.stream.write("\r" + text[:160].ljust(100))
        self.stream.flush()
