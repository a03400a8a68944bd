"""Bring your own task: the protocol's checks, task specs, resuming user tasks, noisy tasks,
the progress reporter, and the worked example of docs/tasks-custom.md.

* every protocol mistake is one :class:`TaskError` line, the same from ``optimize`` and
  ``run`` (which writes nothing then);
* ``tasks.make`` builds tasks from ``file.py[:factory]`` and ``module:factory`` specs and
  remembers them, so a run directory records the spec and ``resume`` needs no task;
* the command line runs a task from a user's file and resumes it;
* a noisy task's reported cost is its cost on fresh episodes, not the search's best draw;
* :class:`ProgressReporter` announces compilation before the first generation line.
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from docs_outputs import same

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, pytree, tasks
from eant2_jax.app.cli import main
from eant2_jax.kernels import network as kn
from eant2_jax.rundir import GENERATIONS, RunDirError
from eant2_jax.tasks import TaskError, map_networks

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "point_mass.py"
XOR_GENOME = "N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"
TINY = EANT2Config(population=3, exploit=ExploitConfig(max_iters=20, pruner="none"))


@pytree.dataclass
class Constant:
    """A deterministic task: cost = sum of squared outputs on one input of ones."""

    n_inputs: int = pytree.field(pytree_node=False, default=2)
    n_outputs: int = pytree.field(pytree_node=False, default=1)
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="identity")

    def cost(self, key, nets):
        del key

        def one(net):
            y, _ = kn.step(net, jnp.ones(self.n_inputs), jnp.zeros(net.bias.shape))
            return jnp.sum(jnp.square(y - 1.0))

        return map_networks(one, nets)


class Plain:
    """Every attribute of the protocol, but not a pytree."""

    n_inputs, n_outputs, hidden, output = 2, 1, "tanh", "identity"

    def cost(self, key, nets):
        return jnp.zeros(nets.bias.shape[:-1])


@pytree.dataclass
class WrongShape(Constant):
    def cost(self, key, nets):
        return jnp.zeros(())


@pytree.dataclass
class IntCosts(Constant):
    def cost(self, key, nets):
        return jnp.zeros(nets.bias.shape[:-1], jnp.int32)


@pytree.dataclass
class NoKey(Constant):
    def cost(self, nets):  # forgot the key
        return jnp.zeros(nets.bias.shape[:-1])


@pytree.dataclass
class NoOutput:
    n_inputs: int = pytree.field(pytree_node=False, default=2)
    n_outputs: int = pytree.field(pytree_node=False, default=1)
    hidden: str = pytree.field(pytree_node=False, default="tanh")

    def cost(self, key, nets):
        return jnp.zeros(nets.bias.shape[:-1])


BAD_TASKS = [
    (NoOutput(), "has no output"),
    (Plain(), "not a JAX pytree"),
    (Constant(n_inputs=0), "n_inputs must be an int >= 1"),
    (Constant(n_outputs=1.0), "n_outputs must be an int >= 1"),
    (Constant(hidden="swish"), "hidden: unknown activation 'swish'"),
    (NoKey(), "cost must take (key, nets)"),
    (WrongShape(), "cost returned shape () for networks of batch shape ("),
    (IntCosts(), "cost returned int32 costs"),
]


@pytest.mark.slow
@pytest.mark.parametrize("task,phrase", BAD_TASKS, ids=[type(t).__name__ for t, _ in BAD_TASKS])
def test_protocol_mistakes_are_one_line_and_run_agrees_with_optimize(task, phrase, tmp_path):
    with pytest.raises(TaskError) as opt:
        eant2_jax.optimize("N0/2*1 I0*1 I1*1", task, key=jax.random.key(0), max_iters=2)
    assert phrase in str(opt.value) and "\n" not in str(opt.value)
    out = tmp_path / "run"
    with pytest.raises(TaskError) as run:
        eant2_jax.run(task, key=jax.random.key(0), config=TINY, generations=0, out=str(out))
    assert phrase in str(run.value)
    # What cost returns is seen when it is traced, after the run directory is made.
    if "cost returned" not in phrase:
        assert not out.exists()


def _write_task_file(path: Path, factory: str = "make_task") -> Path:
    path.write_text(
        "from eant2_jax import pytree\n"
        "import jax.numpy as jnp\n"
        "from eant2_jax.kernels import network as kn\n"
        "from eant2_jax.tasks import map_networks\n\n"
        "@pytree.dataclass\n"
        "class Reach:\n"
        "    target: float = 0.5\n"
        "    n_inputs: int = pytree.field(pytree_node=False, default=1)\n"
        "    n_outputs: int = pytree.field(pytree_node=False, default=1)\n"
        "    hidden: str = pytree.field(pytree_node=False, default='tanh')\n"
        "    output: str = pytree.field(pytree_node=False, default='identity')\n\n"
        "    def cost(self, key, nets):\n"
        "        def one(net):\n"
        "            y, _ = kn.step(net, jnp.ones(1), jnp.zeros(net.bias.shape))\n"
        "            return jnp.square(y[0] - self.target)\n"
        "        return map_networks(one, nets)\n\n"
        f"def {factory}(*, target=0.5):\n"
        "    return Reach(target=float(target))\n"
    )
    return path


def test_make_from_a_file_and_a_module_remembers_the_spec(tmp_path, monkeypatch):
    f = _write_task_file(tmp_path / "reach.py")
    task = tasks.make(str(f), target=0.25)
    assert task.target == 0.25
    assert tasks.spec_of(task) == {"task": f"{f}:make_task", "task_options": {"target": 0.25}}
    monkeypatch.chdir(tmp_path)  # a relative path is recorded as an absolute one
    assert tasks.spec_of(tasks.make("reach.py:make_task"))["task"] == f"{f}:make_task"
    monkeypatch.syspath_prepend(str(tmp_path))
    m = tasks.make("reach:make_task")
    assert tasks.spec_of(m) == {"task": "reach:make_task", "task_options": {}}
    assert tasks.spec_of(Constant()) is None  # not built by make


@pytest.mark.parametrize(
    "spec,phrase",
    [
        ("nope", "unknown task 'nope'"),
        ("missing.py", "no such file"),
        ("reach.py:other", "defines no 'other'"),
        ("no_such_module_xyz:make", "cannot import module 'no_such_module_xyz'"),
        ("reach.py:Reach", "bad options for task 'reach.py:Reach'"),
        ("gymnax:", "name the task after 'gymnax:'"),
    ],
)
def test_bad_specs_are_one_line(spec, phrase, tmp_path, monkeypatch):
    _write_task_file(tmp_path / "reach.py")
    monkeypatch.chdir(tmp_path)
    options = {"bogus": 1.0} if spec.endswith(":Reach") else {}
    with pytest.raises(ValueError) as e:
        tasks.make(spec, **options)
    assert phrase in str(e.value) and "\n" not in str(e.value)


def test_a_factory_that_returns_no_task(tmp_path):
    f = tmp_path / "bad.py"
    f.write_text("def make_task():\n    return 42\n")
    with pytest.raises(TaskError, match=r"task '.*bad.py' has no n_inputs"):
        tasks.make(str(f))


@pytest.mark.slow  # the command line's resume of a user task, named again: the fast lane
def test_python_run_of_a_made_task_resumes_with_the_task_named_again(user_dir, tmp_path):
    """A user's task is code: resume rebuilds it only when the caller names it again
    (docs/reliability.md, "Trust"), and then it must be the recorded one."""
    f = user_dir / "reach_cli.py"
    out = tmp_path / "run"
    task = tasks.make(f"{f}:reach_task")
    eant2_jax.run(task, key=jax.random.key(0), config=TINY, generations=0, out=str(out))
    assert json.loads((out / "config.json").read_text())["task"] == f"{f}:reach_task"
    with pytest.raises(RunDirError, match="is user code"):
        eant2_jax.resume(str(out), generations=1)
    res = eant2_jax.resume(str(out), tasks.make(f"{f}:reach_task"), generations=1)
    assert [g.generation for g in res.generations] == [0, 1]
    # A task built by hand is recorded by its type; resume then says what to do. (The same
    # task class as above, built without `make`: the run reuses its compiled programs.)
    other = tmp_path / "by-hand"
    by_hand = type(task)()
    assert tasks.spec_of(by_hand) is None
    eant2_jax.run(by_hand, key=jax.random.key(0), config=TINY, generations=0, out=str(other))
    with pytest.raises(RunDirError, match=r"records no task spec \(its task, .*Reach, was"):
        eant2_jax.resume(str(other), generations=1)


def _main(argv, capsys, monkeypatch):
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    monkeypatch.setattr(sys, "path", list(sys.path))  # the CLI appends the working directory
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


CLI_TINY = ["--population", "3", "--max-iters", "20", "--seed", "2", "--no-prune"]


@pytest.fixture(scope="module")
def user_dir(tmp_path_factory):
    """One folder holding the user's task file: its runs share compiled programs."""
    d = tmp_path_factory.mktemp("user")
    _write_task_file(d / "reach_cli.py", factory="reach_task")
    return d


