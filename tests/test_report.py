"""Reports: runs of different tasks or configurations are refused unless allowed, the
reference arm is named, and the figures carry legends, integer axes and caps.

The run directories are written by hand (RunDir and GenerationRecord, as the loop writes
them), so no test here runs EANT2.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from eant2_jax.app import netdraw
from eant2_jax.app import report as rp
from eant2_jax.app.cli import main
from eant2_jax.config import EANT2Config, ExploitConfig
from eant2_jax.genome import Genome
from eant2_jax.loop import GenerationRecord
from eant2_jax.rundir import RunDir

GENOME = "N0/3*1.0 N1/2*0.5 I0*1 I1*-2 B*0.1 I2*0.3"


def make_run(
    path: Path,
    *,
    task: str = "xor",
    pruner: str = "covariance",
    population: int = 20,
    generations: int = 3,
    done: int | None = None,
    seed: int = 0,
    target_cost: float | None = None,
    options: dict | None = None,
) -> str:
    """A run directory with ``done`` (default: all) generations of made-up records."""
    config = EANT2Config(
        population=population, target_cost=target_cost, exploit=ExploitConfig(pruner=pruner)
    )
    meta = {"task": task, "task_options": options or {}, "seed": seed, "key": [0, 0]}
    rng = np.random.default_rng(seed + len(pruner))
    cost = 1.0
    # A consistent directory (the checks of resume and report pass): each checkpoint's state
    # agrees with its generation record.
    with RunDir.create(
        path, {**meta, "generations": generations, "config": config.to_dict()}
    ) as rd:
        for g in range(generations + 1 if done is None else done):
            cost *= rng.uniform(0.5, 0.9)
            rec = GenerationRecord(g, cost, 5, 5.0, 2, 100 * (g + 1), 1.0, 0, 0, population, 4,
                                   1.0, str(Genome.parse(GENOME)))  # fmt: skip
            state = {"generation": g, "population": [{"genome": GENOME, "cost": cost}],
                     "next_id": 3, "evaluations": 100 * (g + 1), "key": [0, 0]}  # fmt: skip
            rd.commit([rec.to_json()], [], GENOME, state)
    return str(path)


def _cli(argv, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    monkeypatch.chdir(tmp_path)
    rc = main(argv)
    return rc, *capsys.readouterr()


@pytest.mark.slow
def test_report_of_two_tasks_exits_2_with_one_line(tmp_path, capsys, monkeypatch):
    a = make_run(tmp_path / "a", task="xor")
    b = make_run(tmp_path / "b", task="dpv", pruner="none")
    out = tmp_path / "rep"
    rc, stdout, stderr = _cli(["report", a, b, "--out", str(out)], capsys, monkeypatch, tmp_path)
    assert rc == 2 and stdout == ""
    assert stderr.count("\n") == 1 and stderr.startswith("eant2: error: runs differ in task:")
    assert '"xor"' in stderr and '"dpv"' in stderr and "--allow-mixed" in stderr
    assert not out.exists()  # a refused report writes nothing
    rc, _, stderr = _cli(["report", a, b, "--out", str(out), "--allow-mixed"], capsys,
                         monkeypatch, tmp_path)  # fmt: skip
    assert rc == 0, stderr
    text = (out / "report.md").read_text()
    assert "Task: dpv, xor" in text and "**Mixed runs**" in text and "differ in task" in text


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"population": 6}, "population"),
        ({"generations": 30}, "generations"),
        ({"options": {"hidden": "sigmoid"}}, "task_options"),
    ],
)
def test_different_configs_are_refused(tmp_path, change, field):
    a = make_run(tmp_path / "a")
    b = make_run(tmp_path / "b", pruner="none", **change)
    with pytest.raises(rp.MixedRunsError, match=f"runs differ in {field}:"):
        rp.report([a, b], tmp_path / "rep")
    assert not (tmp_path / "rep").exists()


@pytest.mark.slow
def test_arms_differing_in_pruning_and_seed_only_are_compared(tmp_path):
    dirs = [make_run(tmp_path / f"{p}-{s}", pruner=p, seed=s)
            for p in ("covariance", "none") for s in (0, 1)]  # fmt: skip
    text = rp.report(dirs, tmp_path / "rep").read_text()
    assert "Reference arm: `none` (no pruning)" in text and "**Mixed" not in text
    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert summary["covariance"]["p_fitness"] is not None


@pytest.mark.slow
def test_reference_arm_is_named_or_absent(tmp_path):
    dirs = [make_run(tmp_path / f"{p}-{s}", pruner=p, seed=s)
            for p in ("covariance", "obs") for s in (0, 1)]  # fmt: skip
    text = rp.report(dirs, tmp_path / "r1").read_text()
    assert "without pruning" not in text.replace("no arm without pruning", "")
    assert "No p-values or size reductions: there is no reference arm" in text
    text = rp.report(dirs, tmp_path / "r2", reference="obs").read_text()
    assert "Reference arm: `obs`. p-values" in text
    with pytest.raises(ValueError, match="no arm 'none' to compare against; arms: covariance"):
        rp.report(dirs, tmp_path / "r3", reference="none")


def test_fitness_figure_legend_axes_and_caps(tmp_path):
    dirs = [
        make_run(tmp_path / "a", pruner="covariance", generations=7, target_cost=0.05),
        make_run(tmp_path / "b", pruner="none", generations=7, done=4, target_cost=0.05),
    ]
    runs = rp.load_runs(dirs)
    fig = rp.fitness_figure(runs, ["covariance", "none"])
    fit, size = fig.axes
    labels = [t.get_text() for t in fit.get_legend().get_texts()]
    assert labels == ["covariance (mean of 1)", "none (mean of 1)", "target",
                      "budget (7 generations)"]  # fmt: skip
    assert [t.get_text() for t in size.get_legend().get_texts()][-1] == "budget (7 generations)"
    target = [line for line in fit.lines if line.get_label() == "target"][0]
    assert target.get_ydata()[0] == -0.05
    for ax in fig.axes:  # whole generations only
        ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
        assert ticks and all(float(t).is_integer() for t in ticks)
    means = [line for line in fit.lines if "mean" in line.get_label()]
    styles = {(line.get_linestyle(), line.get_marker()) for line in means}
    assert len(styles) == 2  # arms that overlap stay apart


def test_network_drawing_has_a_legend_and_no_unused_bias(tmp_path):
    def texts(fig):
        ax = fig.axes[0]
        return [t.get_text() for t in ax.texts], [t.get_text() for t in ax.get_legend().get_texts()]

    nodes, legend = texts(netdraw.network_figure(Genome.parse("N0/2*1 I0*1 R0*0.5")))
    assert "bias (1)" not in legend  # no B gene: no bias node
    assert legend == ["network input", "hidden neuron", "output neuron", "input of a neuron",
                      "recurrent jumper", "width, colour: weight"]  # fmt: skip
    nodes, legend = texts(netdraw.network_figure(Genome.parse(GENOME), n_inputs=3))
    assert "1" in nodes and "bias (1)" in legend and "x2" in nodes


@pytest.mark.slow
def test_evaluations_to_the_reference_fitness_match_a_plain_count(tmp_path):
    """Each arm's evaluations to 99% of the reference arm's mean final fitness: the first
    generation whose best cost is within 1% of that cost, averaged over the runs that got
    there (recomputed here from the records as written)."""
    dirs = [make_run(tmp_path / f"{p}-{s}", pruner=p, seed=s, generations=6)
            for p in ("covariance", "none") for s in (0, 1, 2)]  # fmt: skip
    runs = rp.load_runs(dirs)
    summary = rp.summarise(runs)
    target = float(np.mean([r.generations[-1].best_cost for r in runs if r.arm == "none"]))
    for arm in ("covariance", "none"):
        hits = []
        for r in (r for r in runs if r.arm == arm):
            costs = np.array([g.best_cost for g in r.generations])
            ok = np.flatnonzero(costs <= target * 1.01)  # costs are positive here
            if ok.size:
                hits.append(r.generations[ok[0]].evaluations)
        assert summary[arm]["reached_reference"] == len(hits)
        expected = np.mean(hits) if hits else None
        assert summary[arm]["evaluations_to_reference"] == expected
    # The reference arm's own runs end around their mean: not all need reach it.
    assert 1 <= summary["none"]["reached_reference"] <= 3
    text = rp.report(dirs, tmp_path / "rep").read_text()
    assert "evaluations to the reference's 99%" in text
    assert f"({summary['covariance']['reached_reference']}/3)" in text


@pytest.mark.slow
def test_upto_reads_every_run_to_one_generation(tmp_path, capsys, monkeypatch):
    """``eant2 report --upto G``: each run's records and pruning up to generation G, as if
    it had stopped there; a run that stopped before G is one clear error."""
    long = [make_run(tmp_path / f"c-{s}", seed=s, generations=6) for s in (0, 1)]
    short = [make_run(tmp_path / f"n-{s}", pruner="none", seed=s, generations=6, done=4)
             for s in (0, 1)]  # fmt: skip
    dirs = long + short
    cut = rp.summarise([rp.upto(r, 3) for r in rp.load_runs(dirs)])
    alone = []  # the same runs written only up to generation 3
    for d in dirs:
        name = Path(d).name
        arm = "none" if name.startswith("n") else "covariance"
        alone.append(make_run(tmp_path / "alone" / name, pruner=arm, seed=int(name[-1]),
                              generations=6, done=4))  # fmt: skip
    whole = rp.summarise(rp.load_runs(alone))
    for arm in ("covariance", "none"):
        for k in ("fitness_mean", "size_mean", "evaluations_to_99", "p_fitness"):
            assert cut[arm][k] == whole[arm][k], (arm, k)
    rc, out, err = _cli(["report", "--upto", "3", *dirs, "--out", "r3"], capsys, monkeypatch,
                        tmp_path)  # fmt: skip
    assert rc == 0, err
    assert "read up to generation 3" in (tmp_path / "r3" / "report.md").read_text()
    rc, out, err = _cli(["report", "--upto", "5", *dirs, "--out", "r5"], capsys, monkeypatch,
                        tmp_path)  # fmt: skip
    assert rc == 2 and "its last generation is 3, before 5" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "r5").exists()


@pytest.mark.slow
def test_strings_from_run_files_are_escaped_on_one_line(tmp_path):
    """A task (or arm) string read from config.json cannot add lines or Markdown of its own
    to the report."""
    hostile = "xor\n# injected [link](http://x) | cell\u2028more"
    dirs = [make_run(tmp_path / f"{p}-0", task=hostile, pruner=p) for p in ("covariance", "none")]
    text = rp.report(dirs, tmp_path / "rep").read_text()
    task_line = next(line for line in text.splitlines() if line.startswith("Task: "))
    assert task_line.startswith(
        r"Task: xor\n\# injected \[link\]\(http://x\) \| cell\u2028more; 2 runs"
    )
    assert not any(line.startswith("# injected") for line in text.splitlines())
    assert "\u2028" not in text
    assert rp.escape("a_b*c`d<e>") == r"a\_b\*c\`d\<e\>"
    assert rp.escape("plain text, 1.5") == "plain text, 1.5"


@pytest.mark.parametrize("dangling", [False, True])
@pytest.mark.slow
def test_a_link_planted_in_the_report_folder_is_refused(tmp_path, dangling):
    dirs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    target = tmp_path / "bashrc"
    if not dangling:
        target.write_text("precious\n")
    out = tmp_path / "rep"
    out.mkdir()
    (out / "report.md").symlink_to(target)
    with pytest.raises(OSError, match="report.md: is a symbolic link"):
        rp.report(dirs, out)
    assert (target.read_text() == "precious\n") if not dangling else not target.exists()
    # A link in place of the report folder itself is refused too.
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "rep2").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OSError, match="rep2: is a symbolic link"):
        rp.report(dirs, tmp_path / "rep2")
    assert not any((tmp_path / "elsewhere").iterdir())


def test_a_report_is_never_written_inside_a_run_it_reads(tmp_path, capsys, monkeypatch):
    dirs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    before = sorted(p.name for p in Path(dirs[0]).iterdir())
    for out in (Path(dirs[0]), Path(dirs[0]) / "report", Path(dirs[1]) / "a" / "b"):
        with pytest.raises(ValueError, match="inside the run directory"):
            rp.report(dirs, out)
    assert sorted(p.name for p in Path(dirs[0]).iterdir()) == before
    assert not (Path(dirs[1]) / "a").exists()
    # Without --out: beside the first directory, even when it is named "."
    monkeypatch.chdir(dirs[0])
    assert rp.default_folder(["."]) == tmp_path / "report"
    rc, _, err = _cli(["report", dirs[0], dirs[1], "--out", str(Path(dirs[0]) / "r")], capsys,
                      monkeypatch, tmp_path)  # fmt: skip
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "inside the run directory" in err


@pytest.mark.slow
def test_an_existing_report_is_replaced_whole(tmp_path):
    dirs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    out = tmp_path / "rep"
    first = rp.report(dirs, out).read_text()
    (out / "notes.txt").write_text("mine\n")
    assert rp.report(dirs, out).read_text() == first
    assert (out / "notes.txt").read_text() == "mine\n"  # nothing else is touched
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp file left


def _loaded(arm: str, seed: int, cost: float):
    rec = GenerationRecord(0, cost, 5, 5.0, 2, 100, 1.0, 0, 0, 20, 4, 1.0, GENOME)
    return rp.LoadedRun(f"{arm}-{seed}", arm, "xor", seed, [rec], [])


@pytest.mark.parametrize("covariance", [(3.0, 3.0, 3.0000001), (2.0, 2.5, 2.9)])
def test_p_value_of_a_constant_or_nearly_identical_arm_is_scipys_without_a_warning(covariance):
    """The reference arm's runs all end at one cost (a constant sample): scipy warns of
    "precision loss" for it although its variance is exactly 0. The report gives scipy's
    p-value and no warning (which would end a run under warnings-as-errors)."""
    from scipy import stats

    none = (3.0, 3.0, 3.0)
    runs = [_loaded("none", s, c) for s, c in enumerate(none)]
    runs += [_loaded("covariance", s, c) for s, c in enumerate(covariance)]
    summary = rp.summarise(runs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected = stats.ttest_ind(-np.array(covariance), -np.array(none), equal_var=False)
    assert summary["covariance"]["p_fitness"] == float(expected.pvalue)
