"""`KEY=VALUE` physics switches of the benchmarks: parsed against SimParams and StaticSimParams' laws with one-line
errors, each applied where it belongs, and timed side by
side with the defaults by `python -m benchmarks.engine_speed --vs-sim` (and other solver counts by `--vs-substeps`,
`--vs-iterations`, `--vs-relax-iterations`)."""

from __future__ import annotations

import argparse
import json

import pytest

from benchmarks import engine_speed
from benchmarks.sim_overrides import sim_override, with_sim_overrides
from kforge.engine import ContactLaw, SimParams, StaticSimParams


def test_a_field_and_a_number_parse():
    assert sim_override("swept_speculative_contacts=0") == ("swept_speculative_contacts", False)
    assert sim_override("contact_law=1") == ("contact_law", ContactLaw.BAUMGARTE)
    assert sim_override("contact_hertz=30.5") == ("contact_hertz", 30.5)


def test_a_law_goes_to_the_static_params_and_a_constant_to_the_traced_ones():
    overrides = [sim_override("contact_law=1"), sim_override("contact_hertz=20")]
    params, static = with_sim_overrides(SimParams(), StaticSimParams(), overrides)
    assert static == StaticSimParams(contact_law=ContactLaw.BAUMGARTE)
    assert params == SimParams(contact_hertz=20.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("contact_hertz", r"expected KEY=VALUE, got 'contact_hertz'"),
        ("no_such_field=1", r"'no_such_field' is neither a SimParams field nor a law \(known: .*contact_hertz.*\)"),
        ("contact_hertz=fast", r"contact_hertz='fast': the value is not a number"),
        ("contact_law=2", r"contact_law='2': 2.0 is not a valid ContactLaw"),
        ("swept_speculative_contacts=2", r"swept_speculative_contacts='2': the value is not 0 or 1"),
    ],
)
def test_a_bad_switch_is_refused_naming_the_problem(text, message):
    with pytest.raises(argparse.ArgumentTypeError, match=message):
        sim_override(text)


def test_the_engine_benchmark_refuses_an_unknown_field_on_its_command_line(capsys):
    with pytest.raises(SystemExit):
        engine_speed.main(["--vs-sim", "no_such_field=1"])
    assert "'no_such_field' is neither a SimParams field nor a law" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--vs-substeps", "0", "--vs-substeps must be at least 1, got 0"),
        ("--vs-substeps", "two", "invalid int value: 'two'"),
        ("--vs-iterations", "0", "--vs-iterations must be at least 1, got 0"),
        ("--vs-relax-iterations", "-1", "--vs-relax-iterations must be at least 0, got -1"),
    ],
)
def test_the_engine_benchmark_refuses_a_solver_count_below_its_least_or_not_a_number(capsys, option, value, message):
    with pytest.raises(SystemExit):
        engine_speed.main([option, value])
    assert message in capsys.readouterr().err


@pytest.mark.slow  # compiles the s step twice: about 40 s on 2 cores
def test_the_engine_benchmark_times_another_substep_count_beside_the_default(capsys):
    engine_speed.main(
        ["--sizes", "s", "--batches", "2", "--steps", "2", "--repeats", "1", "--vs-substeps", "1", "--json"]
    )
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert "with substeps=1=" in captured.err
    assert report["substeps"] == 1 and report["iterations"] is None and report["sim_overrides"] == {}
    default, fewer = report["steps_per_second"]["ours"]["s"]["2"], report["steps_per_second"]["ours_sim"]["s"]["2"]
    assert default > 0 and fewer > 0
    assert report["sim_vs_default"]["s"]["2"] == pytest.approx(fewer / default)


@pytest.mark.slow  # compiles the s step twice: about 40 s on 2 cores
def test_the_engine_benchmark_times_a_switched_option_beside_the_default(capsys):
    engine_speed.main(
        ["--sizes", "s", "--batches", "2", "--steps", "2", "--repeats", "1"]
        + ["--vs-sim", "swept_speculative_contacts=0", "--json"]
    )
    report = json.loads(capsys.readouterr().out)
    assert report["sim_overrides"] == {"swept_speculative_contacts": False}
    default, switched = report["steps_per_second"]["ours"]["s"]["2"], report["steps_per_second"]["ours_sim"]["s"]["2"]
    assert default > 0 and switched > 0
    assert report["sim_vs_default"]["s"]["2"] == pytest.approx(switched / default)