@pytest.mark.slow
@pytest.mark.parametrize(
    "form", ["--task-file", "positional", pytest.param("module", marks=pytest.mark.slow)]
)
def test_cli_runs_a_task_from_a_user_file_and_resumes(
    form, user_dir, tmp_path, capsys, monkeypatch
):
    f = user_dir / "reach_cli.py"
    monkeypatch.chdir(user_dir)
    monkeypatch.delitem(sys.modules, "reach_cli", raising=False)
    spec = {
        "--task-file": ["--task-file", "reach_cli.py:reach_task"],
        "positional": ["reach_cli.py:reach_task"],
        "module": ["reach_cli:reach_task"],
    }[form]
    out = tmp_path / "runs" / "r"
    argv = ["run", *spec, "--generations", "1", *CLI_TINY, "--task-option", "target=0.25"]
    rc, stdout, err = _main([*argv, "--out", str(out)], capsys, monkeypatch)
    assert rc == 0, err
    meta = json.loads((out / "config.json").read_text())
    want = "reach_cli:reach_task" if form == "module" else f"{f}:reach_task"
    assert (meta["task"], meta["task_options"]) == (want, {"target": 0.25})
    if form != "module":
        monkeypatch.chdir(tmp_path)  # a file spec resumes from anywhere
    # The task is the user's code: named again to resume (a file by its path, from anywhere).
    rc, _, err = _main(["resume", str(out), "--generations", "2"], capsys, monkeypatch)
    assert rc == 2 and "is user code" in err and "--task SPEC" in err
    named = "reach_cli:reach_task" if form == "module" else f"{f}:reach_task"
    argv = ["resume", str(out), "--generations", "2", "--task", named]
    rc, stdout, err = _main(argv, capsys, monkeypatch)
    assert rc == 0, err
    lines = (out / GENERATIONS).read_text().splitlines()
    assert [json.loads(x)["generation"] for x in lines] == [0, 1, 2]
    assert f"run directory: {out}" in stdout


