"""The arms of a reproduction: named configuration overrides from a fixed registry.

An arm is a name, never code: `arm_overrides` maps it to the `ExploitConfig` fields it sets
and `arm_config` applies them to the reproduction's base configuration (validated there, as
any configuration is). A manifest names its arms and records their overrides
(`eant2_jax.app.manifest`), and each run directory's ``config.json`` holds the whole
configuration its arm ran.

Two kinds of names:

* **The protocol's arms** (docs/protocol.md, section 1) fix the pruner and the four fields
  of the rule, each at `ExploitConfig`'s default unless the arm changes it, so that an
  ablation differs from ``default`` in exactly one field whatever the base says:
  ``none``, ``literal`` (the paper's rule as written), ``default``, the ablations
  ``no-refit``, ``mean-reference``, ``trigger-only``, ``window-250`` and the controls
  ``random``, ``magnitude``, ``obs``, ``snr`` (and ``obd``): the default rule with another
  choice of the connection tried.
* **A pruner's name** (``covariance``, ...) or ``NAME-literal`` (the paper's rule for that
  pruner): the pruner (and the literal rule) on the base configuration, as reproductions
  before the protocol named their arms.

A run count may follow a name (``default:20``); `parse_arms` reads such a list.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ..config import EANT2Config, ExploitConfig
from ..kernels.pruning import PRUNERS

__all__ = ["PROTOCOL_ARMS", "RULE", "arm_config", "arm_overrides", "parse_arms"]

# The fields an arm may set: the pruner and the rule.
RULE = ("pruner", "prune_refit", "prune_reference", "prune_at_stop", "prune_window")
_LITERAL = {"prune_refit": 0, "prune_reference": "mean", "prune_at_stop": False}
_DEFAULT_RULE = {f: ExploitConfig.__dataclass_fields__[f].default for f in RULE[1:]}

# The protocol's arms: name -> (what it changes from the default rule, what it is).
PROTOCOL_ARMS: dict[str, tuple[dict[str, Any], str]] = {
    "none": ({"pruner": "none"}, "no pruning (plain CMA-ES)"),
    "literal": ({"pruner": "covariance", **_LITERAL}, "the paper's rule as written"),
    "default": ({"pruner": "covariance"}, "the library's default rule"),
    "no-refit": ({"pruner": "covariance", "prune_refit": 0}, "default, no re-fit"),
    "mean-reference": (
        {"pruner": "covariance", "prune_reference": "mean"},
        "default, acceptance against the current mean's cost",
    ),
    "trigger-only": (
        {"pruner": "covariance", "prune_at_stop": False},
        "default, attempts at the paper's trigger only",
    ),
    "window-250": ({"pruner": "covariance", "prune_window": 250}, "default, window 250"),
    "random": ({"pruner": "random"}, "default rule, a removable connection drawn at random"),
    "magnitude": ({"pruner": "magnitude"}, "default rule, the smallest weight"),
    "obs": ({"pruner": "obs"}, "default rule, optimal brain surgeon's candidate"),
    "obd": ({"pruner": "obd"}, "default rule, optimal brain damage's candidate"),
    "snr": ({"pruner": "snr"}, "default rule, the lowest signal-to-noise ratio"),
}
_MAX_NAME = 64


def _known() -> str:
    pruners = [p for p in PRUNERS if p not in PROTOCOL_ARMS]
    return ", ".join([*PROTOCOL_ARMS, *pruners]) + " (and PRUNER-literal)"


def arm_overrides(arm: str) -> dict[str, Any]:
    """The `ExploitConfig` fields arm ``arm`` sets (see the module's docstring).

    Raises:
      ValueError: not an arm's name (one line listing the names).
    """
    if not isinstance(arm, str) or len(arm) > _MAX_NAME:
        raise ValueError(f"unknown arm {arm!r:.80}; arms are {_known()}")
    if arm in PROTOCOL_ARMS:
        if arm == "none":
            return {"pruner": "none"}
        return {"pruner": "covariance", **_DEFAULT_RULE, **PROTOCOL_ARMS[arm][0]}
    name, _, variant = arm.partition("-")
    if name not in PRUNERS or variant not in ("", "literal") or (name == "none" and variant):
        raise ValueError(f"unknown arm {arm!r}; arms are {_known()}")
    return {"pruner": name, **(_LITERAL if variant else {})}


def arm_config(base: EANT2Config, arm: str) -> EANT2Config:
    """The configuration of arm ``arm``: ``base`` with `arm_overrides` applied to its
    `ExploitConfig` (ValueError for an unknown arm)."""
    exploit = dataclasses.replace(base.exploit, **arm_overrides(arm))
    return dataclasses.replace(base, exploit=exploit)


def parse_arms(text: str, runs: int) -> list[tuple[str, int]]:
    """``"none:20,default:20,no-refit:10,random"`` as ``[(arm, runs), ...]`` in the order
    given; an arm without a count takes ``runs``. ``none`` is added (with ``runs``) when
    missing: every arm is compared with it.

    Raises:
      ValueError: an unknown arm, a count that is not a positive integer, or an arm given
        twice (one line naming it).
    """
    out: dict[str, int] = {}
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        name, colon, count = item.partition(":")
        name = name.strip()
        arm_overrides(name)
        n = runs
        if colon:
            if not count.strip().isdigit() or int(count) < 1:
                raise ValueError(f"arm {name!r}: the run count must be a positive integer, got "
                                 f"{count!r:.40}")  # fmt: skip
            n = int(count)
        if name in out:
            raise ValueError(f"arm {name!r} given twice")
        out[name] = n
    out.setdefault("none", runs)
    return list(out.items())
