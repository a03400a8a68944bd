"""The serial-chain kinematics kernel (``eant2_jax.kernels.kinematics``) against MJX and
MuJoCo C.

* Against ``mjx.kinematics`` (the code it replaces), float32 on the CPU, for the servo arm
  and for random chains (random link offsets and orientations, hinge anchors and axes,
  ``qpos0``, site frames) at random joint angles: the same formulas in the same order, MJX's
  dot products of 3 terms written as sums (which XLA's dot rounds its own way on a CPU), so
  equal to float32 rounding: at most ``6e-7`` plus ``2e-6`` relative apart (entries of O(1),
  float32 eps 1.2e-7: 5 units in the last place; the largest seen, after 5 links, 4.8e-7 on
  an anchor at 1.13 m and 4.0e-7 on an axis entry near 0).
* Against MuJoCo C's ``mj_kinematics`` (float64): ``2e-5`` absolute on positions (metres)
  and rotation entries: float32 rounding (~6e-8 relative) through 2-5 links of O(1) m and
  angles up to 7 rad; largest seen about 2e-6.
"""

from __future__ import annotations

import functools
import subprocess
import sys

import jax
import mujoco
import numpy as np
import pytest

from eant2_jax.kernels import kinematics as kin
from eant2_jax.tasks import servo_scene as scene


def _random_chain_xml(rng: np.random.Generator, links: int) -> str:
    """A chain of ``links`` hinged bodies with random frames, anchors, axes and ``ref``."""

    def vec(scale):
        return " ".join(f"{v:.6f}" for v in rng.normal(scale=scale, size=3))

    def quat():
        q = rng.normal(size=4)
        return " ".join(f"{v:.6f}" for v in q / np.linalg.norm(q))

    body = f'<site name="tip" pos="{vec(0.2)}" quat="{quat()}"/>'
    for i in reversed(range(links)):
        body = (
            f'<body name="b{i}" pos="{vec(0.4)}" quat="{quat()}">'
            f'<joint name="j{i}" type="hinge" pos="{vec(0.1)}" axis="{vec(1.0)}" '
            f'ref="{rng.uniform(-1, 1):.4f}"/>'
            f'<geom type="sphere" size="0.01" mass="0.1"/>{body}</body>'
        )
    return f"<mujoco><worldbody>{body}</worldbody></mujoco>"


def _models(seed: int):
    rng = np.random.default_rng(seed)
    mj, site, _ = scene.stripped_arm()
    yield "servo arm", mj, site
    for links in (1, 2, 5):
        m = mujoco.MjModel.from_xml_string(_random_chain_xml(rng, links))
        yield f"random chain of {links}", m, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "tip")


@functools.partial(jax.jit, static_argnums=1)
@functools.partial(jax.vmap, in_axes=(None, None, 0))
def _mjx_kinematics(model, site: int, q):
    """MJX's poses of ``model`` at the joint angles ``q`` (the model an argument: one
    program for the models of one shape, the random chains of both seeds)."""
    from eant2_jax.tasks.mjx_quiet import mjx

    with jax.numpy_rank_promotion("allow"), jax.default_matmul_precision("highest"):
        d = mjx.kinematics(model, mjx.make_data(model).replace(qpos=q))
    return d.xanchor, d.xaxis, d.site_xpos[site], d.site_xmat[site]


# Our forward pass, compiled and batched over joint angles, the chain an argument (as a
# task holds it: data, not a constant): one program per chain shape, shared by both seeds.
_forward = jax.jit(jax.vmap(kin.forward, in_axes=(None, 0)))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_forward_equals_mjx_kinematics_and_mujoco_c(seed):
    from eant2_jax.tasks.mjx_quiet import mjx

    rng = np.random.default_rng(100 + seed)
    for name, mj, site in _models(seed):
        chain = kin.Chain.from_model(mj, site)
        model = mjx.put_model(mj)
        qs = rng.uniform(-7.0, 7.0, size=(64, mj.nq)).astype(np.float32)

        ours = tuple(_forward(chain, qs))
        ref = _mjx_kinematics(model, site, qs)
        for field, a, b in zip(kin.ChainPose._fields, ours, ref, strict=True):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_allclose(a, b, rtol=2e-6, atol=6e-7, err_msg=f"{name}: {field}")
        d = mujoco.MjData(mj)
        for i, q in enumerate(qs[:16]):
            d.qpos[:] = q
            mujoco.mj_kinematics(mj, d)
            want = (d.xanchor, d.xaxis, d.site_xpos[site], d.site_xmat[site].reshape(3, 3))
            for field, a, b in zip(kin.ChainPose._fields, ours, want, strict=True):
                np.testing.assert_allclose(
                    np.asarray(a[i]), b, atol=2e-5, err_msg=f"{name}: {field} vs MuJoCo C"
                )


