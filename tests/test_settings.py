"""The settings' schema (markerpose.settings) and the one resolver (markerpose.presets.resolve)."""

import math

import pytest

from markerpose import settings
from markerpose.presets import PRESETS, default_conf, resolve
from markerpose.stages import STAGES, match, propose, refine, solve, track, verify


def test_rules_say_what_a_value_takes():
    rule = settings.number(0, 1)
    assert rule.test(0.5) is None and rule.test(0) is None and rule.test(1) is None
    for bad in (-0.1, 1.5, math.nan, math.inf, "0.5", True, None):
        assert rule.test(bad) == "a number in [0, 1]"
    assert settings.number(0, above=True).test(0) == "a number > 0"
    assert settings.number(1, integer=True).test(2.5) == "a whole number >= 1"
    assert settings.number(1, integer=True).test(3) is None
    assert settings.flag().test(1) == "true or false" and settings.flag().test(False) is None
    assert settings.choice("a", "b").test("c") == "one of ['a', 'b']"
    assert settings.path().test(None) is None and settings.path().test(3) == "a file's path or None"


def test_every_stage_default_fits_its_rules_and_every_key_has_one():
    for name, module in zip(STAGES, (propose, match, refine, verify, solve, track)):
        assert set(module.default_conf) == set(module.RULES), name
        settings.check(name, module.default_conf, module.RULES)
    for name in PRESETS:
        conf = resolve(name)
        assert set(conf) == set(default_conf)


def test_resolve_checks_preset_and_overrides_alike():
    with pytest.raises(ValueError, match=r"track.lost_refresh must be a whole number >= 1, got 0"):
        resolve("paper", track={"lost_refresh": 0})
    with pytest.raises(ValueError, match=r"unknown verify setting 'plate_tol'"):  # a constant now: verify.PLATE_TOL
        resolve(verify={"plate_tol": 0.1})
    conf = resolve("paper-classical", solve={"pose": "rigid"})
    assert conf["detector"] == "classical" and conf["solve"] == {"pose": "rigid", "bias_correction": False}
    assert resolve(detector="classical") == resolve("classical")  # the shorthand: the classical preset


def test_the_readme_describes_the_presets_as_the_code_does():
    """The presets are described once (presets.ABOUT); the README's table shows that text."""
    from pathlib import Path

    from markerpose.presets import ABOUT, ORDER

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    for name in ORDER:
        assert f"| `{name}` | {ABOUT[name]}" in readme, name
