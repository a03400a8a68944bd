"""A ready-made progress reporter for `eant2_jax.run`, `eant2_jax.resume` and
`eant2_jax.run_many` (opt-in: the library itself never prints).

::

    result = eant2_jax.run(task, key=key, generations=2,
                           callback=eant2_jax.ProgressReporter(2))

prints, on standard error, one line per event (a live line that rewrites itself on a
terminal): a "compiling" line before a program is first compiled, and per generation::

    gen 1/2 | best 0.01853 | mean 0.01872 ± 9.6e-05 | size 3 (1 neurons) | pruned 0/5 |
        7,128 evals, 167/s | 42.6 s

(one line; docs/tasks-custom.md shows all that ``docs/examples/point_mass.py`` printed).

The ``eant2`` command line renders its runs with the same class.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
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
      clock: the time in seconds (default ``time.perf_counter``; a test passes its own).

    A generation's line shows the best cost, the population's cost mean and standard
    deviation, the best network's size, the pruning attempts accepted, the run's
    evaluations and a rate: the evaluations spent in THIS process (its generations'
    ``generation_evaluations``, all runs' together) over the time since the reporter was
    made, so that a resumed run's rate does not count the evaluations of earlier processes.
    """

    def __init__(
        self,
        total: int | None = None,
        stream: TextIO | None = None,
        header: str | None = None,
        live: bool | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ):
        self.total = total
        self.header = header
        self._stream = stream
        self.live = live
        self.last: dict | None = None
        self.clock = clock
        self.t0 = clock()
        self.spent = 0  # cost evaluations of the generations reported by this process

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
            elapsed = self.clock() - self.t0
            spent = event.get("generation_evaluations")
            self.spent += event["evaluations"] if spent is None else spent
            rate = self.spent / max(elapsed, 1e-9)
            text = (
                f"{self._gen(event['generation'])} | best {event['best_cost']:.4g}"
                f"{_spread(event)}"
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


def _spread(event: dict) -> str:
    """`` | mean M ± S``: the population's cost mean and standard deviation, if recorded."""
    mean, std = event.get("mean_cost"), event.get("cost_std")
    return "" if mean is None or std is None else f" | mean {mean:.4g} ± {std:.2g}"
