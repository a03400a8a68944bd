"""The ``eant2`` command line. The library never prints; this module renders."""

from __future__ import annotations

import argparse
import sys

import numpy as np

__all__ = ["main"]

DEMO_GENOME = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"
# One output neuron reading both inputs, a bias and one hidden neuron: enough for XOR.
XOR_START = "N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"


def _demo(args: argparse.Namespace) -> int:
    import eant2_jax

    genome = eant2_jax.Genome.parse(DEMO_GENOME)
    print(f"genome     {genome}")
    print(
        f"           {genome.n_params} parameters, {genome.n_inputs} inputs, "
        f"{genome.n_outputs} outputs, {genome.n_neurons} neurons, depth {genome.depth()}"
    )
    x = np.random.default_rng(args.seed).normal(size=(4, 2, genome.n_inputs))
    y = np.asarray(eant2_jax.evaluate(genome, x))[0]
    ref = eant2_jax.interpret(genome, x)
    first = np.round(y[:, 0].astype(float), 3).tolist()
    print(f"evaluate   stream 0 over {x.shape[0]} steps: {first}")
    print(f"reference  max |compiled - NumPy reference| = {np.max(np.abs(y - ref)):.2e}")

    import jax

    task = eant2_jax.tasks.make("xor")
    start = eant2_jax.Genome.parse(XOR_START)
    c0 = eant2_jax.cost(start, task, key=jax.random.key(0))[0]
    print(f"\nxor        start {start}  (cost {c0:.4f})")
    res = eant2_jax.optimize(start, task, key=jax.random.key(args.seed), max_iters=args.iters)
    patterns = np.array([[[0, 0], [0, 1], [1, 0], [1, 1]]], dtype=float)
    out = np.asarray(eant2_jax.evaluate(res.genome, patterns)).ravel().astype(float)
    solved = bool(np.all((out > 0.5) == np.array([False, True, True, False])))
    evals = int(res.history["evaluations"][-1])
    print(f"optimize   cost {res.cost:.3g} after {evals} evaluations ({res.stop_reason})")
    print(f"           outputs on the four patterns {np.round(out, 3).tolist()}; solved: {solved}")
    print(f"tuned      {res.genome}")
    return 0 if solved else 1


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="eant2", description="EANT2 neuro-evolution in JAX.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser(
        "demo", help="evaluate a small recurrent genome, then tune a network on XOR with CMA-ES"
    )
    demo.add_argument("--seed", type=int, default=0, help="seed of inputs and CMA-ES")
    demo.add_argument("--iters", type=int, default=600, help="CMA-ES iteration budget")
    demo.set_defaults(func=_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as e:
        print(f"eant2: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