def test_cli_task_spec_errors_are_one_line(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    for argv, phrase in [
        (["run"], "name a task"),
        (["run", "xor", "--task-file", "x.py"], "not both"),
        (["run", "--task-file", "x.txt"], "PATH.py[:FACTORY]"),
        (["run", "--task-file", "missing.py"], "no such file"),
    ]:
        rc, _, err = _main([*argv, "--out", str(out)], capsys, monkeypatch)
        lines = [x for x in err.splitlines() if x.strip()]
        assert rc == 2 and len(lines) == 1 and lines[0].startswith("eant2: error: "), lines
        assert phrase in lines[0], lines
        assert not out.exists()


@pytree.dataclass
class Coin:
    """A noisy task whose cost is one uniform draw of its key, whatever the network."""

    n_inputs: int = pytree.field(pytree_node=False, default=2)
    n_outputs: int = pytree.field(pytree_node=False, default=1)
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="identity")
    noisy: bool = pytree.field(pytree_node=False, default=True)

    def cost(self, key, nets):
        return jnp.broadcast_to(jax.random.uniform(key), nets.bias.shape[:-1])


@pytest.mark.slow
@pytest.mark.parametrize("noisy", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_noisy_costs_are_reevaluated_on_fresh_episodes(noisy):
    """Legacy settings (``recommend="best"``, ``rescore=1``): one fresh draw, of the key
    ``split(key, 3)[2]``, one more evaluation."""
    key = jax.random.key(3)
    # No pruner: Coin's cost ignores the network (and the program compiles faster).
    config = ExploitConfig(max_iters=30, patience=1000, recommend="best", rescore=1, pruner="none")
    res = eant2_jax.tuning.tune(
        [eant2_jax.Genome.parse(XOR_GENOME)], Coin(noisy=noisy), key=key, config=config
    )
    # The search keeps the lowest of 30 draws: optimistic.
    assert res.search_costs[0] < 0.2
    engine_evals = int(res.history.evaluations[-1, 0])
    assert res.picked == ["best"]
    if noisy:
        fresh = float(jax.random.uniform(jax.random.split(key, 3)[2]))
        assert res.costs[0] == pytest.approx(fresh, rel=1e-6)
        assert res.evaluations[0] == engine_evals + 1
    else:
        assert res.costs == res.search_costs and res.evaluations[0] == engine_evals


@pytest.mark.slow
@pytest.mark.parametrize("ahead", [False, True])
def test_default_rescoring_averages_fresh_draws_of_both_points(monkeypatch, ahead):
    """Default settings: the best point and the mean are each scored on ``rescore`` = 4
    fresh draws (keys ``split(split(key, 3)[2], 4)``), averaged; the evaluations count both
    candidates' draws; Coin's cost ignores the network, so the tie keeps the best point.
    ``ahead``: the program compiled in a background thread (as on an accelerator; joined
    at once here) is the one called, with the same result."""
    made = []

    class Spy(eant2_jax.rescoring.Rescorer):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            if self.ahead is not None:  # no two programs at once on a CPU
                self.ahead.get()
            made.append(self)

    monkeypatch.setattr(eant2_jax.rescoring, "Rescorer", Spy)
    monkeypatch.setattr(eant2_jax.programs, "ahead_enabled", lambda: ahead)
    monkeypatch.setattr(eant2_jax.programs.REGISTRY, "ahead", {})
    key = jax.random.key(3)
    config = ExploitConfig(max_iters=30, patience=1000, pruner="none")  # as above
    assert (config.recommend, config.rescore) == ("both", 4)
    res = eant2_jax.tuning.tune([eant2_jax.Genome.parse(XOR_GENOME)], Coin(), key=key,
                                config=config)  # fmt: skip
    keys = jax.random.split(jax.random.split(key, 3)[2], 4)
    want = float(np.mean([float(jax.random.uniform(k)) for k in keys]))
    assert res.costs[0] == pytest.approx(want, rel=1e-6)
    assert res.evaluations[0] == int(res.history.evaluations[-1, 0]) + 2 * 4
    assert res.picked == ["best"]
    assert len(made) == 1 and made[0].used_ahead is ahead
    # The next tuning of the same bucket reuses the program compiled ahead.
    assert len(eant2_jax.programs.REGISTRY.ahead) == int(ahead)
    again = eant2_jax.tuning.tune([eant2_jax.Genome.parse(XOR_GENOME)], Coin(),
                                  key=jax.random.key(4), config=config)  # fmt: skip
    assert len(eant2_jax.programs.REGISTRY.ahead) == int(ahead) and made[1].used_ahead is ahead
    assert again.costs[0] != res.costs[0]  # other keys, other draws


def test_rescoring_keeps_the_point_of_lower_fresh_cost():
    """`rescore`: per structure the candidate of lower fresh cost (a tie keeps the best
    point); "mean" scores only the mean; a structure with no finite cost, and the network
    that passed a solution test, keep their best point."""
    from eant2_jax.rescoring import rescore

    g = eant2_jax.Genome.parse(XOR_GENOME)
    n = g.n_params
    mask = np.ones((4, n), bool)
    mean = np.full((4, n), 0.25)
    tuned = [g, g, g, g]
    calls = []

    def rescorer(fresh):
        def score(genomes):
            calls.append(len(genomes))
            return np.asarray(fresh[: len(genomes)], np.float64)

        return score

    costs = [1.0, 1.0, float("inf"), 1.0]
    # candidates, "both": 0 best, 0 mean, 1 best, 1 mean, 2 best (inf), 3 best (solution)
    out, new, evals, picked = rescore(
        [g] * 4, tuned, costs, [10] * 4, mean, mask, 3, ExploitConfig(rescore=3),
        rescorer([0.5, 0.4, 0.3, 0.3, 0.1, 0.2]),
    )  # fmt: skip
    assert picked == ["mean", "best", "best", "best"]
    assert new == [pytest.approx(0.4), pytest.approx(0.3), float("inf"), pytest.approx(0.2)]
    assert evals == [16, 16, 13, 13]
    assert np.allclose([gene.weight for gene in out[0].genes], 0.25) and out[1] is g and out[3] is g
    out, new, evals, picked = rescore(
        [g] * 4, tuned, costs, [10] * 4, mean, mask, 3, ExploitConfig(recommend="mean"),
        rescorer([0.9, 0.3, 0.1, 0.2]),
    )  # fmt: skip
    assert picked == ["mean", "mean", "best", "best"] and evals == [14, 14, 14, 14]
    assert calls == [6, 4]


@pytest.mark.slow
def test_progress_reporter_announces_compilation(user_dir, monkeypatch):
    from eant2_jax import programs

    monkeypatch.setattr(programs.REGISTRY, "ran", set())  # as in a fresh process
    stream = io.StringIO()
    # The run of the user's task above (its programs, if this process compiled them, are
    # reused: the announcement follows what ran in this process, not the jit cache).
    eant2_jax.run(
        tasks.make(f"{user_dir / 'reach_cli.py'}:reach_task"),
        key=jax.random.key(0),
        config=TINY,
        generations=0,
        callback=eant2_jax.ProgressReporter(0, stream=stream, header="hello", live=False),
    )
    lines = stream.getvalue().splitlines()
    assert lines[0] == "hello"
    assert re.fullmatch(
        r"gen 0/0: compiling the exploitation program \(\d+ structures, \d+ genes, depth \d+, "
        r"\d+ candidates\)\.\.\.",
        lines[1],
    )
    assert len(lines) == 3
    assert re.fullmatch(
        r"gen 0/0 \| best \S+ \| mean \S+ ± \S+ \| size \d+ \(1 neurons\) \| pruned 0/0 \| "
        r"[\d,]+ evals, "
        r"[\d,]+/s \| \d+\.\d s",
        lines[2],
    )


def test_the_docs_show_the_example_file_verbatim():
    doc = (ROOT / "docs" / "tasks-custom.md").read_text()
    body = EXAMPLE.read_text()
    start = body.index("import jax")
    end = body.index('\n\nif __name__ == "__main__":')
    assert body[start:end] in doc


@pytest.mark.slow
def test_the_docs_example_prints_what_the_docs_show():
    """``python docs/examples/point_mass.py`` prints the output shown in the docs (times
    masked)."""
    proc = subprocess.run(
        [sys.executable, str(EXAMPLE)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = (ROOT / "docs" / "tasks-custom.md").read_text()
    shown = doc.split("<!-- output of docs/examples/point_mass.py -->\n```text\n")[1]
    shown = shown.split("```")[0]
    assert same(proc.stdout, shown), proc.stdout  # times masked by docs_outputs.mask
