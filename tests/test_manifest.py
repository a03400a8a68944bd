"""reproduce.json is data: checked field by field before anything runs, its task rebuilt only
when registered (no module or file it names is imported), every bad manifest one line."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from eant2_jax.app import manifest as mf
from eant2_jax.app.cli import main
from eant2_jax.app.experiments import resume_reproduction
from eant2_jax.config import EANT2Config
from eant2_jax.rundir import RunDirError


def good() -> dict:
    """A manifest as `reproduce` writes it."""
    return {
        "version": 1,
        "task_meta": {"task": "xor", "task_options": {}},
        "runs": 2,
        "generations": 2,
        "pruners": ["covariance"],
        "config": EANT2Config(population=5).to_dict(),
        "seed": 0,
        "devices": 1,
        "workers_per_device": 1,
        "lockstep": True,
        "condition": True,
        "condition_iters": 60,
        "condition_inits": 2,
        "condition_dtype": "float64",
    }


def write(d, m) -> None:
    d.mkdir(exist_ok=True)
    text = m if isinstance(m, str | bytes) else json.dumps(m)
    (d / mf.MANIFEST).write_bytes(text if isinstance(text, bytes) else text.encode())


def test_a_good_manifest_is_read_back():
    s = mf.check_manifest(good(), "m")
    assert s["config"] == EANT2Config(population=5) and s["lockstep"] is True
    assert s["task_meta"] == {"task": "xor", "task_options": {}} and s["devices"] == 1
    old = good()
    del old["lockstep"]  # written before lock-step existed: each run alone
    assert mf.check_manifest(old, "m")["lockstep"] is False
    assert mf.check_manifest({**good(), "devices": "all"}, "m")["devices"] == "all"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"runs": 0}, r"runs must be in \[1, 10000\], got 0"),
        ({"runs": 10**30}, "runs must be in"),
        ({"runs": 2.0}, "runs must be an integer, got 2.0"),
        ({"runs": True}, "runs must be an integer, got True"),
        ({"generations": -1}, "generations must be in"),
        ({"seed": 2**32 - 1}, r"seed \+ runs must be at most 2\*\*32"),
        ({"devices": "some"}, "devices must be an integer"),
        ({"condition": 1}, "condition must be true or false"),
        ({"condition_dtype": "float16"}, "condition_dtype must be float32 or float64"),
        ({"condition_iters": 10**9}, "condition_iters must be in"),
        ({"pruners": "covariance"}, "pruners must be a list"),
        ({"pruners": ["lottery"]}, "pruners: unknown arm 'lottery'"),
        ({"pruners": ["obs", "obs"]}, "pruners: arm 'obs' given twice"),
        ({"task_meta": {"task": "xor"}}, "task_meta must be an object with task and task_opt"),
        ({"task_meta": {"task": 3, "task_options": {}}}, "task_meta.task must be a task's name"),
        ({"config": {"population": 5}}, "config: "),
        ({"config": []}, "config: "),
        ({"surprise": 1}, "unknown field 'surprise'"),
        ({"version": 2}, "not a reproduce.json of version 1"),
    ],
)
def test_each_field_is_checked_by_type_and_range(change, message):
    with pytest.raises(mf.ManifestError, match=f"^m: .*{message}") as e:
        mf.check_manifest({**good(), **change}, "m")
    assert "\n" not in str(e.value)


def test_reproduce_checks_its_settings_before_creating_anything(tmp_path):
    from eant2_jax import tasks
    from eant2_jax.app.experiments import reproduce

    with pytest.raises(mf.ManifestError, match="reproduce: condition_inits must be in"):
        reproduce(tasks.make("xor"), tmp_path / "r", task_meta={"task": "xor",
                  "task_options": {}}, condition_inits=10**6)  # fmt: skip
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "task_meta",
    [
        {"task": "os:system", "task_options": {"command": "touch {marker}"}},
        {"task": "evil.py:make", "task_options": {}},
        {"task": "evil.py", "task_options": {}},
        {"task": "evil:make", "task_options": {}},
    ],
)
def test_a_manifest_naming_code_runs_nothing(tmp_path, capsys, monkeypatch, task_meta):
    """A received reproduction whose manifest names ``os:system``, a module or a task file
    shipped beside it: ``eant2 resume`` rebuilds nothing, imports nothing, runs nothing."""
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    marker = tmp_path / "ran"
    rep = tmp_path / "rep"
    rep.mkdir()
    code = f"import pathlib\npathlib.Path({str(marker)!r}).touch()\ndef make():\n    pass\n"
    (rep / "evil.py").write_text(code)
    m = good()
    m["task_meta"] = json.loads(json.dumps(task_meta).replace("{marker}", str(marker)))
    write(rep, m)
    monkeypatch.chdir(rep)  # cd DIR; eant2 resume .
    monkeypatch.syspath_prepend(str(rep))  # even a module the manifest names is importable
    with pytest.raises(mf.ManifestError, match="is not a registered task"):
        resume_reproduction(".")
    assert main(["resume", "."]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("eant2: error:")]
    assert len(errors) == 1 and "is not a registered task" in errors[0], err
    assert "Traceback" not in err
    assert not marker.exists()
    assert sorted(p.name for p in rep.iterdir()) == ["evil.py", mf.MANIFEST]  # nothing ran


def test_the_manifest_is_read_as_data(tmp_path):
    """Never through a link, a regular file only, at most its cap in bytes."""
    (tmp_path / "secret.json").write_text(json.dumps(good()))
    links = tmp_path / "links"
    links.mkdir()
    (links / mf.MANIFEST).symlink_to(tmp_path / "secret.json")
    with pytest.raises(mf.ManifestError, match="not a reproduction .*cannot read it"):
        mf.read_manifest(links)
    zero = tmp_path / "zero"
    zero.mkdir()
    (zero / mf.MANIFEST).symlink_to("/dev/zero")
    with pytest.raises(mf.ManifestError, match="cannot read it"):
        mf.read_manifest(zero)
    big = tmp_path / "big"
    write(big, " " * (1 << 20) + "{}")
    with pytest.raises(mf.ManifestError, match="more than 1048576 bytes"):
        mf.read_manifest(big)
    with pytest.raises(RunDirError, match="not a reproduction"):
        mf.read_manifest(tmp_path / "absent")


def _mutants(rng: np.random.Generator, n: int):
    """``n`` manifests, each a good one with a few random mutations: wrong types, huge and
    negative numbers, NaN and infinities, deep nesting, missing and unknown fields, random
    task specs and options, and text that is not JSON at all."""
    odd = [None, True, 1.5, -1, 0, 2**31, 2**63, 10**40, -(10**40), math.nan, math.inf, "",
           "x" * 2000, "all", [], {}, [1, [2, [3]]], {"a": {"b": {}}}, "os:system", "\n# h",
           "float64", ["covariance"], "covariance"]  # fmt: skip

    def deep(k):
        v: object = 0
        for _ in range(k):
            v = [v]
        return v

    for _ in range(n):
        m = good()
        for _ in range(int(rng.integers(1, 4))):
            where = m
            path = [str(rng.choice(sorted(m)))]
            if path[0] in ("config", "task_meta") and rng.random() < 0.6:
                where = m[path[0]]
                if isinstance(where, dict) and where:
                    path.append(str(rng.choice(sorted(where))))
            target, key = (m, path[0]) if len(path) == 1 else (m[path[0]], path[1])
            if not isinstance(target, dict):
                continue
            op = rng.integers(5)
            if op == 0:
                target.pop(key, None)
            elif op == 1:
                target[key] = copy.deepcopy(odd[int(rng.integers(len(odd)))])
            elif op == 2:
                target[key] = deep(int(rng.integers(1, 60)))
            elif op == 3:
                target["extra" + str(rng.integers(3))] = 1
            else:
                v = target.get(key)
                target[key] = -v if isinstance(v, int | float) else [v]
        kind = rng.integers(10)
        text = json.dumps(m)  # NaN and infinities as JSON's bare constants
        if kind == 0:
            text = text[: int(rng.integers(len(text)))]  # cut short
        elif kind == 1:
            text = "[" * int(rng.integers(30, 5000)) + "]" * 10
        yield text


@pytest.mark.slow
def test_fuzzed_manifests_end_in_one_line_each(tmp_path):
    """A seeded loop of 400 mutated manifests: each is read back as valid settings with a
    registered task, or refused with one `ManifestError` line; never a traceback."""
    rng = np.random.default_rng(20261125)
    outcomes = {"refused": 0, "valid": 0}
    d = tmp_path / "rep"
    for i, text in enumerate(_mutants(rng, 400)):
        write(d, text)
        try:
            s = mf.read_manifest(d)
            task = mf.resume_task(s["task_meta"], "m")
        except mf.ManifestError as e:
            assert "\n" not in str(e) and str(e), (i, text[:300])
            outcomes["refused"] += 1
            continue
        assert isinstance(s["config"], EANT2Config) and task.n_inputs > 0
        assert 1 <= s["runs"] <= mf.LIMITS["runs"][1] and isinstance(s["pruners"], list)
        outcomes["valid"] += 1
    assert outcomes["refused"] > 300 and outcomes["valid"] > 0, outcomes


def test_a_damaged_condition_result_is_one_line(tmp_path):
    from eant2_jax.app.manifest import check_condition

    cond = {"before": [[1.0, 2.0]], "after": [[1.0]], "peak_before": [2.0], "peak_after": [1.0],
            "size_before": 5, "size_after": 3, "genome_before": "N0/1*1 I0*1",
            "genome_after": "N0/1*1 I0*1", "dtype": "float64", "max_condition": 1e17}  # fmt: skip
    assert check_condition(cond, "c") is cond
    for change in ({"size_before": "5\n# x"}, {"peak_after": []}, {"dtype": None},
                   {"before": [["x"]]}, {"max_condition": math.nan}):  # fmt: skip
        with pytest.raises(mf.ManifestError, match="^c: .* is missing or not what"):
            check_condition({**cond, **change}, "c")
