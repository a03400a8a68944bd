"""Double pole physics (Wieland 1991), the inputs a network sees, and the damping fitness:
the pieces of `eant2_jax.tasks.pole` that know nothing of networks. The equations and
constants are documented there; everything is for ONE state, batched by the caller.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .. import pytree

__all__ = [
    "FITNESSES",
    "GRID_VALUES",
    "Physics",
    "act",
    "balanced",
    "damping_fitness",
    "derivatives",
    "grid_starts",
    "jiggle",
    "observe",
    "physics",
    "rk4",
    "start_state",
]

# Input scaling of NEAT's experiments.cpp (CartPole::evalNet): dpv feeds
# (x/4.8, x'/2, th1/0.52, th1'/2, th2/0.52, th2'/2), dpnv (x/4.8, th1/0.52, th2/0.52).
# (ESP's code scales differently: x/2.4, x'/10, th/36deg, th1'/5, th2'/16.)
_SCALE_V = (4.8, 2.0, 0.52, 2.0, 0.52, 2.0)
_SCALE_NV = (4.8, 0.52, 0.52)

# The generalisation test of Gruau et al. (1996) as coded by ESP and NEAT: 5^4 starts from
# v in GRID_VALUES for each of x, x', th1, th1' (th2 = th2' = 0).
GRID_VALUES = (0.05, 0.25, 0.5, 0.75, 0.95)
# v from 0 to 1 would span x in +-2.16 m, x' in +-1.35 m/s, th1 in +-3.6 deg and th1' in
# +-8.6 deg/s (the codes' comments); the grid's v in [0.05, 0.95] stays inside.
_GRID_SCALE = (4.32, 2.70, 0.12566304, 0.30019504)
_GRID_SHIFT = (2.16, 1.35, 0.06283152, 0.15009752)

_JIGGLE_WINDOW = 100  # Gruau et al.: the damping term sums the last 100 time steps.

FITNESSES = ("steps", "damping")


@pytree.dataclass
class Physics:
    """Constants of the cart and poles (leaves, so they may be traced or vmapped).

    Every default is the value of Gomez & Miikkulainen (1999, appendix) and of the
    ``CartPole`` class of ESP's and NEAT's C++, which both take them from Wieland (1991).

    Attributes:
      gravity: g = -9.8 m/s^2 (sign convention of the printed equations; see module doc).
      mass_cart: M = 1.0 kg.
      mass_pole: ``[2]`` m_1 = 0.1 kg, m_2 = 0.01 kg.
      half_length: ``[2]`` l_1 = 0.5 m, l_2 = 0.05 m (half the pole lengths, 1 m and 0.1 m).
      pole_friction: mu_p = 2e-6, hinge friction coefficient (both poles).
      cart_friction: mu_c = 5e-4, cart-track friction coefficient (0.0 in NEAT's code).
      force_mag: 10 N, the force at output +-1.
      dt: 0.01 s, one RK4 step.
      track_limit: 2.4 m, the cart fails beyond +-2.4 m.
      angle_limit: 36 deg = 0.6283 rad, a pole fails beyond it (the codes write 0.628329).
    """

    gravity: jax.Array
    mass_cart: jax.Array
    mass_pole: jax.Array
    half_length: jax.Array
    pole_friction: jax.Array
    cart_friction: jax.Array
    force_mag: jax.Array
    dt: jax.Array
    track_limit: jax.Array
    angle_limit: jax.Array


def physics(**overrides: float) -> Physics:
    """The standard constants (see `Physics`), any of them overridden by keyword."""
    values = {
        "gravity": -9.8,
        "mass_cart": 1.0,
        "mass_pole": (0.1, 0.01),
        "half_length": (0.5, 0.05),
        "pole_friction": 2e-6,
        "cart_friction": 5e-4,
        "force_mag": 10.0,
        "dt": 0.01,
        "track_limit": 2.4,
        "angle_limit": 36.0 * math.pi / 180.0,
    }
    unknown = set(overrides) - set(values)
    if unknown:
        raise TypeError(f"unknown physics constants: {', '.join(sorted(unknown))}")
    values.update(overrides)
    return Physics(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})


def start_state(theta1: float = 0.07) -> jax.Array:
    """The standard start ``[6]``: cart at rest at 0, long pole at ``theta1`` rad (0.07 rad =
    4.01 deg, NEAT's ``CartPole::init``), short pole upright, all velocities 0."""
    return jnp.array([0.0, 0.0, theta1, 0.0, 0.0, 0.0], jnp.float32)


def derivatives(p: Physics, s: jax.Array, force: jax.Array) -> jax.Array:
    """Time derivative ``[6]`` of the state ``s`` ``[6]`` under a constant ``force`` (N).

    Wieland's equations (module docstring), term by term as ESP's ``CartPole::step``.
    """
    xd = s[1]
    th = s[2::2]  # [2] pole angles
    thd = s[3::2]  # [2] pole angular velocities
    m, half = p.mass_pole, p.half_length
    cos, sin = jnp.cos(th), jnp.sin(th)
    ml = m * half
    fric = p.pole_friction * thd / ml  # mu_p th' / (m l)
    f_eff = ml * thd * thd * sin + 0.75 * m * cos * (fric + p.gravity * sin)  # Ft_i
    m_eff = m * (1.0 - 0.75 * cos * cos)  # mt_i
    xdd = (force - p.cart_friction * jnp.sign(xd) + jnp.sum(f_eff)) / (p.mass_cart + jnp.sum(m_eff))
    thdd = -0.75 * (xdd * cos + p.gravity * sin + fric) / half
    return jnp.stack([xd, xdd, thd[0], thdd[0], thd[1], thdd[1]])


def rk4(p: Physics, s: jax.Array, force: jax.Array) -> jax.Array:
    """One classical RK4 step of ``p.dt`` (ESP's and NEAT's ``CartPole::rk4``)."""
    h = p.dt
    k1 = derivatives(p, s, force)
    k2 = derivatives(p, s + 0.5 * h * k1, force)
    k3 = derivatives(p, s + 0.5 * h * k2, force)
    k4 = derivatives(p, s + h * k3, force)
    return s + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def act(p: Physics, s: jax.Array, output: jax.Array) -> jax.Array:
    """One network action: force ``force_mag * clip(output, -1, 1)`` held for two RK4 steps
    (0.02 s; ``CartPole::performAction``)."""
    force = p.force_mag * jnp.clip(output, -1.0, 1.0)
    return rk4(p, rk4(p, s, force), force)


def balanced(p: Physics, s: jax.Array) -> jax.Array:
    """True iff the cart is on the track and both poles are within the angle limit
    (``CartPole::outsideBounds`` negated; False for NaN states)."""
    return (jnp.abs(s[0]) <= p.track_limit) & jnp.all(jnp.abs(s[2::2]) <= p.angle_limit)


def observe(s: jax.Array, *, velocities: bool) -> jax.Array:
    """Network inputs from a state: ``[6]`` scaled state (dpv) or ``[3]`` x, th1, th2 (dpnv),
    with NEAT's scaling (``_SCALE_V`` / ``_SCALE_NV``); no bias input (the genome has B genes)."""
    if velocities:
        return s / jnp.asarray(_SCALE_V, s.dtype)
    return s[0::2] / jnp.asarray(_SCALE_NV, s.dtype)


def jiggle(s: jax.Array) -> jax.Array:
    """``|x| + |x'| + |th1| + |th1'|``, the term of Gruau et al.'s damping sum (raw state,
    as NEAT's ``JIGGLE_STEP``)."""
    return jnp.sum(jnp.abs(s[..., :4]), axis=-1)


def damping_fitness(steps: jax.Array, jiggle_sum: jax.Array) -> jax.Array:
    """Gruau et al. (1996): ``0.1 t/1000 + 0.9 * 0.75 / J`` if ``t >= 100`` else ``0.1 t/1000``.

    Args:
      steps: ``t``, the number of balanced actions.
      jiggle_sum: ``J``, the sum of `jiggle` over the last 100 balanced states.

    Returns:
      The fitness (higher is better). ``J`` is floored at 1e-12 so a (physically unreachable)
      perfectly still trajectory gives a huge finite fitness rather than inf. NEAT's code
      uses ``t > 100`` (one step apart); this follows the paper's ``t < 100 -> f2 = 0``.
    """
    steps = jnp.asarray(steps, jnp.float32)
    f1 = steps / 1000.0
    f2 = jnp.where(steps >= _JIGGLE_WINDOW, 0.75 / jnp.maximum(jiggle_sum, 1e-12), 0.0)
    return 0.1 * f1 + 0.9 * f2


def grid_starts() -> np.ndarray:
    """The 625 start states ``float32[625, 6]`` of the generalisation test.

    ``x = 4.32 v - 2.16``, ``x' = 2.70 v - 1.35``, ``th1 = 0.12566304 v - 0.06283152``,
    ``th1' = 0.30019504 v - 0.15009752`` for v in `GRID_VALUES`, ``th2 = th2' = 0``;
    x varies slowest (the loop order of ESP's ``generalizationTest``).
    """
    v = np.asarray(GRID_VALUES, np.float64)
    axes = [v * a - b for a, b in zip(_GRID_SCALE, _GRID_SHIFT, strict=True)]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
    return np.concatenate([mesh, np.zeros((mesh.shape[0], 2))], axis=1).astype(np.float32)
