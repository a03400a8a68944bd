"""A custom EANT2 task in plain JAX: push a point mass to a target (docs/tasks-custom.md).

Run it: ``python docs/examples/point_mass.py`` (CMA-ES on one network, then EANT2), or
``eant2 run docs/examples/point_mass.py --generations 3`` (the factory is ``make_task``).
"""

import jax
import jax.numpy as jnp

from eant2_jax import pytree
from eant2_jax.kernels import network as kn
from eant2_jax.tasks import map_networks


@pytree.dataclass
class PointMass:
    """Push a unit mass on a line from a random start at rest to x = 0, and hold it there."""

    dt: float = 0.1  # a traced number: a new value runs the same compiled program
    steps: int = pytree.field(pytree_node=False, default=50)  # shapes the program: static
    starts: int = pytree.field(pytree_node=False, default=8)  # episodes per evaluation
    n_inputs: int = pytree.field(pytree_node=False, default=2)  # position, velocity
    n_outputs: int = pytree.field(pytree_node=False, default=1)  # force
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="tanh")  # force in [-1, 1]
    noisy: bool = pytree.field(pytree_node=False, default=True)  # random starts

    def episode(self, net: kn.Network, x0: jax.Array) -> jax.Array:
        """Mean of x^2 + 0.1 v^2 over one episode of ONE network from position x0."""

        def step(carry, _):
            x, v, h = carry
            y, h = kn.step(net, jnp.stack([x, v]), h, hidden=self.hidden, output=self.output)
            v = v + self.dt * y[0]  # semi-implicit Euler
            x = x + self.dt * v
            return (x, v, h), x**2 + 0.1 * v**2

        h0 = jnp.zeros(net.bias.shape)  # recurrent state: zero at the start
        carry = (x0, jnp.zeros_like(x0), h0)
        _, err = jax.lax.scan(step, carry, None, length=self.steps)
        return jnp.mean(err)

    def cost(self, key: jax.Array, nets: kn.Network) -> jax.Array:
        """Costs [*batch]: every network of the call starts from the same positions."""
        x0 = jax.random.uniform(key, (self.starts,), minval=-1.0, maxval=1.0)

        def one(net):
            return jnp.mean(jax.vmap(self.episode, in_axes=(None, 0))(net, x0))

        return map_networks(one, nets)


def make_task(*, steps: int = 50, starts: int = 8) -> PointMass:
    """The factory ``eant2 run FILE.py`` calls (options: ``--task-option steps=100``)."""
    return PointMass(steps=int(steps), starts=int(starts))


if __name__ == "__main__":
    import sys

    import eant2_jax

    task = eant2_jax.tasks.make(__file__)  # remembers its spec: the run can be resumed
    zero = eant2_jax.cost("N0/2*1 I0*0 I1*0", task, key=jax.random.key(1))[0]
    print(f"no force: cost {zero:.4f}")
    # A bias the task does not need (it is symmetric about x = 0): covariance pruning, on by
    # default, removes it. On a noisy task the pruned network is compared with the current
    # mean on the same episodes (prune_reference="mean"; docs/pruning.md).
    start = "N0/3*1 I0*0 I1*0 B*0"
    res = eant2_jax.optimize(
        start, task, key=jax.random.key(0), max_iters=100, prune_reference="mean"
    )
    removed = [a.kind for a in res.pruning if a.accepted]
    print(f"optimize: cost {res.cost:.4f} ({res.stop_reason}), {res.genome.n_params} genes")
    print(f"pruning:  {len(res.pruning)} attempt(s), removed {removed}: {res.genome}")

    config = eant2_jax.EANT2Config(population=6, exploit=eant2_jax.ExploitConfig(max_iters=100))
    result = eant2_jax.run(
        task,
        key=jax.random.key(0),
        config=config,
        generations=2,
        callback=eant2_jax.ProgressReporter(2, stream=sys.stdout, live=False),
    )
    print(f"run: best cost {result.generations[-1].best_cost:.4f}, {result.best.n_params} genes")
