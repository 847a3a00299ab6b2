"""Every command documents itself, and the config reference in docs/ matches the code."""

import importlib
import re
from pathlib import Path

import pytest

from cubetrack.cli.defaults import render
from cubetrack.cli.main import COMMANDS, main

DOCS = Path(__file__).resolve().parents[2] / "docs"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: cubetrack " + command) and len(out.splitlines()) > 3


def test_top_level_help_lists_every_command(capsys):
    """Each command has its own row in the command list: its name, then its one-line HELP (a bare
    ``command in out`` held for "track" inside "cubetrack" even with no row at all)."""
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    rows = re.findall(r"^ {4}(\S+)\s+(.*(?:\n {20,}.*)*)", out, flags=re.MULTILINE)
    listed = {name: " ".join(text.split()) for name, text in rows}
    assert sorted(listed) == sorted(COMMANDS)
    for command, module in COMMANDS.items():
        assert listed[command] == " ".join(importlib.import_module(f"cubetrack.cli.{module}").HELP.split()), command


def test_configuration_reference_is_current():
    text = (DOCS / "configuration.md").read_text(encoding="utf-8")
    assert render() in text, "docs/configuration.md is stale: regenerate it with `cubetrack defaults`"


def test_defaults_round_trip_through_the_config_loader(tmp_path):
    """Every section `cubetrack defaults` prints reads back as the defaults, and a section it
    does not know is refused with the file's name."""
    import tomllib

    from cubetrack.app.config import SECTIONS, ConfigParams, load_config
    from cubetrack.core.errors import ConfigError
    from cubetrack.core.layout import paper_cube_layout, write_layout
    from cubetrack.sink.output_params import OUTPUT_TYPES, output_params

    write_layout(paper_cube_layout(), tmp_path / "cube.toml")
    (tmp_path / "c.toml").write_text('[[robots]]\nname = "r"\nlayout = "cube.toml"\n' + render())
    printed = tomllib.loads(render())
    assert set(printed) == {*SECTIONS, "outputs"}
    assert load_config(tmp_path / "c.toml")[1] == ConfigParams()
    # one [[outputs]] table per output type, each read back as that type's defaults
    assert [output_params(t, "x") for t in printed["outputs"]] == [cls() for cls in OUTPUT_TYPES.values()]
    (tmp_path / "c.toml").write_text('[[robots]]\nname = "r"\nlayout = "cube.toml"\n[filtre]\nx = 1\n')
    with pytest.raises(ConfigError, match=r"c\.toml: unknown section\(s\) filtre; known: .*filter"):
        load_config(tmp_path / "c.toml")


def test_defaults_prints_one_section_and_refuses_an_unknown_one(capsys):
    assert main(["defaults", "--section", "bundle_adjustment"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("[bundle_adjustment]\n") and "max_span_s = 0.1" in out and "[filter]" not in out
    assert main(["defaults", "--section", "filtre"]) == 1
    assert "no such section" in capsys.readouterr().err
