"""``eant2 render`` and the drawings with weights (eant2_jax.app.render, draw, netdraw).

* a rollout's states are the task's own for the same key: a gymnax episode has the task's
  return and length to the bit, and each recorded state is the environment's step from the
  one before; the servo's moves give the task's own costs and poses (a step-by-step replay
  of ``Servo.move``);
* the servo arm, a CartPole episode (matplotlib) and a Catch episode (gymnax's visualizer)
  are written as GIFs with the expected number of frames (read back with PIL);
* a file naming a user's task imports nothing; a missing task, an .mp4 without ffmpeg and
  an existing output are one-line errors;
* a network drawing writes each weight of a small network and a colour bar.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import eant2_jax
from eant2_jax import tasks
from eant2_jax.app import draw, netdraw, render
from eant2_jax.app.cli import main
from eant2_jax.app.report_figures import pyplot
from eant2_jax.genomefile import GenomeFile

# Output 1 (push right) = theta + theta_dot (normalised), a little of x: balances CartPole.
BALANCE = "N0/1*1 B*0 N1/4*1 I0*0.1 I1*0.3 I2*2 I3*0.5"


def _frames(path) -> int:
    with Image.open(path) as im:
        assert im.format == "GIF"
        return im.n_frames


def _random_genome(rng, n_in: int, n_out: int) -> eant2_jax.Genome:
    """Each output reads every input and the bias, with fresh random weights; output 0 also
    reads a hidden neuron with a recurrent jumper (so the carried state matters)."""
    genes = []
    for k in range(n_out):
        extra = 1 if k == 0 else 0
        genes.append(f"N{k}/{n_in + 1 + extra}*1")
        genes += [f"I{i}*{rng.normal():.4f}" for i in range(n_in)]
        genes.append(f"B*{rng.normal(scale=0.3):.4f}")
        if extra:
            genes += [f"N{n_out}/2*{rng.normal():.4f}", f"I0*{rng.normal():.4f}",
                      f"R0*{rng.normal():.4f}"]  # fmt: skip
    return eant2_jax.Genome.parse(" ".join(genes))


def _write(path, genome, task_name, options=None, hidden="tanh", output="identity", n_in=None):
    spec = GenomeFile(genome, hidden=hidden, output=output, n_inputs=n_in or genome.n_inputs,
                      task=task_name, task_options=options)  # fmt: skip
    spec.write(path)
    return path


# ------------------------------------------------------------------------ gymnax
@pytest.fixture(scope="module")
def cartpole():
    pytest.importorskip("gymnax")
    return tasks.make("gymnax:CartPole-v1")


@pytest.mark.slow
def test_gymnax_episode_states_are_the_tasks_own(cartpole):
    task, rng = cartpole, np.random.default_rng()
    env, params = task.env, task.env_params
    episode = jax.jit(type(task).episode)  # the task's own, nothing recorded
    for trial in range(3):  # one structure: one compilation of each program
        genome = _random_genome(rng, 4, 2)
        if trial == 0:  # a controller that balances: the whole 500 steps
            genome = genome.with_weights([1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0.1, 0.3, 2, 0.5, 0])
        net = render.network_of(GenomeFile(genome, "tanh", "identity", 4), task)
        key = jax.random.key(int(rng.integers(2**31)))
        ep = render.gymnax_episode(task, net, key)
        ret, length = episode(task, net, key)
        assert (ep.ret, ep.length) == (float(ret), int(length))
        assert ep.states.x.shape == ep.rewards.shape == (ep.length,)
        assert float(ep.rewards.sum()) == ep.ret  # CartPole: 1 per step
        # Each recorded state is the environment's step from the one before, with the
        # recorded action and episodic.rollout's key schedule (float32 rounding: the
        # recording's program and this one fuse the physics differently).
        reset_key, step_key = jax.random.split(key)
        first = env.reset(reset_key, params)[1]
        np.testing.assert_allclose(ep.states.theta[0], first.theta, rtol=1e-6)
        # Steps 0 .. length-2, their rows repeated up to the task's max_steps - 1 so that
        # every trial's step program has one shape (one compilation); only the real rows
        # are compared.
        n = ep.length - 1
        at = np.minimum(np.arange(task.max_steps - 1), max(n - 1, 0))
        keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(step_key, jnp.asarray(at))
        before = jax.tree.map(lambda a, at=at: np.asarray(a)[at], ep.states)
        actions = np.asarray(ep.actions)[at]
        after = jax.vmap(env.step, in_axes=(0, 0, 0, None))(keys, before, actions, params)
        for name in ("x", "x_dot", "theta", "theta_dot"):
            np.testing.assert_allclose(getattr(after[1], name)[:n], getattr(ep.states, name)[1:],
                                       rtol=1e-5, atol=1e-6, err_msg=name)  # fmt: skip
    assert render.gymnax_episode(task, net, key, steps=5).states.theta.shape == (5,)


@pytest.mark.slow
def test_cartpole_episode_is_drawn_with_one_frame_per_step(cartpole, tmp_path):
    net = render.network_of(GenomeFile(eant2_jax.Genome.parse(BALANCE), "tanh", "identity", 4),
                            cartpole)  # fmt: skip
    ep = render.gymnax_episode(cartpole, net, jax.random.key(3), steps=7)
    assert ep.length == 500 and ep.ret == 500.0
    out, png = tmp_path / "cart.gif", tmp_path / "last.png"
    n = draw.gymnax_animation(cartpole, ep, out, frame=png, dpi=40, size=(3, 2))
    assert n == 7 == _frames(out)
    with Image.open(png) as im:
        assert im.format == "PNG"
    with pytest.raises(OSError, match="already exists"):
        draw.gymnax_animation(cartpole, ep, out, dpi=40, size=(3, 2))


@pytest.mark.slow
def test_catch_is_drawn_by_gymnaxs_own_visualizer(tmp_path):
    pytest.importorskip("gymnax")
    task = tasks.make("gymnax:Catch-bsuite")
    assert draw.gymnax_renderer("Catch-bsuite") == "gymnax"
    genome = _random_genome(np.random.default_rng(), 2, task.n_outputs)
    net = render.network_of(GenomeFile(genome, "tanh", "identity", task.n_inputs), task)
    ep = render.gymnax_episode(task, net, jax.random.key(0))
    assert 0 < ep.length <= task.max_steps
    n = draw.gymnax_animation(task, ep, tmp_path / "catch.gif", dpi=30)
    assert n == ep.length == _frames(tmp_path / "catch.gif")


# ------------------------------------------------------------------------ servo
@pytest.fixture(scope="module")
def servo():
    return tasks.make("servo", n_starts=12, moves_per_start=3)


@pytest.mark.slow
def test_servo_moves_are_the_tasks_own(servo):
    task, rng = servo, np.random.default_rng()
    genome = _random_genome(rng, 10, 3)
    net = render.network_of(GenomeFile(genome, "tanh", "identity", 10), task)
    moves = render.servo_moves(task, net, jax.random.key(int(rng.integers(2**31))), starts=12,
                               moves=3)  # fmt: skip
    assert sorted(moves.starts.tolist()) == list(range(12))  # drawn without replacement
    own = jax.jit(lambda t, n: t.start_costs(t.network_policy(n), jnp.zeros_like(n.bias)))
    own = np.asarray(own(task, net))
    # The task's cost from each start (Servo.episode: the mean of its 3 moves); the same
    # moves, their mean taken in another program: float32 rounding (~1e-7 relative).
    np.testing.assert_allclose(moves.cost.mean(axis=1), own[moves.starts], rtol=1e-6, atol=1e-7)
    # A step-by-step replay of the task's own move from the first start, in programs of its
    # own: the network's move rounds a few float32 ulps apart in another program, and the
    # move's substeps carry that into the joint angles (seen: 2.7e-6 rad on a 0.94 rad angle
    # after one move, on a fresh random genome), the marker images and the move cost alike
    # (seen: 2.7e-6 relative cost; 1.2e-6 on an image coordinate of -0.0123). Bounds of 1e-5
    # to 5e-5 hold that rounding.
    s = int(moves.starts[0])
    q, qd, x, h = task.q_start[s], jnp.zeros(3), task.x_start[s], jnp.zeros_like(net.bias)
    policy, move = jax.jit(task.network_policy(net)), jax.jit(task.move)
    for m in range(3):
        dq, h = policy(h, q, x)
        q, qd, x, c = move(q, qd, dq)
        np.testing.assert_allclose(moves.q[0, m + 1], q, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(moves.x[0, m + 1], x, rtol=1e-5, atol=5e-5)
        np.testing.assert_allclose(moves.cost[0, m], c, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="--starts must be in"):
        render.servo_moves(task, net, jax.random.key(0), starts=13, moves=1)


@pytest.mark.slow
def test_render_command_writes_the_servo_arm(tmp_path, capsys):
    genome = _random_genome(np.random.default_rng(0), 10, 3)
    src = _write(tmp_path / "arm.genome", genome, "servo", {"n_starts": 8}, n_in=10)
    out, png = tmp_path / "arm.gif", tmp_path / "arm.png"
    # 2 starts of 1 move: 2 * (1 + 1) = 4 frames (a count of starts * moves + 1, 3, would
    # be wrong); few frames, as drawing each one is most of this test's time.
    argv = ["render", str(src), "--starts", "2", "--steps", "1", "--seed", "4", "--out",
            str(out), "--frame", str(png)]  # fmt: skip
    assert main(argv) == 0
    assert _frames(out) == 2 * (1 + 1)  # each start pose, then each move
    printed = capsys.readouterr().out
    assert "servo: starts" in printed and f"animation: {out} (4 frames)" in printed
    first = out.read_bytes()
    assert main(argv) == 2  # exists: refused without --force
    assert "exists; not overwriting" in capsys.readouterr().err
    assert main([*argv, "--force"]) == 0
    assert out.read_bytes() == first  # the same key, the same animation


# ------------------------------------------------------------------------ trust, errors
def test_a_user_task_named_by_a_file_is_never_imported(tmp_path, capsys):
    marker = tmp_path / "imported"
    user = tmp_path / "user_task.py"
    user.write_text(f"open({str(marker)!r}, 'w').close()\ndef make_task():\n    raise SystemExit\n")
    genome = eant2_jax.Genome.parse(BALANCE)
    src = _write(tmp_path / "u.genome", genome, f"{user}:make_task")
    assert main(["render", str(src), "--out", str(tmp_path / "u.gif")]) == 2
    err = capsys.readouterr().err
    assert "is user code" in err and "--task SPEC" in err and err.count("\n") == 1
    assert not marker.exists()
    bare = tmp_path / "bare.genome"
    bare.write_text(BALANCE + "\n")  # no header: no task recorded
    assert main(["render", str(bare), "--out", str(tmp_path / "b.gif")]) == 2
    assert "no task recorded" in capsys.readouterr().err
    assert not (tmp_path / "u.gif").exists() and not (tmp_path / "b.gif").exists()


def test_format_errors_are_one_line(tmp_path):
    from matplotlib import animation

    with pytest.raises(ValueError, match="is a .gif or an .mp4"):
        draw.check_format(tmp_path / "x.avi")
    if not animation.writers.is_available("ffmpeg"):
        with pytest.raises(ValueError, match="needs ffmpeg"):
            draw.check_format(tmp_path / "x.mp4")
    draw.check_format(tmp_path / "x.gif")


# ------------------------------------------------------------------------ network drawing
@pytest.mark.slow
def test_network_drawing_shows_weights_and_a_colour_bar(tmp_path):
    genome = eant2_jax.Genome.parse("N0/3*1.5 N1/2*0.5 I0*1.25 R1*-0.75 I1*-2 B*0.3")
    fig = netdraw.network_figure(genome, title="t")
    try:
        texts = {t.get_text() for ax in fig.axes for t in ax.texts}
        for w in (0.5, 1.25, -0.75, -2.0, 0.3):
            assert f"{w:.2g}" in texts
        assert "×1.5" in texts  # the output neuron's own weight
        assert len(fig.axes) == 2  # the network and its colour bar
        legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert "recurrent jumper" in legend and "width, colour: weight" in legend
    finally:
        pyplot().close(fig)
    path = netdraw.draw_network(genome, tmp_path / "sub" / "n.png")
    with Image.open(path) as im:
        assert im.format == "PNG"


@pytest.mark.slow
def test_a_run_directory_plays_its_champion_on_its_own_task(tmp_path, capsys):
    out = tmp_path / "xor"
    config = eant2_jax.EANT2Config(
        population=2, exploit=eant2_jax.ExploitConfig(max_iters=5, pruner="none")
    )  # no pruning: a cheaper program; the test reads the run directory, not the run
    eant2_jax.run(tasks.make("xor"), key=jax.random.key(0), generations=0, config=config,
                  out=str(out))  # fmt: skip
    spec, name = render.read_source(str(out))
    assert (spec.task, name) == ("xor", "xor/best.genome") and spec.has_header
    assert render.task_kind(render.task_of(spec, str(out))) is None
    assert main(["render", str(out), "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert 'draws the servo task and gymnax environments, not "xor"' in err
    assert err.count("\n") == 1
    pytest.importorskip("gymnax")
    assert main(["render", str(out), "--task", "gymnax:CartPole-v1"]) == 2
    err = capsys.readouterr().err
    assert "the genome does not fit" in err and err.count("\n") == 1
    assert not (tmp_path / "x.gif").exists()
