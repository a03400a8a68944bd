"""TensorNEAT in the field benchmark: its problem for each environment, NEAT with its
examples' settings, and the field protocol's training run (bench/field_protocol.py).

TensorNEAT (EMI-Group/tensorneat) is fetched, never vendored: every function here takes
the folder that holds its ``tensorneat`` package (``--tensorneat SRC``) and imports it from
there. Its problems feed raw observations (halfcheetah: normalised by statistics of random
episodes at setup, its example's); a discrete action is the argmax of one output per
action, a continuous one ``scale * tanh`` of the outputs.
"""

from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench import field_tnstate
from bench.common import BenchInputError

__all__ = ["algorithm", "compact", "import_from", "problem", "run_generations", "train"]


def import_from(src: str | Path) -> None:
    """Make TensorNEAT importable from ``src`` (the folder holding its package)."""
    path = str(Path(src).resolve())
    if path not in sys.path:
        sys.path.insert(0, path)


def problem(family: str, name: str, *, n_inputs: int, n_outputs: int, max_steps: int,
            repeat: int, backend: str, obs_norm_episodes: int = 0):  # fmt: skip
    """TensorNEAT's problem for one environment (``family`` gymnax, brax or servo), each
    evaluation the mean return of ``repeat`` episodes of at most ``max_steps`` steps."""
    import jax

    if family == "servo":
        from tensorneat.problem import BaseProblem

        from bench.peer_methods import outputs_cost
        from eant2_jax import tasks

        task = tasks.make("servo")

        class Servo(BaseProblem):
            """The servo task for TensorNEAT: a genome's outputs at the 1023 start inputs,
            scored by the task's own move and cost (fitness = minus the cost)."""

            jitable = True

            def evaluate(self, state, randkey, act_func, params):
                y = jax.vmap(lambda x: act_func(state, params, x))(task.x_start)
                return -outputs_cost(task, y[None])[0]

            @property
            def input_shape(self):
                return (n_inputs,)

            @property
            def output_shape(self):
                return (n_outputs,)

        return Servo()
    if family == "gymnax":
        from tensorneat.problem.rl import GymNaxEnv

        class Gymnax(GymNaxEnv):
            """TensorNEAT's GymNaxEnv for gymnax >= 0.0.9, whose ``step`` returns
            (obs, state, reward, terminated, truncated, info): TensorNEAT's loop expects
            the older (obs, state, reward, done, info). Nothing else changes."""

            def env_step(self, randkey, env_state, action):
                out = self.env.step(randkey, env_state, action, self.env_params)
                if len(out) == 6:
                    obs, st, reward, terminated, truncated, info = out
                    return obs, st, reward, terminated | truncated, info
                return out

        return Gymnax(name, max_step=max_steps, repeat_times=repeat)
    from tensorneat.problem.rl import BraxEnv

    if not obs_norm_episodes:
        return BraxEnv(name, backend=backend, max_step=max_steps, repeat_times=repeat)

    def random_actions(randkey, obs):  # the halfcheetah example's random_sample_policy
        return jax.random.uniform(randkey, (n_outputs,), minval=-1.0, maxval=1.0)

    return BraxEnv(name, backend=backend, max_step=max_steps, repeat_times=repeat,
                   obs_normalization=True, sample_episodes=obs_norm_episodes,
                   sample_policy=random_actions)  # fmt: skip


def algorithm(n_inputs: int, n_outputs: int, *, pop: int, output: str | None,
              activation: str = "tanh", **sizes: Any):  # fmt: skip
    """NEAT with the examples' settings: ``pop`` genomes, 20 species, survival threshold 0.1,
    compatibility threshold 1.0, ``BiasNode`` (``activation``, sum aggregation), no initial
    hidden layer. ``output``: ``argmax``, ``tanh``, ``"S tanh"`` (S times tanh, the action
    bounds) or None (no transform); ``sizes``: ``max_nodes``/``max_conns``."""
    import jax.numpy as jnp
    from tensorneat.algorithm.neat import NEAT
    from tensorneat.common import ACT, AGG
    from tensorneat.genome import BiasNode, DefaultGenome

    if output == "argmax":
        transform = jnp.argmax
    elif output is None:
        transform = None
    else:
        scale = float(output.split()[0]) if " " in output else 1.0

        def transform(y):
            return scale * jnp.tanh(y)

    return NEAT(
        pop_size=pop, species_size=20, survival_threshold=0.1, compatibility_threshold=1.0,
        genome=DefaultGenome(
            num_inputs=n_inputs, num_outputs=n_outputs, init_hidden_layers=(),
            node_gene=BiasNode(activation_options=getattr(ACT, activation),
                               aggregation_options=AGG.sum),
            output_transform=transform, **sizes,
        ),
    )  # fmt: skip


def compact(nodes: np.ndarray, conns: np.ndarray) -> dict[str, Any]:
    """A genome's used rows as JSON lists, and a digest of them (its identity)."""
    nodes = nodes[~np.isnan(nodes[:, 0])]
    conns = conns[~np.isnan(conns[:, 0])]
    digest = hashlib.sha256(nodes.astype(np.float32).tobytes() + b"|"
                            + conns.astype(np.float32).tobytes()).hexdigest()[:16]  # fmt: skip
    return {"nodes": nodes.tolist(), "conns": conns.tolist(), "digest": digest}


