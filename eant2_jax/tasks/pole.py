"""Double pole balancing, with (``dpv``) and without (``dpnv``) velocity inputs.

The classic neuro-evolution benchmark (Wieland 1991), in the protocol of ESP (Gomez &
Miikkulainen 1999), NEAT (Stanley & Miikkulainen 2002) and CoSyNE (Gomez et al. 2008): a cart
on a 4.8 m track carries two poles hinged side by side, a long one (half-length 0.5 m) and a
short one (half-length 0.05 m); a network pushes the cart with a force in [-10, 10] N and must
keep both poles up and the cart on the track. Everything below is written for ONE network and
ONE start state and batched with ``jax.vmap`` by the caller (`map_networks`).

Equations of motion (Wieland 1991; printed in Gomez & Miikkulainen 1999, appendix, and
coded as ``CartPole::step`` in ESP's and NEAT's C++):

    x''    = (F - mu_c sgn(x') + sum_i Ft_i) / (M + sum_i mt_i)
    th_i'' = -3 / (4 l_i) * (x'' cos th_i + g sin th_i + mu_p th_i' / (m_i l_i))
    Ft_i   = m_i l_i th_i'^2 sin th_i + 3/4 m_i cos th_i (mu_p th_i' / (m_i l_i) + g sin th_i)
    mt_i   = m_i (1 - 3/4 cos^2 th_i)

with ``g = -9.8`` m/s^2 as printed and coded (the sign places the upright pole at an unstable
equilibrium with these signs; the magnitude is the usual 9.8). ``Ft_i`` is the effective force
and ``mt_i`` the effective mass of pole i on the cart. The state is
``s = (x, x', th_1, th_1', th_2, th_2')`` in m, m/s, rad, rad/s; th > 0 leans a pole towards
+x. The force is held for one action of two RK4 steps of 0.01 s (``CartPole::performAction``).

Choices this module makes, each documented where it is implemented:

* Cart friction ``mu_c sgn(x')`` is applied, as in Wieland's equations and ESP's code. NEAT's
  C++ declares ``MUC = 0.0005`` but never uses it; pass ``cart_friction=0.0`` to reproduce
  that code. (5e-4 N against forces of up to 10 N: the difference is negligible.)
  ``sgn(0) = 0`` here; ESP's macro gives +1 at 0 (the first step from rest only).
* No bias input: NEAT feeds a constant 0.5 (ESP 1.0) as an extra input; an EANT2 genome has
  bias genes (``B``) for that, so the task has 6 (dpv) or 3 (dpnv) inputs.
* The output neuron uses ``tanh`` (in [-1, 1]) and ``force = 10 N * clip(y, -1, 1)``; the
  clip is needed because a root neuron's own weight scales its output. NEAT's output is a
  sigmoid in [0, 1] mapped by ``(y - 0.5) * 20``, which is the same family
  (``2 sigmoid(2a) - 1 = tanh(a)``).
* A state is balanced iff ``|x| <= 2.4`` and ``|th_i| <= 36 deg`` for both poles; a NaN state
  (from a network with absurd weights) is not, so NaNs end a trial as failures.
* float32 throughout (ESP and NEAT use double). A controller that balances keeps the state
  near a stable orbit and its count does not depend on rounding; a network that only delays
  the fall rides an unstable trajectory that amplifies rounding by up to ``e^(12 t / s)``, so
  its count can differ between programs that round differently — XLA's CPU code for a batch
  of one is not its vectorised code for a batch of nine (seen once: 305 vs 568 steps for
  the same weights). Within one program (one CMA-ES run) costs are deterministic.

Fitness and cost (lower is better; ``cost = -fitness``; the PRNG key is unused: the task is
deterministic):

* ``fitness="steps"`` (dpv): the number of actions after which the state is still balanced,
  from the standard start, up to ``max_steps`` (100,000 as in NEAT's and ESP's dpv).
* ``fitness="damping"`` (dpnv): Gruau et al. (1996) ``f = 0.1 f1 + 0.9 f2`` with
  ``f1 = t / 1000`` and ``f2 = 0.75 / sum_{last 100 balanced states} (|x| + |x'| + |th_1| +
  |th_1'|)`` if ``t >= 100`` else 0, over ``max_steps = 1000`` actions. It rewards balancing
  AND penalises the oscillation a controller without velocities can use to infer them.

A trial ends at the first failure; the whole batch exits early once every trial in it has
ended (a ``lax.while_loop`` over ``chunk``-step ``lax.scan`` blocks; see `PoleTask`).

Counting evaluations (as NEAT's, ESP's and CoSyNE's papers count them): one evaluation = one
network run by the task's cost during evolution (each CMA-ES candidate, each pruning trial).
The solution check of `solved` (100,000 steps, then the 625-start generalisation test)
is a test and is NOT counted. `eant2_jax.exploitation` counts exactly the former
(``evaluations`` in its history).

References:
  A. Wieland, "Evolving neural network controllers for unstable systems", IJCNN 1991.
  F. Gruau, D. Whitley, L. Pyeatt, "A comparison between cellular encoding and direct encoding
  for genetic neural networks", GP 1996 (the damping fitness and the 625-start test).
  F. Gomez, R. Miikkulainen, "Solving non-Markovian control tasks with neuroevolution",
  IJCAI 1999 (ESP; constants and equations in its appendix).
  K. O. Stanley, R. Miikkulainen, "Evolving neural networks through augmenting topologies",
  Evolutionary Computation 10(2), 2002 (NEAT; input scaling and start state from its code).
  F. Gomez, J. Schmidhuber, R. Miikkulainen, "Accelerated neural evolution through
  cooperatively coevolved synapses", JMLR 9, 2008 (CoSyNE; same protocol).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import pytree
from ..kernels import network as kn
from .base import map_networks

__all__ = [
    "GRID_VALUES",
    "Physics",
    "PoleTask",
    "Trial",
    "act",
    "balanced",
    "damping_fitness",
    "derivatives",
    "dpnv",
    "dpv",
    "grid_starts",
    "jiggle",
    "observe",
    "physics",
    "rk4",
    "solved",
    "start_state",
    "trajectory",
]

# The physics lives in its own module; its names are part of this module's API too.
from .pole_physics import (  # noqa: F401
    _JIGGLE_WINDOW,
    _SCALE_NV,
    _SCALE_V,
    FITNESSES,
    GRID_VALUES,
    Physics,
    act,
    balanced,
    damping_fitness,
    derivatives,
    grid_starts,
    jiggle,
    observe,
    physics,
    rk4,
    start_state,
)


class Trial(NamedTuple):
    """Outcome of one network from one start: ``steps`` balanced actions (int32) and
    ``jiggle_sum``, the damping sum over the last (up to) 100 balanced states."""

    steps: jax.Array
    jiggle_sum: jax.Array


@pytree.dataclass
class PoleTask:
    """Double pole balancing (module docstring). Build with `dpv` or `dpnv`.

    Attributes:
      physics: the constants (`Physics`).
      start: ``[6]`` the start state of the cost's trial.
      velocities: dpv (6 inputs) if True, dpnv (3 inputs) if False (static).
      fitness: ``steps`` or ``damping`` (static; see the module docstring).
      max_steps: actions per trial (static).
      chunk: actions per ``lax.scan`` block between the batch's early-exit checks (static).
        ``chunk >= max_steps`` makes the trial one fixed-length scan.
      hidden, output: activation names (static).
    """

    physics: Physics
    start: jax.Array
    velocities: bool = pytree.field(pytree_node=False, default=True)
    fitness: str = pytree.field(pytree_node=False, default="steps")
    max_steps: int = pytree.field(pytree_node=False, default=100_000)
    chunk: int = pytree.field(pytree_node=False, default=100)
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="tanh")

    @property
    def n_inputs(self) -> int:
        return 6 if self.velocities else 3

    @property
    def n_outputs(self) -> int:
        return 1

    @property
    def solved_cost(self) -> float | None:
        """``-max_steps`` under the steps fitness: every action balanced, NEAT's and ESP's
        dpv solution; None under the damping fitness, whose solutions are those that pass
        `solved` (no cost level says it: pass ``solution_test``, `eant2_jax.run`)."""
        return -float(self.max_steps) if self.fitness == "steps" else None

    def rollout(self, net: kn.Network, start: jax.Array) -> Trial:
        """Run ONE network from ONE start ``[6]`` until it fails or ``max_steps`` actions.

        The network's recurrent state starts at zero. Under ``vmap`` the loop runs until
        every trial of the batch has ended; ended trials are frozen by a mask.
        """
        p = self.physics
        n = self.max_steps
        chunk = max(1, min(self.chunk, n))
        damping = self.fitness == "damping"  # the steps fitness needs no jiggle ring
        h0 = jnp.zeros(net.bias.shape, jnp.float32)
        ring0 = jnp.zeros(_JIGGLE_WINDOW, jnp.float32)
        carry0 = (start.astype(jnp.float32), h0, jnp.int32(0), jnp.bool_(True), ring0)

        def one(carry, _):
            s, h, t, alive, ring = carry
            y, h_new = kn.step(
                net,
                observe(s, velocities=self.velocities),
                h,
                hidden=self.hidden,
                output=self.output,
            )
            s_new = act(p, s, y[0])
            # A trial is live while it has failed nowhere and has actions left.
            live = alive & (t < n)
            ok = live & balanced(p, s_new)
            if damping:
                # Ring of the jiggle of the last 100 balanced states (the states after
                # actions t-99..t), the window of NEAT's JIGGLE_STEP sum.
                ring = jnp.where(ok, ring.at[t % _JIGGLE_WINDOW].set(jiggle(s_new)), ring)
            s = jnp.where(live, s_new, s)
            h = jnp.where(live, h_new, h)
            return (s, h, t + ok.astype(jnp.int32), ok, ring), None

        def block(carry):
            return jax.lax.scan(one, carry, None, length=chunk)[0]

        def going(carry):
            _, _, t, alive, _ = carry
            return alive & (t < n)

        _, _, t, _, ring = jax.lax.while_loop(going, block, carry0)
        return Trial(t, jnp.sum(ring))

    def fitness_of(self, trial: Trial) -> jax.Array:
        """The task's fitness (higher is better) of a trial's outcome."""
        if self.fitness == "damping":
            return damping_fitness(trial.steps, trial.jiggle_sum)
        return trial.steps.astype(jnp.float32)

    def cost(self, key: jax.Array, nets: kn.Network) -> jax.Array:
        """``-fitness`` ``[*batch]`` of networks from the task's start state.

        The key is unused: the task is deterministic (fixed start, no noise).
        """
        del key

        def one(net):
            return -self.fitness_of(self.rollout(net, self.start))

        return map_networks(one, nets)


def _make(
    *,
    velocities: bool,
    fitness: str,
    max_steps: int,
    chunk: int,
    hidden: str,
    output: str,
    theta1: float,
    cart_friction: float,
) -> PoleTask:
    kn.activation(hidden), kn.activation(output)  # clear error for unknown names
    if fitness not in FITNESSES:
        raise ValueError(f"fitness must be one of {', '.join(FITNESSES)}, got {fitness!r}")
    if int(max_steps) < 1 or int(chunk) < 1:
        raise ValueError(f"max_steps and chunk must be >= 1, got {max_steps} and {chunk}")
    return PoleTask(
        physics=physics(cart_friction=cart_friction),
        start=start_state(theta1),
        velocities=velocities,
        fitness=fitness,
        max_steps=int(max_steps),
        chunk=int(chunk),
        hidden=hidden,
        output=output,
    )


def dpv(
    *,
    max_steps: int = 100_000,
    fitness: str = "steps",
    chunk: int = 100,
    hidden: str = "tanh",
    output: str = "tanh",
    theta1: float = 0.07,
    cart_friction: float = 5e-4,
) -> PoleTask:
    """Double pole balancing WITH velocities (Markovian): 6 inputs, 1 output.

    Fitness: balanced actions up to ``max_steps`` (100,000: NEAT's and ESP's dpv, where a
    network that reaches it is a solution). ``cost = -steps``.
    """
    return _make(
        velocities=True,
        fitness=fitness,
        max_steps=max_steps,
        chunk=chunk,
        hidden=hidden,
        output=output,
        theta1=theta1,
        cart_friction=cart_friction,
    )


def dpnv(
    *,
    max_steps: int = 1000,
    fitness: str = "damping",
    chunk: int = 100,
    hidden: str = "tanh",
    output: str = "tanh",
    theta1: float = 0.07,
    cart_friction: float = 5e-4,
) -> PoleTask:
    """Double pole balancing WITHOUT velocities (non-Markovian: needs recurrence): 3 inputs.

    Fitness: Gruau et al.'s damping fitness over ``max_steps = 1000`` actions (as ESP and
    NEAT); ``cost = -fitness``. A solution must pass `solved`.
    """
    return _make(
        velocities=False,
        fitness=fitness,
        max_steps=max_steps,
        chunk=chunk,
        hidden=hidden,
        output=output,
        theta1=theta1,
        cart_friction=cart_friction,
    )


def trajectory(task: PoleTask, net: kn.Network, start: jax.Array, steps: int):
    """States ``[steps, 6]`` after each action and outputs ``[steps]`` of ONE network from
    ``start``, with no early stop and no failure check (for plots and tests)."""

    def one(carry, _):
        s, h = carry
        y, h = kn.step(
            net, observe(s, velocities=task.velocities), h, hidden=task.hidden, output=task.output
        )
        s = act(task.physics, s, y[0])
        return (s, h), (s, y[0])

    h0 = jnp.zeros(net.bias.shape, jnp.float32)
    _, (states, outputs) = jax.lax.scan(one, (start.astype(jnp.float32), h0), None, length=steps)
    return states, outputs


@functools.partial(jax.jit, static_argnames=("long_steps", "test_steps"))
def _check(task: PoleTask, nets: kn.Network, starts: jax.Array, long_steps: int, test_steps: int):
    # Both parts count balanced steps only (no damping ring to carry).
    long_task = task.replace(max_steps=long_steps, fitness="steps")
    test_task = task.replace(max_steps=test_steps, fitness="steps")

    def one(net):
        long = long_task.rollout(net, task.start).steps
        tests = jax.vmap(test_task.rollout, in_axes=(None, 0))(net, starts).steps
        return long, jnp.sum(tests >= test_steps, dtype=jnp.int32)

    return map_networks(one, nets)


def solved(
    task: PoleTask,
    net: kn.Network,
    *,
    long_steps: int = 100_000,
    test_steps: int = 1000,
    required: int = 200,
    generalisation: bool | None = None,
) -> dict:
    """The solution check of ESP/NEAT, on device (host-side entry point; not counted as
    evaluations).

    1. Balance ``long_steps`` (100,000) actions from the task's start state.
    2. Generalisation (Gruau et al. 1996): from each of the 625 `grid_starts`, balance
       ``test_steps`` (1,000) actions; at least ``required`` (200) must succeed.

    Both parts are always measured (the 625 trials run as one batch). Whether part 2 is part
    of the verdict follows the published protocol unless ``generalisation`` says otherwise:
    dpnv requires it (Gruau et al.; ESP; NEAT), dpv does not (NEAT and ESP stop dpv at
    100,000 steps).

    Args:
      task: a `PoleTask` (its inputs, activations and physics are used).
      net: a `Network` with any leading batch shape (for a genome:
        ``eant2_jax.compiler.networks([genome], task.n_inputs)``).
      long_steps, test_steps, required: the protocol's numbers.
      generalisation: require part 2 (None: True for dpnv, False for dpv).

    Returns:
      ``{"balanced_steps", "generalisation", "solved"}``: Python ints/bool for an unbatched
      network, NumPy arrays ``[*batch]`` for a batch.
    """
    if generalisation is None:
        generalisation = not task.velocities
    if not isinstance(net, kn.Network):
        raise TypeError(
            f"solved() takes a Network (eant2_jax.compiler.networks turns genomes into "
            f"networks), got {type(net).__name__}"
        )
    nets, scalar = net, net.bias.ndim == 1
    if scalar:
        nets = jax.tree.map(lambda a: a[None], nets)
    long, count = _check(
        task, nets, jnp.asarray(grid_starts()), long_steps=long_steps, test_steps=test_steps
    )
    long, count = np.asarray(long), np.asarray(count)
    ok = long >= long_steps
    if generalisation:
        ok = ok & (count >= required)
    if scalar:
        return {
            "balanced_steps": int(long[0]),
            "generalisation": int(count[0]),
            "solved": bool(ok[0]),
        }
    return {"balanced_steps": long, "generalisation": count, "solved": ok}
