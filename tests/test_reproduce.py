"""`eant2 reproduce` in a short setting on CPU: every figure and the table are produced."""

import json

import pytest
from rundirs import run_records

# The command's short setting.
SERVO_ARGV = [
    "reproduce", "--runs", "2", "--generations", "1",
    "--population", "3", "--max-iters", "20", "--condition-iters", "20",
    "--condition-inits", "2", "--pruners", "covariance",
    "--task-option", "n_starts=4",
]  # fmt: skip


@pytest.mark.slow
def test_reproduce_short_servo(tmp_path, capsys, monkeypatch):
    """The command, in this process (what a child process would add is its start: the
    process behaviour of `eant2 reproduce`, Ctrl-C and exit 130, is
    tests/test_reproduce_resume.py's)."""
    from eant2_jax.app.cli import main

    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # in-process: leave the JAX configuration alone
    out = tmp_path / "rep"
    argv = [*SERVO_ARGV, "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err[-3000:]
    assert f"report: {out / 'report' / 'report.md'}" in capsys.readouterr().out
    report = out / "report"
    for name in ("fitness_size.png", "condition.png", "best_network.png", "pruned_network.png"):
        assert (report / name).stat().st_size > 1000, name  # a real PNG, not an empty file
        assert (report / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (report / "report.md").read_text()
    assert "| covariance | 2 |" in text and "| none | 2 |" in text
    assert "The paper's claims" in text and "Baselines" in text
    summary = json.loads((report / "summary.json").read_text())
    assert set(summary) == {"covariance", "none"}
    cond = json.loads((out / "condition.json").read_text())
    assert cond["dtype"] == "float64" and len(cond["peak_before"]) == 2
    assert all(len(c) == 20 for c in cond["before"] + cond["after"])
    for arm in ("covariance", "none"):
        for seed in (0, 1):
            gens = (out / f"{arm}-s{seed}" / "generations.jsonl").read_text().splitlines()
            assert len(gens) == 2  # generations 0, 1
    # Both refusals come before anything runs. An unknown arm is one line:
    argv_bad = [*argv[:-1], str(tmp_path / "bad"), "--pruners", "covariance-exact"]
    assert main(argv_bad) == 2 and not (tmp_path / "bad").exists()
    assert "unknown arm" in capsys.readouterr().err
    # The output directory is never overwritten.
    assert main(argv) == 2
    assert "not overwriting" in capsys.readouterr().err


def test_arms_name_a_pruner_and_its_rule():
    from eant2_jax.app.experiments import arm_config
    from eant2_jax.config import EANT2Config

    base = EANT2Config()
    tentative = arm_config(base, "covariance").exploit
    assert tentative.pruner == "covariance" and tentative.prune_refit == base.exploit.prune_refit
    literal = arm_config(base, "obs-literal").exploit
    assert literal.pruner == "obs"
    rule = (literal.prune_refit, literal.prune_reference, literal.prune_at_stop)
    assert rule == (0, "mean", False)  # as ExploitConfig.literal() sets it
    assert arm_config(base, "none").exploit.pruner == "none"
    for bad in ("covariance-exact", "none-literal", "lottery"):
        with pytest.raises(ValueError, match="unknown arm"):
            arm_config(base, bad)


def _xor_settings():
    """A tiny reproduction on XOR: one run of the covariance arm and of the unpruned one,
    and the condition experiment."""
    from eant2_jax.config import EANT2Config, ExploitConfig

    return dict(
        task_meta={"task": "xor", "task_options": {}}, runs=1, generations=1,
        pruners=("covariance",), devices=1, condition_iters=20, condition_inits=2,
        config=EANT2Config(population=3, exploit=ExploitConfig(max_iters=30)),
    )  # fmt: skip


@pytest.fixture(scope="module")
def plain_xor(tmp_path_factory):
    """That reproduction by the plain path (the condition experiment inline, nothing
    compiled ahead), shared by the tests that compare another path's result with it; and
    its progress events."""
    import jax

    from eant2_jax import tasks
    from eant2_jax.app.experiments import reproduce

    out, events = tmp_path_factory.mktemp("plain") / "rep", []
    settings = _xor_settings()
    reproduce(tasks.make("xor"), out, overlap_condition=False, callback=events.append, **settings)
    assert not jax.config.jax_enable_x64  # float64 stayed inside the experiment
    return out, events


@pytest.mark.slow
def test_the_condition_experiment_in_a_background_thread_gives_the_same_result(tmp_path, plain_xor):
    """``overlap_condition`` runs the experiment in a thread (float64 there alone) while the
    main thread goes on; its result equals the inline one's. (The pruning arms themselves
    are not overlapped here: on a CPU two programs at once can deadlock XLA's thread pool,
    which is why the overlap is off there by default.)"""
    import jax

    from eant2_jax import tasks
    from eant2_jax.app.experiments import reproduce

    plain, plain_events = plain_xor
    events = []
    out = tmp_path / "overlap"
    reproduce(
        tasks.make("xor"), out, overlap_condition=True, callback=events.append, **_xor_settings()
    )
    assert not jax.config.jax_enable_x64  # float64 stayed inside the experiment
    cond = [json.loads((d / "condition.json").read_text()) for d in (plain, out)]
    assert cond[0] == cond[1] and cond[0]["dtype"] == "float64"
    for evs in (plain_events, events):
        assert [e["phase"] for e in evs if e["event"] == "condition"] == ["start", "done"]
    for run in ("covariance-s0", "none-s0"):  # the runs are the same too
        assert run_records(plain / run) == run_records(out / run), run


def test_a_background_error_reaches_the_caller():
    from eant2_jax.app.experiments import Background

    def boom(x):
        raise ValueError(f"bad {x}")

    with pytest.raises(ValueError, match="bad 3"):
        Background("t", boom, 3).result()
    assert Background("t", lambda x: x + 1, 3).result() == 4


@pytest.mark.slow
def test_later_arms_first_programs_compiled_ahead_are_used_and_change_nothing(
    tmp_path, monkeypatch, plain_xor
):
    """On an accelerator `reproduce` starts compiling each later arm's generation-0
    program (one lock-step group per arm) before the first arm runs. Forced on here, each
    compilation waited for at once (two programs at once on a CPU can deadlock XLA's thread
    pool): the pruning arm's first generation runs that very program (called without jit's
    fallback, so arguments shaped otherwise than foreseen would raise), and every run
    directory's records are those of the plain path."""
    from compiles import force_compile_ahead, joined

    from eant2_jax import tasks
    from eant2_jax.app import experiments
    from eant2_jax.loop import compile_first_ahead

    plain, _ = plain_xor
    calls = []
    used = force_compile_ahead(monkeypatch)  # strictly: no fallback to jit
    monkeypatch.setattr(experiments, "compile_first_ahead", joined(compile_first_ahead, calls))
    # Without the condition experiment, which reads the runs' result and changes none.
    settings = {**_xor_settings(), "condition": False}
    experiments.reproduce(tasks.make("xor"), tmp_path / "ahead", **settings)
    assert calls == [True]  # the covariance arm's, before the unpruned arm ran
    assert used  # the arms ran programs compiled ahead, strictly
    for run in ("covariance-s0", "none-s0"):
        assert run_records(plain / run) == run_records(tmp_path / "ahead" / run), run
