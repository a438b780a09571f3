"""One option specification (`hamid.options.OPTION_GROUPS`): `FitOptions`' fields,
`hamid.fit`'s keywords and the commands' options are checked against it, so that an option
is added in one place and a command that forgets one fails here."""

from __future__ import annotations

import collections
import dataclasses
import inspect
import json
import re

import click
import pandas as pd
import pytest
from click.testing import CliRunner

import hamid
from hamid import api
from hamid.cli import option_groups
from hamid.cli.app import cli
from hamid.options import FIT_KEYWORDS, OPTION_GROUPS, READING_OPTIONS, FitOptions

SAMPLE = "sample_data/duffing.csv"   # k = 1, k3 = 0.5 (the file's header)
# `hamid fit`'s parameters that are no keyword of `hamid.fit`: what to fit, what to write,
# how to fail, how to spread many files.
FIT_CLI_ONLY = {"data", "model", "strict", "fmt", "output", "residuals", "figure", "each",
                "scheduler", "ship_data"}
FIT_PARAMETERS = inspect.signature(hamid.fit).parameters


def _command(*groups):
    """A command with the options of these group decorators, and nothing else."""
    def command(**options):
        """A test command."""
    for group in reversed(groups):
        command = group(command)
    return click.command()(command)


def _options(command: click.Command, names) -> list[click.Option]:
    return [p for p in command.params if isinstance(p, click.Option) and p.name in names]


def test_every_fit_option_field_is_in_exactly_one_group():
    assert len(FIT_KEYWORDS) == len(set(FIT_KEYWORDS)) == 28
    assert set(FIT_KEYWORDS) == {f.name for f in dataclasses.fields(FitOptions)} | {"progress"}
    assert list(OPTION_GROUPS) == ["reading", "velocities", "method", "covariance", "run"]
    assert set(READING_OPTIONS) == {"columns", "time", "time_unit", "trajectory", "scale",
                                    "gaps", "delimiter", "decimal", "skip_rows", "units_row",
                                    "format"}
    assert OPTION_GROUPS["run"] == ("jobs", "chunk_rows", "in_memory", "progress")


def test_fits_keywords_are_the_spec_in_its_order():
    keyword_only = [name for name, p in FIT_PARAMETERS.items()
                    if p.kind is inspect.Parameter.KEYWORD_ONLY]
    assert keyword_only == list(FIT_KEYWORDS)
    assert [name for name, p in FIT_PARAMETERS.items()
            if p.kind is not inspect.Parameter.KEYWORD_ONLY] == ["data", "model"]


def test_fits_defaults_are_the_default_options():
    """`fix=None` and `damping="none"` are read as FitOptions' {} and ()."""
    given = {f.name: FIT_PARAMETERS[f.name].default for f in dataclasses.fields(FitOptions)}
    assert FitOptions(**given) == FitOptions()
    assert FitOptions().damping == () and FitOptions(damping=[]).damping == ()
    damped = FitOptions(damping="viscous")
    assert dataclasses.replace(damped, damping=()) == FitOptions()   # parsed, parsed again
    assert dataclasses.replace(damped, level=0.9).damping == ("viscous",)


def test_fit_hands_every_keyword_to_fit_options_as_given(monkeypatch):
    """Each keyword arrives in its own field, none swapped or dropped (the call lists
    them all)."""
    class Received(Exception):
        pass

    def record(**options):
        raise Received(options)

    monkeypatch.setattr(api, "FitOptions", record)
    values = {name: object() for name in FIT_KEYWORDS}
    with pytest.raises(Received) as received:
        hamid.fit("unused.csv", **values)
    values.pop("progress")
    assert received.value.args[0] == values


def test_fit_takes_every_option_of_the_spec_once():
    names = collections.Counter(p.name for p in cli.commands["fit"].params)
    assert max(names.values()) == 1
    assert set(names) == (set(FIT_KEYWORDS) - set(option_groups.API_ONLY)) | FIT_CLI_ONLY
    assert set(option_groups.API_ONLY) == {"in_memory", "progress"}


@pytest.mark.parametrize("group", list(OPTION_GROUPS))
def test_each_group_declares_its_options_in_the_spec_order(group):
    declared = [p.name for p in _command(getattr(option_groups, group)).params]
    assert declared == [name for name in OPTION_GROUPS[group]
                        if name not in option_groups.API_ONLY]


def test_every_option_shows_fits_default():
    """What the help shows as the default is what `hamid.fit` does when the option is left
    out (the command line passes only the options given)."""
    # in a context under the group's, as on the command line (a context of its own would
    # leave click's cached help option without the group's -h)
    parent = cli.make_context("hamid", ["fit"], resilient_parsing=True)
    left_out = cli.commands["fit"].make_context("fit", ["data.csv"], parent=parent).params
    shown = {name: value for name, value in left_out.items() if name in FIT_KEYWORDS}
    assert len(shown) == len(FIT_KEYWORDS) - len(option_groups.API_ONLY)
    assert shown == {name: FIT_PARAMETERS[name].default for name in shown}


