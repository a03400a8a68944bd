"""Configurations from field specs: one `option(...)` per field gives its validation, JSON
round trip, older files' default and help (eant2_jax/configspec.py)."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest

from eant2_jax import jsonio, pytree
from eant2_jax.config import EANT2Config, ExploitConfig
from eant2_jax.configspec import INT32_MAX, above, at_least, document, option


@document
@pytree.dataclass
class WiderExploit(ExploitConfig):
    """ExploitConfig with one more field: the one line below is all it takes."""

    step_cap: float = option(
        2.0, "Largest step, in units of sigma0.", check=above(0), added="0.2.0", old=1.0
    )


@document
@pytree.dataclass
class WiderStatic(ExploitConfig):
    """ExploitConfig with one more static field."""

    lanes: int = option(4, "Lanes of a batch.", check=above(0), static=True)


@document
@dataclasses.dataclass(frozen=True)
class WiderRun(EANT2Config):
    """EANT2Config whose exploit is a WiderExploit, with a new host field."""

    elite: int = option(1, "Elite kept unchanged.", check=at_least(0), added="0.2.0", old=0)
    exploit: WiderExploit = option(
        help="The exploitation config.", factory=WiderExploit, convert=lambda v: v
    )


def test_a_field_added_by_one_spec_is_validated_traced_and_documented():
    assert WiderExploit().step_cap == 2.0 and type(WiderExploit(step_cap=3).step_cap) is float
    with pytest.raises(ValueError, match=r"^WiderExploit\.step_cap must be > 0 and finite, got"):
        WiderExploit(step_cap=-1.0)
    with pytest.raises(ValueError, match=r"^WiderExploit\.step_cap must be a number, got 'x'"):
        WiderExploit(step_cap="x")
    # A number is a traced leaf (a new value: the same program); static shapes the program.
    leaves, treedef = jax.tree.flatten(WiderExploit(step_cap=3.0))
    assert leaves[-1] == 3.0 and len(leaves) == len(jax.tree.leaves(ExploitConfig())) + 1
    assert treedef == jax.tree.structure(WiderExploit(step_cap=5.0))
    assert jax.tree.structure(WiderStatic(lanes=2)) != jax.tree.structure(WiderStatic(lanes=3))
    assert len(jax.tree.leaves(WiderStatic())) == len(jax.tree.leaves(ExploitConfig()))
    # Help: the docstring's attribute list and the command line's rows.
    assert "  step_cap: Largest step, in units of sigma0. Added in 0.2.0;" in WiderExploit.__doc__
    assert "  lanes: *static*. Lanes of a batch." in WiderStatic.__doc__
    assert ("step_cap", "float", 2.0, "Largest step, in units of sigma0.") in (
        WiderExploit().describe()
    )
    assert ("exploit.step_cap", "float", 2.0, "Largest step, in units of sigma0.") in (
        WiderRun().describe()
    )
    assert WiderRun.locate("exploit.step_cap")[1].name == "step_cap"


def test_a_field_added_by_one_spec_round_trips_and_old_files_read_its_old_default():
    run = WiderRun(elite=3, exploit=WiderExploit(step_cap=4.0, max_iters=7))
    d = run.to_dict()
    assert d["elite"] == 3 and d["exploit"]["step_cap"] == 4.0
    text = jsonio.dumps(d)
    assert WiderRun.from_dict(jsonio.loads(text, "x"), complete=True) == run
    # A file written before the two fields existed: complete, and reads as they ran.
    old = {k: v for k, v in d.items() if k != "elite"}
    old["exploit"] = {k: v for k, v in d["exploit"].items() if k != "step_cap"}
    loaded = WiderRun.from_dict(old, complete=True)
    assert (loaded.elite, loaded.exploit.step_cap, loaded.exploit.max_iters) == (0, 1.0, 7)
    # A field that is not new is still required of a complete file.
    del old["exploit"]["sigma0"]
    with pytest.raises(ValueError, match="^WiderExploit option\\(s\\) missing: sigma0$"):
        WiderRun.from_dict(old, complete=True)
    with pytest.raises(ValueError, match="WiderExploit: step_cap must be a number, got 'big'"):
        WiderRun.from_dict({**d, "exploit": {**d["exploit"], "step_cap": "big"}})


def test_integers_are_checked_against_int32_before_anything_runs():
    with pytest.raises(ValueError, match=f"^ExploitConfig.max_iters must be at most {INT32_MAX}"):
        ExploitConfig(max_iters=INT32_MAX + 1)
    for name in ("patience", "prune_window", "bound_patience", "chunk", "popsize", "rescore"):
        with pytest.raises(ValueError, match=f"ExploitConfig.{name} must be at most"):
            ExploitConfig(**{name: 2**31})
    with pytest.raises(ValueError, match="EANT2Config.similar_limit must be at most"):
        EANT2Config(similar_limit=2**40)
    assert EANT2Config(max_evaluations=2**40).max_evaluations == 2**40  # counted on the host
    assert ExploitConfig(max_iters=INT32_MAX).max_iters == INT32_MAX


def test_values_take_one_python_type_and_json_keeps_non_finite_numbers():
    c = ExploitConfig(popsize=np.int64(8), max_iters=30.0, lazy_eigen=1, max_condition=math.inf)
    assert (type(c.popsize), type(c.max_iters), type(c.lazy_eigen)) == (int, int, float)
    again = ExploitConfig.from_dict(jsonio.loads(jsonio.dumps(c.to_dict()), "x"), complete=True)
    assert again == c and again.max_condition == math.inf
    # None stands for a value: written back as None, read back as that value.
    assert ExploitConfig(target_cost=None).target_cost == -math.inf
    assert ExploitConfig(target_cost=None).replace(sigma0=0.3).to_dict()["target_cost"] is None
    for bad, phrase in [(True, "must be an integer"), (2.5, "must be an integer")]:
        with pytest.raises(ValueError, match=f"EANT2Config.population {phrase}"):
            EANT2Config(population=bad)


def test_json_is_typed_and_unknown_or_missing_keys_are_named():
    d = EANT2Config().to_dict()
    with pytest.raises(ValueError, match="^unknown EANT2Config option\\(s\\): popsize; known:"):
        EANT2Config.from_dict({**d, "popsize": 3})
    with pytest.raises(ValueError, match="the configuration has no 'exploit' object"):
        EANT2Config.from_dict({k: v for k, v in d.items() if k != "exploit"})
    with pytest.raises(ValueError, match="ExploitConfig: sigma0 must be a number, got \\[1\\]"):
        EANT2Config.from_dict({**d, "exploit": {**d["exploit"], "sigma0": [1]}})
    with pytest.raises(ValueError, match="EANT2Config.devices must be an integer or a string"):
        EANT2Config.from_dict({**d, "devices": [2]})
    with pytest.raises(ValueError, match="EANT2Config option\\(s\\) missing: population"):
        EANT2Config.from_dict({k: v for k, v in d.items() if k != "population"}, complete=True)
    assert EANT2Config.from_dict({"exploit": {}}) == EANT2Config(exploit=ExploitConfig())
    with pytest.raises(ValueError, match="unknown option 'exploit.sigma' \\(did you mean"):
        EANT2Config.locate("exploit.sigma")
