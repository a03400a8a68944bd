"""The field benchmark's runs (bench/bench_field.py): one (environment, seed, method) in
this fresh process, ``python -m bench.field_runner worker ...``, writing its curve after every
generation and then its champions' test returns."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from bench.bench_field import ENVS, METHODS, TENSORNEAT_POP, Env, quick_env
from bench.common import unseen_key
from bench.field_workers import Log

__all__ = ["tensorneat_size", "worker"]


class _Deadline(Exception):
    pass


def _task(env: Env, args: argparse.Namespace, episodes: int):
    from eant2_jax import tasks

    if env.family == "servo":
        return tasks.make("servo")
    if env.family == "gymnax":
        return tasks.make(f"gymnax:{env.name}", episodes=episodes, max_steps=env.max_steps,
                          normalize=env.normalize)  # fmt: skip
    return tasks.make(
        f"brax:{env.name}", episodes=episodes, max_steps=env.max_steps, backend=args.backend
    )


def _worker_eant2(env: Env, args: argparse.Namespace, log: Log) -> None:
    import jax

    import eant2_jax
    from eant2_jax.compiler import networks
    from eant2_jax.genome import Genome
    from eant2_jax.tasks.episodic import returns

    task = _task(env, args, env.episodes)
    config = eant2_jax.EANT2Config(
        population=args.population or env.population,
        max_evaluations=args.budget,
        reexploit=env.reexploit,
        inherit_search=env.reexploit,
        min_bucket=env.min_bucket,
        # The field compares returns at equal budgets: both methods spend the whole budget.
        stop_when_solved=False,
        exploit=eant2_jax.ExploitConfig(
            pruner=args.pruner,
            max_iters=args.max_iters or env.max_iters,
            rescore=env.rescore,
            popsize=env.popsize,
        ),
    )
    log.data["settings"] = config.to_dict()

    def on_event(e: dict) -> None:
        if e["event"] != "generation":
            return
        log.point(evaluations=e["evaluations"], train_return=-e["best_cost"],
                  size=e["best_size"], champion=e["best_genome"])  # fmt: skip
        if log.wall() > args.deadline_s:
            raise _Deadline

    try:
        eant2_jax.run(task, key=jax.random.key(args.seed), config=config,
                      generations=10**9, callback=on_event)  # fmt: skip
    except _Deadline:
        log.data["deadline"] = True
    test = _task(env, args, 1)
    scores: dict[str, float] = {}
    for p in log.data["curve"]:
        text = p["champion"]
        if text in scores:
            pass
        elif env.family == "servo":  # deterministic: the cost is the test
            c = eant2_jax.cost(Genome.parse(text), task, key=unseen_key(args.seed))
            scores[text] = -float(np.asarray(c).ravel()[0])
        else:
            nets = networks([Genome.parse(text)], task.n_inputs)
            r = returns(test, nets, key=unseen_key(args.seed), episodes=args.test_episodes)
            scores[text] = float(np.mean(r[0]))
        p["test_return"] = scores[text]


def _tensorneat_problem(env: Env, args: argparse.Namespace, repeat: int):
    from bench.field_tensorneat import problem

    return problem(
        env.family,
        env.name,
        n_inputs=env.n_inputs,
        n_outputs=env.n_outputs,
        max_steps=env.max_steps,
        repeat=repeat,
        backend=args.backend,
        obs_norm_episodes=dict(env.tensorneat).get("obs_norm_episodes", 0),
    )


def _worker_tensorneat(env: Env, args: argparse.Namespace, log: Log) -> None:
    from bench.field_tensorneat import algorithm as neat
    from bench.field_tensorneat import import_from

    import_from(args.tensorneat)
    import jax
    from tensorneat.pipeline import Pipeline

    if env.discrete:
        out = "argmax"
    elif env.family == "servo":
        out = None  # the task's own tanh step
    else:
        out = f"{env.action_scale} tanh"
    pop = args.tensorneat_pop
    extra = dict(env.tensorneat)
    sizes = {k: extra[k] for k in ("max_nodes", "max_conns") if k in extra}
    algorithm = neat(env.n_inputs, env.n_outputs, pop=pop, output=out,
                          activation=extra.get("activation", "tanh"), **sizes)  # fmt: skip
    generations = max(1, math.ceil(args.budget / pop))
    pipeline = Pipeline(algorithm=algorithm, problem=_tensorneat_problem(env, args, env.episodes),
                        seed=args.seed, generation_limit=generations,
                        fitness_target=math.inf)  # fmt: skip
    log.data["settings"] = {"pop_size": pop, "species_size": 20, "survival_threshold": 0.1,
                            "compatibility_threshold": 1.0, "generations": generations,
                            **extra}  # fmt: skip
    state = pipeline.setup()
    # As Pipeline.auto_run compiles it: ahead of time, once (a plain jit retraced the step
    # after its first call, the state's types having changed).
    step = jax.jit(pipeline.step).lower(state).compile()
    best, champion, champions = -math.inf, None, []
    for g in range(generations):
        state, population, fitness = step(state)
        fitness = np.asarray(jax.device_get(fitness))
        i = int(np.argmax(fitness))
        if fitness[i] > best or champion is None:
            best = float(fitness[i])
            champion = (np.asarray(population[0][i]), np.asarray(population[1][i]))
            champions.append(champion)
        size = tensorneat_size(champion, env.n_inputs)
        log.point(evaluations=(g + 1) * pop, train_return=best, size=size,
                  champion=len(champions) - 1)  # fmt: skip
        if log.wall() > args.deadline_s:
            log.data["deadline"] = True
            break
    # Not set up again: the state already holds what setup registers (the observation
    # statistics of a normalised problem, which the test episodes must share).
    test = _tensorneat_problem(env, args, args.test_episodes)

    @jax.jit
    def score(nodes, conns):
        t = algorithm.transform(state, (nodes, conns))
        return test.evaluate(state, unseen_key(args.seed), algorithm.forward, t)

    scores = [float(score(*c)) for c in champions]
    for p in log.data["curve"]:
        p["test_return"] = scores[p["champion"]]


def tensorneat_size(genome: tuple[np.ndarray, np.ndarray], n_inputs: int) -> int:
    """Weights of a TensorNEAT genome: its connections plus the biases of its non-input
    nodes (unused rows of the padded node and connection arrays are NaN)."""
    nodes, conns = genome
    used_nodes = int(np.sum(~np.isnan(nodes[:, 0])))
    return int(np.sum(~np.isnan(conns[:, 0]))) + used_nodes - n_inputs


def worker(argv: list[str]) -> int:
    """``python -m bench.bench_field worker ...``: one run, in this (fresh) process."""
    p = argparse.ArgumentParser(prog="python -m bench.field_runner worker")
    p.add_argument("--method", choices=METHODS, required=True)
    p.add_argument("--env", choices=sorted(ENVS), required=True)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--budget", type=int, required=True)
    p.add_argument("--deadline-s", type=float, required=True)
    p.add_argument("--t0", type=float, required=True, help="time.time() at process start")
    p.add_argument("--out", required=True)
    p.add_argument("--test-episodes", type=int, default=20)
    p.add_argument("--backend", default="spring")
    p.add_argument("--population", type=int, default=None)
    p.add_argument("--max-iters", type=int, default=None)
    p.add_argument("--pruner", default="covariance", help="eant2's pruner (--quick: none)")
    p.add_argument("--tensorneat", default=None)
    p.add_argument("--tensorneat-pop", type=int, default=TENSORNEAT_POP)
    p.add_argument("--quick", action="store_true",
                   help="the environment as --quick runs it (bench_field.quick_env)")  # fmt: skip
    args = p.parse_args(argv)
    env = quick_env(ENVS[args.env]) if args.quick else ENVS[args.env]
    log = Log(args.out, args.t0, {"method": args.method, "env": args.env, "seed": args.seed,
                                   "budget": args.budget})  # fmt: skip
    log.data["start_s"] = log.wall()  # process start to the first line of Python here
    (_worker_eant2 if args.method == "eant2" else _worker_tensorneat)(env, args, log)
    log.data["done"] = True
    log.write()
    return 0


if __name__ == "__main__":
    sys.exit(worker(sys.argv[2:] if sys.argv[1:2] == ["worker"] else sys.argv[1:]))
