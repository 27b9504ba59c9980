"""``bondgraph loop --skip-effects``: effects the user rules out (calibrated
sensors) are neither scored nor discovered; ``bondgraph models --effects``
lists the library by the names the option takes."""

from __future__ import annotations

import argparse

import pytest

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.cli import loop as cli_loop
from bondgraph.cli import models as cli_models
from bondgraph.diagnose.effects import DEFAULT_EFFECTS
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import OptionError


def settings(*argv: str) -> LoopSettings:
    p = argparse.ArgumentParser()
    cli_loop.configure(p)
    return cli_loop.loop_settings(p.parse_args(list(argv)), LoopSettings(params=["m"]),
                                  mass_spring_damper())


def test_sensor_pattern_leaves_out_every_sensor_effect_and_nothing_else():
    s = settings("--skip-effects", "sensor_*, cold_start")
    names = [e.name for e in s.effects]
    sensor = [e.name for e in DEFAULT_EFFECTS if e.target_kind == "sensor"]
    assert len(sensor) == 7            # offset, gain, rectification, low-pass, poly2/3, quantisation
    assert not set(sensor) & set(names) and "cold_start" not in names
    assert names == [e.name for e in DEFAULT_EFFECTS
                     if e.name not in sensor and e.name != "cold_start"]


def test_a_pattern_that_matches_nothing_is_refused_with_the_names():
    with pytest.raises(OptionError, match="'sensr_\\*' matches no effect") as err:
        settings("--skip-effects", "sensr_*")
    assert "sensor_offset" in str(err.value) and "coulomb" in str(err.value)
    with pytest.raises(OptionError, match="leaves no effect to score"):
        settings("--skip-effects", "*")


def test_the_whole_library_list_but_one_leaves_that_one():
    """The names of `bondgraph models --effects` copied whole, one left
    out: the optional ones among them (scored only with --add-effects) are
    no mistake, and the loop scores the one left."""
    every = [e.name for e in DEFAULT_EFFECTS] + [e.name for e in cli_loop.OPTIONAL_EFFECTS]
    assert "bouc_wen" in every
    s = settings("--skip-effects", ",".join(n for n in every if n != "cubic_stiffness"))
    assert [e.name for e in s.effects] == ["cubic_stiffness"]


def test_discovery_seeks_no_law_at_sensors_the_user_ruled_out(monkeypatch):
    from bondgraph.diagnose.discover import effect as disc

    seen = {}

    def fake(graph, record, s, res, *, log=None, sensors=None, **kw):
        seen["sensors"] = sensors
        return None

    monkeypatch.setattr(disc, "discovered_effect", fake)
    for argv, want in ((("--skip-effects", "sensor_*"), ()), (("--skip-effects", "coulomb"), None)):
        s = settings(*argv)
        args = argparse.Namespace(quiet=True, skip_effects=argv[1])
        assert cli_loop._with_discovery(args, mass_spring_damper(), None, s, "res", None) == "res"
        assert seen["sensors"] == want
    # a case whose own library has no sensor effect, without --skip-effects: sensors as before
    s = LoopSettings(params=["m"], effects=tuple(e for e in DEFAULT_EFFECTS
                                                 if e.target_kind != "sensor"))
    args = argparse.Namespace(quiet=True, skip_effects=None)
    assert cli_loop._with_discovery(args, mass_spring_damper(), None, s, "res", None) == "res"
    assert seen["sensors"] is None


def test_models_lists_the_effect_library(capsys):
    p = argparse.ArgumentParser()
    cli_models.configure(p)
    assert cli_models.run(p.parse_args(["--effects"])) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[0].split()[:4] == ["effect", "attaches", "to", "scored"]
    by_name = {r.split()[0]: r for r in rows[1:]}
    assert len(by_name) == len(rows) - 1 >= len(DEFAULT_EFFECTS)
    assert by_name["sensor_gain"].split()[1:3] == ["sensor", "additive"]
    assert by_name["r_power"].split()[1:3] == ["resistor", "structural"]
    assert "optional: --add-effects" in by_name["bouc_wen"]
    assert "last resort" in by_name["disturbance"]
