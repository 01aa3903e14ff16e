"""``--help`` reads like a Unix tool's: upper-case metavars, never typer's ``<str>``."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from scanguard.cli import app

runner = CliRunner()


def help_text(*command: str) -> str:
    r = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    return r.output


@pytest.mark.parametrize(
    "command",
    [
        ["run"],
        ["run-many"],
        ["demo"],
        ["evaluate"],
        ["train"],
        ["calibrate"],
        ["simulate"],
        ["info"],
        ["dataset", "build"],
        ["dataset", "stats"],
        ["export", "onnx"],
    ],
)
def test_no_typer_type_labels(command: list[str]) -> None:
    text = help_text(*command)
    assert not re.search(r"<(str|int|float|bool|path|list\[\w+\])>", text), text
    assert "{" not in text.split("\n", 1)[0], text  # usage: RECORDING, not {recording}


def test_run_help_shows_unix_metavars() -> None:
    text = help_text("run")
    assert "Usage: scanguard run [OPTIONS] RECORDING" in text
    for shown in ("--out PATH", "--scan-topic TOPIC", "--backend NAME", "--particles INT"):
        assert shown in text, shown
    assert "--seed INT" in text and "--model PATH" in text


def test_evaluate_help_shows_unix_metavars() -> None:
    text = help_text("evaluate")
    for shown in ("--data PATH", "--runtime NAME", "--split NAME", "--workers INT", "--out PATH"):
        assert shown in text, shown
    assert "--backend" not in text  # renamed --runtime (a SLAM back end is run's --backend)


def test_simulate_help_shows_float_metavar() -> None:
    assert "--duration FLOAT" in help_text("simulate")


def test_commands_listed_in_registration_order() -> None:
    text = help_text()
    # typer lists the commands first, then the groups (dataset, export)
    names = ["info", "simulate", "train", "evaluate", "calibrate", "run", "demo", "run-many"]
    where = [text.index(f"\n  {n} ") for n in names]
    assert where == sorted(where), text