@pytest.mark.slow
def test_a_long_chain_passed_as_an_argument_matches_mujoco_c():
    """A chain of 8 links as an argument of the compiled, batched `forward` (a task's chain
    is data, not a constant): the scan over links keeps its program one link's (written out
    and batched, XLA took 21 s to compile 5 links on a 2-core CPU), and its poses are MuJoCo
    C's."""
    rng = np.random.default_rng(7)
    mj = mujoco.MjModel.from_xml_string(_random_chain_xml(rng, 8))
    site = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, "tip")
    chain = kin.Chain.from_model(mj, site)
    qs = rng.uniform(-7.0, 7.0, size=(16, mj.nq)).astype(np.float32)
    ours = _forward(chain, qs)
    d = mujoco.MjData(mj)
    for i, q in enumerate(qs):
        d.qpos[:] = q
        mujoco.mj_kinematics(mj, d)
        want = (d.xanchor, d.xaxis, d.site_xpos[site], d.site_xmat[site].reshape(3, 3))
        for field, a, b in zip(kin.ChainPose._fields, ours, want, strict=True):
            np.testing.assert_allclose(np.asarray(a[i]), b, atol=2e-5, err_msg=field)


def test_from_model_names_what_is_not_a_chain():
    def model(xml):
        return mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{xml}</worldbody></mujoco>")

    g = '<geom type="sphere" size="0.01" mass="0.1"/>'
    cases = [
        (f'<body><joint type="ball"/>{g}<site name="s"/></body>', "exactly one hinge"),
        (
            f'<body><joint type="hinge"/><joint type="hinge"/>{g}<site name="s"/></body>',
            "exactly one hinge",
        ),
        (
            f'<body><joint type="hinge"/>{g}<body>{g}<body><joint type="hinge"/>{g}'
            '<site name="s"/></body></body></body>',
            "without a joint lies between",
        ),
        (f'<site name="s"/><body><joint type="hinge"/>{g}</body>', "no joint"),
        (
            f'<body><joint type="hinge"/>{g}<site name="s"/></body>'
            f'<body><joint type="hinge"/>{g}</body>',
            "exactly the chain's hinges",
        ),
    ]
    for xml, match in cases:
        with pytest.raises(ValueError, match=match):
            kin.Chain.from_model(model(xml), 0)
    with pytest.raises(ValueError, match="site 3 is not in"):
        kin.Chain.from_model(model(cases[0][0]), 3)


@pytest.mark.slow
def test_a_fixed_base_is_composed_on_the_host():
    """Fixed bodies before the first hinge become the chain's base pose (float64 on the
    host, so float32 MJX may differ in the last bits: compared with MuJoCo C)."""
    xml = (
        '<mujoco><worldbody><body pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 0.2"><body pos="0 0 0.5"'
        ' euler="0.3 0 1"><body pos="0.4 0 0"><joint type="hinge" axis="0 1 0"/>'
        '<geom type="sphere" size="0.01" mass="0.1"/><site name="s" pos="0.2 0 0"/></body>'
        "</body></body></worldbody></mujoco>"
    )
    mj = mujoco.MjModel.from_xml_string(xml)
    chain = kin.Chain.from_model(mj, 0)
    d = mujoco.MjData(mj)
    for q in (-2.0, 0.0, 0.7):
        d.qpos[:] = q
        mujoco.mj_kinematics(mj, d)
        pose = kin.forward(chain, np.array([q], np.float32))
        np.testing.assert_allclose(np.asarray(pose.site_xpos), d.site_xpos[0], atol=2e-6)
        np.testing.assert_allclose(
            np.asarray(pose.site_xmat), d.site_xmat[0].reshape(3, 3), atol=2e-6
        )


@pytest.mark.slow
def test_kinematic_servo_never_imports_mjx():
    """The kinematic servo task (the default) builds and scores without importing MJX; the
    dynamic mode imports it. A fresh process: other tests here import MJX."""
    code = (
        "import sys\n"
        "from eant2_jax import tasks\n"
        "t = tasks.make('servo', n_starts=8)\n"
        "t.baselines()\n"
        "assert 'mujoco.mjx' not in sys.modules, 'kinematic servo imported MJX'\n"
        "tasks.make('servo', mode='dynamic', n_starts=8)\n"
        "assert 'mujoco.mjx' in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)