def _help(command: str) -> str:
    done = CliRunner().invoke(cli, [command, "--help"], prog_name="hamid")
    assert done.exit_code == 0, done.output
    return done.stdout


def _help_sections(command: str) -> dict[str, list[str]]:
    """The sections of a command's help after its description: heading -> the lines."""
    sections: dict[str, list[str]] = {"Options": []}
    heading = "Options"
    for line in _help(command).split("\nOptions:\n", 1)[1].splitlines():
        if line.endswith(":") and not line.startswith(" "):
            heading = line[:-1]
            sections[heading] = []
        elif line.strip():
            sections[heading].append(line)
    return sections


def _help_flags(command: str) -> dict[str, str]:
    """The option strings of a command's help, each with its line and the lines under it."""
    entries = re.split(r"\n(?=  -)", "\n".join(
        line for lines in _help_sections(command).values() for line in lines))
    return {flag: " ".join(entry.split()) for entry in entries
            for flag in re.findall(r"--[a-z-]+", re.split(r"\s{2,}", entry.strip())[0])}


def test_fit_select_plot_predict_and_backbone_list_the_same_reading_options():
    reading = _options(_command(option_groups.reading), READING_OPTIONS)
    flags = {flag for option in reading for flag in [*option.opts, *option.secondary_opts]}
    assert flags == {"--columns", "--time", "--time-unit", "--scale", "--gaps", "--trajectory",
                     "--format-in", "--delimiter", "--decimal", "--skip-rows", "--units-row",
                     "--no-units-row"}
    shown = {command: {flag: text for flag, text in _help_flags(command).items()
                       if flag in flags}
             for command in ("fit", "select", "plot", "predict", "backbone")}
    assert set(shown["fit"]) == flags
    assert shown["fit"] == shown["select"] == shown["plot"] == shown["predict"] \
        == shown["backbone"]


@pytest.mark.parametrize(("command", "groups"), [
    ("fit", list(OPTION_GROUPS)), ("select", ["reading", "velocities"]), ("plot", ["reading"]),
    ("predict", ["reading"]), ("backbone", ["reading"]),
])
def test_the_help_lists_each_groups_options_under_its_heading(command, groups):
    sections = _help_sections(command)
    headings = {"reading": "Reading options", "velocities": "Velocity options",
                "method": "Method options", "covariance": "Covariance options",
                "run": "Run options"}
    assert list(sections) == ["Options", *(headings[group] for group in groups)]
    for group in groups:
        shown = [re.match(r"  (--[a-z-]+)", line) for line in sections[headings[group]]]
        declared = _command(getattr(option_groups, group)).params
        assert [match[1] for match in shown if match] == [p.opts[0] for p in declared]


def test_select_lists_the_velocity_options_as_fit_does():
    fit, select = _help_flags("fit"), _help_flags("select")
    for flag in ("--velocity", "--window", "--order"):
        assert select[flag] == fit[flag]


@pytest.fixture(scope="module")
def positions(tmp_path_factory):
    """The Duffing sample without its velocity column."""
    path = tmp_path_factory.mktemp("positions") / "positions.csv"
    pd.read_csv(SAMPLE, comment="#").drop(columns="v").to_csv(path, index=False)
    return path


def test_select_derives_velocities_as_fit_does(positions):
    """`--velocity savgol` on positions alone: the sample's terms, their known values
    (E = v^2/2 + k x^2/2 + k3 x^4/4, k = 1, k3 = 0.5), refitted with derived velocities."""
    done = CliRunner().invoke(cli, ["select", str(positions), "--library", "poly:1:4",
                                    "--columns", "q1=x", "--velocity", "savgol",
                                    "--format", "json"], prog_name="hamid")
    assert done.exit_code == 0, done.output
    report = json.loads(done.stdout)
    assert report["chosen"] == ["q1**2", "q1**4"]
    assert report["fit"]["data"]["velocity_source"] == "savgol"
    estimates = {p["name"]: p["estimate"] for p in report["fit"]["parameters"]}
    assert estimates == pytest.approx({"c_2": 0.5, "c_4": 0.125}, rel=1e-6)


def test_select_refuses_velocity_options_without_savgol_as_fit_does(positions):
    done = CliRunner().invoke(cli, ["select", str(positions), "--library", "poly:1:4",
                                    "--columns", "q1=x", "--window", "11"], prog_name="hamid")
    assert done.exit_code == 2 and done.stdout == ""
    assert "--window and --order apply only to --velocity savgol" in done.stderr


def test_select_takes_the_velocity_keywords(positions):
    chosen = hamid.select(positions, "poly:1:4", columns={"q1": "x"}, velocity="savgol",
                          window=11)
    assert chosen.chosen == ["q1**2", "q1**4"]
    assert chosen.fit.to_dict()["data"]["velocity_window"] == 11
    with pytest.raises(TypeError, match="'cov'"):
        hamid.select(positions, "poly:1:4", cov="hc")
