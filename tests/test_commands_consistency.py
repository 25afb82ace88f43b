"""Every ``smart-marl`` subcommand behaves like the others: ``--help`` with a description and a help
text on every option, exit code 2 on bad arguments (argparse's and the value checks in ``run``,
with ``smart-marl CMD: error: ...`` on stderr), 1 on bad input naming the file, ``--seed`` where
there is randomness, ``--device`` where a model runs, ``--out`` for the folder a command writes,
and one example per command in the README.

The commands are discovered from the parser, so a new subcommand is checked as soon as it is
registered (in ``smart_marl.cli._COMMAND_MODULES`` or through the
``smart_marl.commands`` entry-point group)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from smart_marl import cli
from smart_marl.cli import build_parser, main
from smart_marl.commands.arguments import seed as seed_type

README = Path(__file__).resolve().parents[1] / "README.md"

# what each command does, and so which of the shared flags it must take
RANDOM = {"demo", "generate-sumo", "vocab build", "train", "eval", "finetune", "whatif"}  # --seed
RUNS_A_MODEL = {"train", "eval", "finetune", "whatif"}  # --device (plus any command taking --checkpoint)
WRITES_A_FOLDER = {"preprocess", "demo", "generate-sumo", "vocab build", "train", "whatif"}  # --out DIR
# finetune writes its run folder from its config's out_dir (issue 9 part 1, not checked here yet)


def _leaf_parsers() -> dict[str, argparse.ArgumentParser]:
    """'info' -> its parser, 'vocab build' -> the nested one, ..."""
    out = {}

    def walk(prefix, parser):
        nested = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not nested:
            out[prefix] = parser
            return
        for name, sub in nested[0].choices.items():
            walk(f"{prefix} {name}".strip(), sub)

    walk("", build_parser())
    return out


COMMANDS = _leaf_parsers()
NAMES = sorted(COMMANDS)


def _options(parser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings}


def _exit_code(argv, capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return int(code or 0), out.out, out.err


def test_the_commands_are_all_registered():
    assert {"info", "preprocess", "demo", "train", "models", "generate-sumo", "vocab build", "eval", "whatif"} <= set(NAMES)


def test_cli_docstring_documents_the_exit_codes():
    doc = " ".join(cli.__doc__.split())
    assert "0 success" in doc and "1 the job failed on bad input" in doc and "2 bad arguments" in doc


@pytest.mark.parametrize("name", NAMES)
def test_help_exits_0_with_a_description_and_a_help_text_on_every_option(name, capsys):
    code, out, _ = _exit_code([*name.split(), "--help"], capsys)
    assert code == 0
    assert out.startswith(f"usage: smart-marl {name}")
    parser = COMMANDS[name]
    assert parser.description and len(parser.description) > 30
    missing = [a.option_strings or a.dest for a in parser._actions if a.help is None]
    assert not missing, f"smart-marl {name}: options without a help text: {missing}"


@pytest.mark.parametrize("name", NAMES)
def test_an_unknown_option_exits_2_with_the_usage(name, capsys):
    code, _, err = _exit_code([*name.split(), "--no-such-option"], capsys)
    assert code == 2 and "usage: smart-marl" in err


@pytest.mark.parametrize("name", [n for n in NAMES if any(a.required for a in COMMANDS[n]._actions if a.nargs != "*")])
def test_missing_required_arguments_exit_2(name, capsys):
    code, _, err = _exit_code(name.split(), capsys)
    assert code == 2 and "required" in err


def test_no_command_exits_2(capsys):
    code, _, err = _exit_code([], capsys)
    assert code == 2 and "COMMAND" in err


@pytest.mark.parametrize("name", NAMES)
def test_shared_flags_where_the_command_needs_them(name):
    opts = _options(COMMANDS[name])
    if name in RANDOM:
        assert "--seed" in opts and opts["--seed"].type is seed_type, f"smart-marl {name} has randomness but no checked --seed"
    if name in RUNS_A_MODEL or "--checkpoint" in opts:
        assert "--device" in opts, f"smart-marl {name} runs a model but has no --device"
    if name in WRITES_A_FOLDER:
        assert "--out" in opts, f"smart-marl {name} writes files but has no --out"
    for flag in ("--seed", "--device", "--out", "--json", "--format"):
        if flag in opts:  # one spelling, one meaning: no short aliases or alternative names
            assert opts[flag].option_strings == [flag]


@pytest.mark.parametrize("argv", [
    ["generate-sumo", "--scenes", "0", "--out", "OUT"],
    ["vocab", "build", "SRC", "--sizes", "big", "--out", "OUT"],
    ["eval", "--scenes", "SRC", "--policy", "random", "--rollouts", "0"],
    ["whatif", "SRC", "--script", "S.yaml", "--out", "OUT", "--rollouts", "0"],
    ["whatif", "SRC", "--script", "S.yaml", "--out", "OUT", "--device", "banana"],
], ids=lambda a: " ".join(a[:2]))
def test_bad_values_exit_2_before_any_work_with_an_error_line(argv, tmp_path, capsys):
    argv = [str(tmp_path / a) if a in ("OUT", "SRC", "S.yaml") else a for a in argv]
    code, _, err = _exit_code(argv, capsys)
    assert code == 2
    assert f"smart-marl {argv[0]}" in err and "error:" in err
    assert not (tmp_path / "OUT").exists()


@pytest.mark.parametrize("argv", [
    ["info", "MISSING"],
    ["preprocess", "MISSING", "--out", "OUT", "--quiet"],
    ["vocab", "build", "MISSING", "--out", "OUT", "--no-progress"],
    ["eval", "--scenes", "MISSING", "--policy", "constant_velocity"],
    ["whatif", "MISSING", "--script", "MISSING", "--out", "OUT"],
    ["train", "--config", "MISSING", "--print-config"],
], ids=lambda a: a[0])
def test_bad_input_exits_1_naming_the_file(argv, tmp_path, capsys):
    missing = tmp_path / "missing.tfrecord"
    argv = [str(missing) if a == "MISSING" else str(tmp_path / "out") if a == "OUT" else a for a in argv]
    code, _, err = _exit_code(argv, capsys)
    assert code == 1
    assert str(missing) in err and f"smart-marl {argv[0]}: error:" in err


@pytest.mark.parametrize("name", NAMES)
def test_readme_has_an_example_of_every_command(name):
    assert f"smart-marl {name}" in README.read_text(), f"README.md has no example of `smart-marl {name}`"


def test_train_flags_set_the_config_fields(capsys, tmp_path):
    code, out, _ = _exit_code(["train", "--config", "smart-1m", "--out", str(tmp_path / "run"), "--seed", "7", "--device", "cpu",
                               "seed=3", "--print-config"], capsys)
    assert code == 0
    import json

    cfg = json.loads(out)
    assert (cfg["out_dir"], cfg["seed"], cfg["device"]) == (str(tmp_path / "run"), 7, "cpu")  # the flag wins