def train(env: dict[str, Any], *, seed: int, src: str, n_inputs: int, n_outputs: int,
          log, top: int, pop: int | None = None, generations: int | None = None,
          deadline_s: float = math.inf, rundir: str | Path | None = None) -> None:  # fmt: skip
    """The protocol's TensorNEAT run: its example's settings (``env["tensorneat"]``),
    generation by generation through ``Pipeline.step``; after each generation ``log.point``
    with the evaluations, the best training fitness, and the ``top`` best distinct genomes
    by training fitness seen so far (their arrays go into ``log.data["candidates"]``).

    With ``rundir`` the state after each generation is kept there (`bench.field_tnstate`)
    and a run that finds one goes on from it, with ``log`` as
    `bench.field_workers.resume_log` reopened it: a run longer than one device call
    finishes over several, its wall times going on (each new process's setup and compile
    count against it)."""
    import_from(src)
    import jax
    from tensorneat.pipeline import Pipeline

    tn = env["tensorneat"]
    pop = pop or tn["pop_size"]
    generations = generations or tn["generations"]
    sizes = {"max_nodes": tn["max_nodes"], "max_conns": tn["max_conns"]}
    algo = algorithm(n_inputs, n_outputs, pop=pop, output=tn["output"],
                     activation=tn["activation"], **sizes)  # fmt: skip
    prob = problem(env["family"], env["name"], n_inputs=n_inputs, n_outputs=n_outputs,
                   max_steps=env["max_steps"], repeat=env["episodes"],
                   backend=env.get("backend", "spring"),
                   obs_norm_episodes=tn["obs_norm_episodes"])  # fmt: skip
    pipeline = Pipeline(algorithm=algo, problem=prob, seed=seed, generation_limit=generations,
                        fitness_target=math.inf)  # fmt: skip
    settings = {**tn, "pop_size": pop, "generations": generations}
    log.data.update(kind="tensorneat", activations=[tn["activation"]], settings=settings)
    state = pipeline.setup()
    if tn["obs_norm_episodes"]:  # what its problem subtracts and divides by
        log.data["obs_mean"] = np.asarray(state.problem_obs_mean).tolist()
        log.data["obs_std"] = np.asarray(state.problem_obs_std).tolist()
    # As Pipeline.auto_run compiles it: ahead of time, once.
    step = jax.jit(pipeline.step).lower(state).compile()
    digest = field_tnstate.settings_digest(
        {"env": env["name"], "seed": seed, "n": [n_inputs, n_outputs], **settings}
    )
    run_generations(step, state, log=log, top=top, pop=pop, generations=generations,
                    deadline_s=deadline_s, rundir=rundir, digest=digest)  # fmt: skip


def run_generations(step, state, *, log, top: int, pop: int, generations: int,
                    deadline_s: float = math.inf, rundir: str | Path | None = None,
                    digest: str = "") -> None:  # fmt: skip
    """`train`'s generations: ``step`` (TensorNEAT's compiled ``Pipeline.step``) from
    ``state`` (its setup's) to ``generations``, or on from the state kept in ``rundir``."""
    import jax

    from bench.field_champions import Archive

    archive, candidates = Archive(top), log.data.setdefault("candidates", {})
    start = 0
    if rundir is not None:
        kept = field_tnstate.load(rundir, state, digest)
        curve = log.data["curve"]
        if kept is not None:
            state, start = kept
        if len(curve) < start or (kept is None and curve):
            raise BenchInputError(f"TensorNEAT run in {rundir}: {start} generations kept, "
                                  f"its log holds {len(curve)}")  # fmt: skip
        # A kill between a generation's point and its state leaves one point more: the
        # generation runs again from the kept state and writes the same point.
        del curve[start:]
        for ident, fitness in curve[-1]["archive"] if curve else []:
            archive.offer(ident, fitness)
    for g in range(start, generations):
        state, population, fitness = step(state)
        fitness = np.asarray(jax.device_get(fitness), np.float64)
        nodes, conns = (np.asarray(a) for a in jax.device_get(population))
        fitness = np.where(np.isnan(fitness), -np.inf, fitness)
        for i in np.argsort(-fitness, kind="stable")[:top]:
            genome = compact(nodes[i], conns[i])
            if archive.offer(genome["digest"], float(fitness[i])):
                candidates.setdefault(genome["digest"], genome)
        log.point(evaluations=(g + 1) * pop, train_return=archive.best(),
                  archive=archive.entries())  # fmt: skip
        if rundir is not None:
            field_tnstate.save(rundir, state, g + 1, digest)
        if log.wall() > deadline_s:
            log.data["deadline"] = True
            break
    keep = {d for p in log.data["curve"] for d, _ in p["archive"]}
    log.data["candidates"] = {d: g for d, g in candidates.items() if d in keep}
