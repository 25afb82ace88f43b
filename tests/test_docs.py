"""The front door (issue 35 items 1 and 2): the README a newcomer reads, the documentation site built
from docs/, and every command they show.

- The README stays short (<= 250 lines) and its tables stay true: the environment's arguments and
  defaults are the constructor's, its ``infos`` keys are what a step returns, the extras are
  pyproject's, the realism rows are the model card's.
- The site builds with Sphinx, warnings as errors (broken links and anchors, autodoc failures).
- Every shell command in the README and docs/ is accounted for. Each ``smart-marl`` command parses
  with the real parser, and a ``train`` or ``finetune`` one resolves its config (``--print-config``),
  on every page, the dated experiment logs included; each benchmark command names flags its script
  defines; each ``python -c`` imports what it uses. Each command of the README and the user pages
  (not the experiment logs, which record runs of hours) is also mapped to the test that runs it, or
  run here: the what-if command, and (slow) the walk-through from WOMD files to a trained prior and
  the Python examples.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import inspect
import io
import json
import re
import runpy
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README] + sorted(DOCS.rglob("*.md"))
USER_PAGES = [p for p in PAGES if "experiments" not in p.relative_to(ROOT).parts]
SHARED = ROOT.parent / "shared" / "data"


# ------------------------------------------------------------------------------ extraction
def fenced_blocks(path: Path, langs: tuple[str, ...]) -> list[tuple[int, str]]:
    """(first line number, text) of every fenced code block of one of ``langs``."""
    out, lang, start, lines = [], None, 0, []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("```"):
            if lang is None:
                lang, start, lines = line[3:].strip() or "text", i + 1, []
            else:
                if lang in langs:
                    out.append((start, "\n".join(lines) + "\n"))
                lang = None
        elif lang is not None:
            lines.append(line)
    return out


def shell_commands(path: Path) -> list[tuple[str, str]]:
    """(``file:line``, command) of every command in the page's bash blocks: backslash continuations
    joined, comments and blank lines left out."""
    out = []
    for start, text in fenced_blocks(path, ("bash", "sh", "console")):
        buf, first = "", start
        for i, line in enumerate(text.splitlines(), start):
            s = line.strip()
            if not buf:
                first = i
            if s.endswith("\\"):
                buf += s[:-1] + " "
                continue
            buf += s
            if buf and not buf.startswith("#"):
                out.append((f"{path.relative_to(ROOT)}:{first}", buf))
            buf = ""
    return out


ALL_COMMANDS = [c for p in PAGES for c in shell_commands(p)]
USER_COMMANDS = [c for p in USER_PAGES for c in shell_commands(p)]


def smart_marl_argv(command: str) -> list[str] | None:
    """The argv after ``smart-marl`` (a ``for`` loop's body with its variable set; or after
    ``torchrun [its options] -m smart_marl.cli``), or None."""
    loop = re.fullmatch(r"for (\w+) in (\S+)[^;]*; do (.*); done", command)
    if loop:
        command = loop.group(3).replace("$" + loop.group(1), loop.group(2))
    words = shlex.split(command)
    if words and words[0].endswith("torchrun") and "-m" in words:
        at = words.index("-m")
        return words[at + 2:] if words[at + 1:at + 2] == ["smart_marl.cli"] else None
    if not words or not words[0].endswith("smart-marl"):
        return None
    return words[1:]


def section(path: Path, heading: str) -> str:
    """The text of a ``## heading`` section."""
    text = path.read_text()
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else None]


def table_rows(text: str) -> list[list[str]]:
    """The body rows of the first Markdown table in ``text``, cells stripped."""
    rows = [line for line in text.splitlines() if line.startswith("|")]
    return [[c.strip() for c in r.strip("|").split("|")] for r in rows[2:]]


# ---------------------------------------------------------------------------------- README
def test_the_readme_is_at_most_250_lines():
    assert len(README.read_text().splitlines()) <= 250


def test_the_readme_set_up_and_test_commands_are_the_ones_ci_runs():
    """The two set-up commands, the main command and the test command; CI runs the same lines."""
    readme = [c for _, c in shell_commands(README)]
    for command in ('python3 -m venv .venv', '.venv/bin/pip install -c constraints.txt -e ".[dev]"',
                    ".venv/bin/smart-marl demo", ".venv/bin/python -m pytest -q"):
        assert command in readme
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert "python3 -m venv .venv" in ci
    assert '.venv/bin/pip install -q -c constraints.txt -e ".[dev]"' in ci  # the README's, quiet
    assert ".venv/bin/python -m pytest -q" in ci
    slow = [line for line in ci if line.startswith(".venv/bin/python -m pytest -q -m slow")]
    assert slow and all((ROOT / f).is_file() for f in slow[0].split()[6:])
    tests_in_ci = [line for line in ci if line.startswith(".venv/bin/python -m pytest")]
    assert tests_in_ci and all(line in readme for line in tests_in_ci), "every test command CI runs is in the README"


def test_the_gpu_recipe_keeps_an_installed_torch():
    """The GPU recipe installs a CUDA torch first, then the package without constraints: that keeps
    the installed build only while no requirement of the package pins torch (no ``==``, no upper bound)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = project["dependencies"] + [r for extra in project["optional-dependencies"].values() for r in extra]
    torch = [r for r in reqs if re.match(r"torch\b(?!rl|vision)", r)]
    assert torch == ["torch>=2.3"]
    recipe = [c for _, c in shell_commands(README) if "download.pytorch.org" in c]
    assert recipe and recipe[0].startswith(".venv/bin/pip install torch --index-url ")


def test_the_extras_table_lists_every_extra_of_the_package():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    rows = table_rows(section(README, "Install"))
    extras = {r[0].strip("`"): r[1] for r in rows}
    assert set(extras) == set(project["optional-dependencies"])
    for name, brings in extras.items():
        if name == "dev":
            continue
        listed = {w.strip() for w in brings.split(",")}
        packages = {re.split(r"[<>=!~\[ ]", r)[0] for r in project["optional-dependencies"][name]}
        assert listed <= packages, (name, listed - packages)


def test_the_environment_table_is_the_constructors_signature():
    """Every argument of SmartTrafficEnv, in order, with its default."""
    from envs.smart_traffic_v0 import SmartTrafficEnv

    params = [p for p in inspect.signature(SmartTrafficEnv.__init__).parameters.values() if p.name != "self"]
    for page in (README, DOCS / "environment.md"):
        text = section(page, "The environment") if page == README else section(page, "Arguments")
        rows = table_rows(text)
        assert [r[0].strip("`") for r in rows] == [p.name for p in params], page.name
        for row, p in zip(rows, params):
            default = p.default if p.default is not None else None
            if isinstance(default, (tuple, list)):
                default = tuple(default)
            assert ast.literal_eval(row[1].strip("`")) == default, (page.name, p.name)


def test_the_readme_environment_example_runs_and_the_infos_keys_are_the_environments():
    code = fenced_blocks(README, ("python",))[0][1]
    assert "parallel_env(" in code
    namespace: dict = {}
    exec(compile(code, f"{README}:python-block-1", "exec"), namespace)
    infos = namespace["infos"]
    assert namespace["env"].agents == [] and infos  # the episode ran to its end
    keys = set(next(iter(infos.values())))
    text = section(README, "The environment")
    listed = set(re.findall(r"`(\w+)`", text[text.index("**`infos[agent]`**"):text.index("**TorchRL.**")]))
    assert keys <= listed, f"infos keys the README does not name: {sorted(keys - listed)}"
    page = section(DOCS / "environment.md", "`infos`")
    assert keys <= set(re.findall(r"`(\w+)`", page))


def test_the_readme_realism_table_is_the_model_cards():
    readme = table_rows(section(README, "The shipped prior"))
    card = table_rows(section(DOCS / "model_card.md", "Evaluation"))
    assert readme and readme == card[:len(readme)]


def test_the_readme_whatif_command_runs(tmp_path, monkeypatch, capsys):
    """The README's what-if command on the embedded scenes, shortened (1 rollout of 4 steps: the brake starts at 1 s)."""
    from smart_marl.cli import main

    command = next(c for _, c in shell_commands(README) if " whatif " in c)
    monkeypatch.chdir(tmp_path)
    argv = smart_marl_argv(command) + ["--rollouts", "1", "--steps", "4", "--no-realism", "--animation", "none"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "lead car brakes hard" in out and "52 (brake)" in out
    assert (tmp_path / "out" / "whatif" / "table.csv").is_file()


# --------------------------------------------------------------------------- the site
def test_the_docs_build_with_warnings_as_errors(tmp_path):
    pytest.importorskip("sphinx", reason="the docs extra is not installed")
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS),
                           str(tmp_path / "html")], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-5000:]
    html = (tmp_path / "html" / "api" / "envs.html").read_text()
    assert "parallel_env" in html and "SmartTrafficEnv" in html  # autodoc imported the modules
    assert (tmp_path / "html" / "experiments" / "2026-11-23-prior-stages.html").is_file()


def test_every_page_is_in_the_site():
    """A page outside every toctree is a warning under -W only when Sphinx sees it; this names it."""
    listed = set()
    for page in DOCS.rglob("*.md"):
        for _, block in fenced_blocks(page, ("{toctree}",)):
            base = page.parent.relative_to(DOCS)
            listed |= {(base / line.strip()).as_posix() for line in block.splitlines() if line.strip() and not line.startswith(":")}
    pages = {p.relative_to(DOCS).with_suffix("").as_posix() for p in DOCS.rglob("*.md")} - {"index"}
    assert pages <= listed, sorted(pages - listed)


# ------------------------------------------------------------------------- the commands
CUDA_FREE = {"--device": "cpu"}  # `--device cuda` is refused by the argument check on a machine without a GPU


def _print_config_or_parse(argv: list[str], capsys) -> None:
    from smart_marl.cli import build_parser, main

    argv = [CUDA_FREE.get(prev, a) if prev in CUDA_FREE and a == "cuda" else a for prev, a in zip([""] + argv, argv)]
    if argv[0] in ("train", "finetune") and "--evaluate" not in argv and "--select" not in argv:  # those two run, not configure
        code = main(argv + ["--print-config"])
        capsys.readouterr()
        assert code == 0, f"smart-marl {' '.join(argv)} --print-config exited {code}"
    else:
        build_parser().parse_args(argv)  # argparse exits 2 on an unknown flag or a bad value


def _help_flags(name: str, run, path: list[str]) -> frozenset[str]:
    """The options in the ``--help`` of ``run()`` (a script or a module run as ``__main__`` in this process,
    ``sys.argv[0]`` = ``name``, ``path`` put first on ``sys.path`` meanwhile)."""
    out = io.StringIO()
    argv, saved = sys.argv, list(sys.path)
    sys.argv, sys.path[:0] = [name, "--help"], path
    try:
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
            run()
    finally:
        sys.argv, sys.path[:] = argv, saved
    return frozenset(re.findall(r"(--[\w-]+)", out.getvalue()))


@functools.lru_cache(maxsize=None)
def _script_flags(script: Path) -> frozenset[str]:
    """The options a benchmark script's parser defines."""
    return _help_flags(str(script), lambda: runpy.run_path(str(script), run_name="__main__"), [str(script.parent)])


@pytest.mark.parametrize("where,command", ALL_COMMANDS, ids=[w for w, _ in ALL_COMMANDS])
def test_every_documented_command_names_what_exists(where, command, capsys):
    argv = smart_marl_argv(command)
    words = shlex.split(command.split(" > ")[0])
    if argv is not None:
        _print_config_or_parse(argv, capsys)
    elif words[:1] == [".venv/bin/python"] and words[1].startswith("benchmarks/"):
        script = ROOT / words[1]
        assert script.is_file()
        unknown = {w.split("=")[0] for w in words[2:] if w.startswith("--")} - _script_flags(script)
        assert not unknown, f"{script.name} defines no {sorted(unknown)}"
    elif words[:2] == [".venv/bin/python", "-m"] and words[2].startswith("smart_marl."):
        unknown = {w.split("=")[0] for w in words[3:] if w.startswith("--")} - _module_flags(words[2])
        assert not unknown, f"{words[2]} defines no {sorted(unknown)}"
    elif words[:2] == [".venv/bin/python", "-c"]:
        tree = ast.parse(words[2])
        imports = ast.Module([n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))], [])
        exec(compile(imports, where, "exec"), {})
    elif words[:3] == [".venv/bin/python", "-m", "pytest"]:
        assert all((ROOT / w).is_file() for w in words[3:] if w.startswith("tests/"))
    else:
        assert command in COVERED_ELSEWHERE, f"{where}: no check for {command!r}"


COVERED_ELSEWHERE = {  # commands whose check is a test of this file, named here
    "python3 -m venv .venv": "test_the_readme_set_up_and_test_commands_are_the_ones_ci_runs",
    '.venv/bin/pip install -c constraints.txt -e ".[dev]"': "test_the_readme_set_up_and_test_commands_are_the_ones_ci_runs",
    ".venv/bin/pip install torch --index-url https://download.pytorch.org/whl/cu126": "test_the_gpu_recipe_keeps_an_installed_torch",
    '.venv/bin/pip install -e ".[dev]"': "test_the_gpu_recipe_keeps_an_installed_torch",
    ".venv/bin/sphinx-build -W -b html docs docs/_build/html": "test_the_docs_build_with_warnings_as_errors",
    "tar czf submission.tar.gz -C runs/val $(cd runs/val && ls submission.binproto-*)":
        "test_the_submission_upload_command_packs_every_file_of_the_set",
}

@functools.lru_cache(maxsize=None)
def _module_flags(module: str) -> frozenset[str]:
    """The options a package module run with ``python -m`` defines."""
    return _help_flags(module, lambda: runpy.run_module(module, run_name="__main__", alter_sys=False), [])


# Each command of the README and the user pages -> the tests that run it (a test of this file, or
# another module's, whose source holds the needle: the command's words as that test spells them).
RUN_BY = [
    (r"^python3 -m venv|pip install -c constraints|^\.venv/bin/python -m pytest",
     [("tests/test_docs.py::test_the_readme_set_up_and_test_commands_are_the_ones_ci_runs", ".ci")]),
    (r"pip install torch --index-url|pip install -e \"\.\[dev\]\"$",
     [("tests/test_docs.py::test_the_gpu_recipe_keeps_an_installed_torch", "torch")]),
    (r"sphinx-build", [("tests/test_docs.py::test_the_docs_build_with_warnings_as_errors", '"sphinx"')]),
    (r"smart-marl demo", [("tests/test_cli.py::test_demo_simulates_the_sample_scenes_with_the_embedded_prior", '"demo"'),
                          ("tests/test_wheel.py::test_the_demo_runs_from_the_wheel", '"demo"')]),
    (r"smart-marl finetune --config tiny$",
     [("tests/test_wheel.py::test_the_named_finetune_config_ships_with_the_wheel", '"--config", "tiny"')]),
    (r"smart-marl finetune --evaluate",
     [("tests/test_finetune.py::test_policy_checkpoint_round_trips_and_evaluate_command_prints_the_table", '"--evaluate"')]),
    (r"smart-marl whatif embedded",
     [("tests/test_docs.py::test_the_readme_whatif_command_runs", "main(argv)"),
      ("tests/test_wheel.py::test_a_shipped_whatif_example_runs_on_the_embedded_scenes", '"whatif", "embedded"')]),
    (r"path/to/womd|data/womd_(cache|vocab|tokens)|runs/womd",
     [("tests/test_docs.py::test_the_training_walkthrough_runs_end_to_end", "main(argv)")]),
    (r"smart-marl info ", [("tests/test_cli.py::test_info_on_the_real_womd_file", '"info"')]),
    (r"smart-marl preprocess \.\./shared", [("tests/test_cli.py::test_preprocess_skip_bad_reports_and_goes_on", '"preprocess"')]),
    (r"smart-marl generate-sumo",
     [("tests/test_sumo.py::test_generate_sumo_command_writes_a_cache_that_reads_back", '"generate-sumo"'),
      ("tests/test_sumo.py::test_no_parked_cars_flag_and_a_bad_occupancy_range", '"--no-parked-cars"'),
      ("tests/test_sumo.py::test_speed_limits_are_drawn_from_the_configured_levels_and_weights", "--speed-limits")]),
    (r"smart-marl vocab build data/sumo", [("tests/test_tokens.py::test_cli_vocab_build_writes_loadable_files", '"vocab", "build"')]),
    (r"smart-marl vocab transfer embedded --motion-vocab vocab/",
     [("tests/test_vocab_transfer.py::test_vocab_transfer_command_writes_a_checkpoint_that_loads_with_the_new_vocabulary",
       '"vocab", "transfer"'),
      ("tests/test_vocab_transfer.py::test_transfer_of_one_type_keeps_the_other_types_tokens_and_head_rows_exactly", '"--types"')]),
    (r"smart-marl models", [("tests/test_train.py::test_models_command_prints_every_named_config_with_its_parameter_count", '"models"')]),
    (r"smart-marl train --config smart-1m data=data/sumo",
     [("tests/test_docs.py::test_the_training_walkthrough_runs_end_to_end", "main(argv)"),
      ("tests/test_train.py::test_train_only_trains_the_named_parameters_and_freezes_the_rest", "train_only"),
      ("tests/test_train.py::test_a_run_records_the_mixed_in_data_and_rejects_a_bad_share", "extra_data")]),
    (r"smart-marl pretokenize data/sumo", [("tests/test_token_cache.py::test_cli_pretokenize", '"pretokenize"')]),
    (r"smart-marl pretokenize data/scaling_train",
     [("tests/test_scaling.py::test_the_scaling_command_runs_a_tiny_grid_and_resumes_without_training_again", '"pretokenize"')]),
    (r"smart-marl eval --scenes (\.\./shared\S*|DIR) --policy prior",
     [("tests/test_avoidance.py::test_eval_hands_the_flag_to_the_rollouts", '"eval"'),
      ("tests/test_metrics_submission.py::test_eval_policy_prior_scores_the_rollout_engines_rollouts", '"eval"')]),
    (r"smart-marl eval --scenes \.\./shared\S* --policy constant_velocity",
     [("tests/test_metrics_submission.py::test_eval_command_scores_a_written_policy_submission_identically", '"eval"')]),
    (r"benchmarks/", [("tests/test_docs.py::test_every_documented_command_names_what_exists", "_script_flags")]),
    (r"-m smart_marl\.prior_rl ", [("tests/test_prior_rl.py::test_the_command_line_runs_and_resumes", "main(args"),
                                   ("tests/test_docs.py::test_every_documented_command_names_what_exists", "_module_flags")]),
    (r"smart-marl finetune --config scale|smart_marl\.cli finetune --config scale",
     [("tests/test_docs.py::test_the_scale_finetune_commands_run_on_a_small_pool", "main(argv)")]),
    # the launcher: two processes fine-tuning one policy (the test starts them with a script calling finetune())
    (r"torchrun .*-m smart_marl\.cli finetune",
     [("tests/test_finetune_distributed.py::test_two_processes_under_torchrun_train_one_policy", '"--nproc_per_node=2"')]),
    (r"smart-marl eval --scenes VAL/ --policy prior --out runs/val --write-submission",
     [("tests/test_eval_sharding.py::test_merged_submission_files_hold_exactly_the_plain_rollouts", '"--write-submission"'),
      ("tests/test_eval_sharding.py::test_a_killed_process_resumes_to_the_uninterrupted_result", '"--out"')]),
    (r"smart-marl eval .*--shard |smart-marl eval --merge ",
     [("tests/test_eval_sharding.py::test_prior_rollouts_do_not_depend_on_the_split", '"--shard"'),
      ("tests/test_eval_sharding.py::test_prior_rollouts_do_not_depend_on_the_split", '"--merge"')]),
    (r"torchrun .*-m smart_marl\.cli eval",
     [("tests/test_eval_sharding.py::test_torchrun_ranks_take_their_shards_and_rank0_merges",
       '"--nproc_per_node=2", "-m", "smart_marl.cli", "eval"')]),
    (r"smart-marl eval --scenes VAL/ --submission ",
     [("tests/test_eval_sharding.py::test_merged_submission_files_hold_exactly_the_plain_rollouts", '"--submission"')]),
    (r"^tar czf submission\.tar\.gz", [("tests/test_docs.py::test_the_submission_upload_command_packs_every_file_of_the_set",
                                        "subprocess.run")]),
]


@functools.lru_cache(maxsize=None)
def _parsed(file: str) -> ast.Module:
    return ast.parse((ROOT / file).read_text())


def _test_source(test_id: str) -> str:
    file, name = test_id.split("::")
    tree = _parsed(file)
    fn = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == name), None)
    assert fn is not None, f"{test_id} does not exist"
    return ast.get_source_segment((ROOT / file).read_text(), fn)


@pytest.mark.parametrize("where,command", USER_COMMANDS, ids=[w for w, _ in USER_COMMANDS])
def test_every_command_of_the_readme_and_the_user_pages_is_run_by_a_test(where, command):
    tests = [t for pattern, ts in RUN_BY if re.search(pattern, command) for t in ts]
    assert tests, f"{where}: no test runs {command!r}; add one to RUN_BY"
    for test_id, needle in tests:
        assert needle in _test_source(test_id), f"{test_id} does not run {needle}"


def test_every_coverage_entry_is_used():
    for pattern, _ in RUN_BY:
        assert any(re.search(pattern, c) for _, c in USER_COMMANDS), f"RUN_BY entry {pattern!r} matches no command"
    assert set(COVERED_ELSEWHERE) <= {c for _, c in ALL_COMMANDS}


def test_the_submission_upload_command_packs_every_file_of_the_set(tmp_path):
    """The evaluation-at-scale page's tar command, run as shown on a run folder holding a split submission."""
    command = next(c for _, c in shell_commands(DOCS / "evaluation_at_scale.md") if c.startswith("tar "))
    run = tmp_path / "runs" / "val"
    (run / "shard-00000-of-00002").mkdir(parents=True)
    names = [f"submission.binproto-{i:05d}-of-00003" for i in range(3)]
    for name in names + ["result.json", "run.json"]:
        (run / name).write_bytes(name.encode())
    proc = subprocess.run(["bash", "-c", command], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    listing = subprocess.run(["tar", "tzf", "submission.tar.gz"], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert listing.stdout.split() == names  # the files at the archive's top level, as the challenge takes them


@pytest.mark.slow
def test_the_scale_finetune_commands_run_on_a_small_pool(tmp_path, monkeypatch, capsys):
    """The ``scale`` config's commands (README, RL at scale), shortened: the package's 4 sample scenes,
    2 at a time, one short iteration, no evaluation; the config's network, critic and pool as shipped."""
    from smart_marl.cli import main

    commands = [c for p in (README, DOCS / "scale.md") for _, c in shell_commands(p) if "finetune --config scale" in c]
    assert commands
    monkeypatch.chdir(tmp_path)
    for command in dict.fromkeys(commands):
        argv = smart_marl_argv(command) + ["scenes=embedded", "num_scenes=4", "num_envs=2", "horizon_steps=2", "iterations=1",
                                           "frames_per_batch=8", "minibatch_size=8", "ppo_epochs=1", "eval_episodes=0",
                                           "tensorboard=false", "--out", "runs/ft"]
        assert main(argv) == 0, f"smart-marl {' '.join(argv)}\n{capsys.readouterr().err[-3000:]}"
        assert (tmp_path / "runs" / "ft" / "checkpoints" / "policy_last.json").is_file()


# ------------------------------------------------------------------ slow: running them
# The walk-through on small inputs: the real WOMD records of ../shared/data when present, else the
# package's sample scenes; vocabularies of 64/32/4 tokens (the one WOMD record holds 10 cyclist snippets); two training steps; two rollouts.
WALKTHROUGH_SUBSTITUTIONS = {
    "--sizes 1024/512/512": "--sizes 64/32/4", "motion_1024-512-512.npz": "motion_64-32-4.npz",
    "--road-size 1024": "--road-size 64", "road_1024.npz": "road_64.npz",
    "max_steps=2000": "max_steps=2 batch_size=2 num_workers=0 val_every=1000 ckpt_every=1000",
    "max_steps=20000": "max_steps=2 batch_size=2 num_workers=0 val_every=1000 ckpt_every=1000",
    "--workers 2": "--workers 1",
}
WALKTHROUGH_EXTRA = {"eval": ["--rollouts", "2"], "finetune": ["iterations=1", "eval_episodes=0", "--out", "runs/ft"],
                     "preprocess": ["--quiet"], "pretokenize": ["--quiet"], "vocab build": ["--no-progress"],
                     "train": ["progress=false", "tensorboard=false"]}


@pytest.mark.slow
def test_the_training_walkthrough_runs_end_to_end(tmp_path, monkeypatch, capsys):
    """README "Training a prior on your own WOMD files", then the training page's from-scratch recipe."""
    from smart_marl.cli import main
    from smart_marl.embedded import SAMPLES_DIR

    src = SHARED / "womd_tfrecord" if SHARED.is_dir() else SAMPLES_DIR
    readme = [c for _, c in shell_commands(README) if re.search(r"path/to/womd|data/womd_|runs/womd", c)]
    scratch = [c for _, c in shell_commands(DOCS / "training.md") if "womd_vocab_full" in c]
    assert [smart_marl_argv(c)[0] for c in readme] == ["preprocess", "vocab", "vocab", "pretokenize", "train", "eval", "finetune"]
    assert len(scratch) == 2
    monkeypatch.chdir(tmp_path)
    for command in readme + scratch:
        for a, b in WALKTHROUGH_SUBSTITUTIONS.items():
            command = command.replace(a, b)
        command = command.replace("path/to/womd/training", str(src)).replace("path/to/womd/validation", str(src))
        argv = smart_marl_argv(command)
        name = " ".join(argv[:2]) if argv[0] == "vocab" else argv[0]
        extra = WALKTHROUGH_EXTRA.get(name, [])
        kv = [i for i, a in enumerate(argv) if "=" in a and not a.startswith("-")]
        at = kv[-1] + 1 if kv else len(argv)  # key=value overrides join the command's own (one positional run)
        argv = argv[:at] + [a for a in extra if "=" in a] + argv[at:] + [a for a in extra if "=" not in a]
        assert main(argv) == 0, f"smart-marl {' '.join(argv)}\n{capsys.readouterr().err[-3000:]}"
        capsys.readouterr()
    assert (tmp_path / "runs" / "womd" / "checkpoints" / "final.json").is_file()
    assert (tmp_path / "runs" / "womd_scratch" / "checkpoints" / "final.json").is_file()
    assert (tmp_path / "runs" / "ft" / "checkpoints" / "policy_last.json").is_file()
    cfg = json.loads((tmp_path / "runs" / "ft" / "config.json").read_text())
    assert cfg["prior"] == "runs/womd/checkpoints/final.json"  # the fine-tuning ran on the trained prior


# Python examples: each page's python blocks run in order in one process, in a temporary folder.
# What is shortened for the test (each key must still be in the page, so a changed example fails here).
PYTHON_SUBSTITUTIONS = {
    '{"beta": 0.1, "out_dir": "runs/finetune_py"}': '{"beta": 0.1, "out_dir": "runs/finetune_py", "iterations": 1, "eval_episodes": 1}',
    "evaluate_checkpoint(result.checkpoint, episodes=4)": "evaluate_checkpoint(result.checkpoint, episodes=1)",
    '"num_scenes": 6,': '"num_scenes": 2,',
    '"eval_episodes": 32})': '"eval_episodes": 1, "iterations": 1, "eval_num_scenes": 1, "out_dir": "runs/ft_real"})',
    '"path/to/training.tfrecord-00000-of-01000"': f'"{SHARED / "womd_tfrecord"}"',
    "num_rollouts=4, seed=0, realism=False)": "num_rollouts=1, num_steps=4, seed=0, realism=False)",
    "seed=0,\n                    realism=False)": "num_steps=4, seed=0, realism=False)",
}
NEEDS_SHARED = ("../shared/data", "path/to/training")


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in USER_PAGES if fenced_blocks(p, ("python",))], ids=lambda p: p.name)
def test_the_python_examples_run(page, tmp_path):
    blocks = [code for _, code in fenced_blocks(page, ("python",))]
    if page != README:  # a block the README shows too has run in the README's test; its names are still defined
        readme = {code for _, code in fenced_blocks(README, ("python",))}
        blocks = [b if b not in readme else _definitions_only(b) for b in blocks]
    if not SHARED.is_dir():
        blocks = [b for b in blocks if not any(s in b for s in NEEDS_SHARED)]
    code = "\n".join(blocks)
    for a, b in PYTHON_SUBSTITUTIONS.items():
        code = code.replace(a, b)
    code = code.replace("../shared/data", str(SHARED))
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-4000:]


def _definitions_only(code: str) -> str:
    """The imports of ``code`` (what later blocks of the page use from it)."""
    tree = ast.parse(code)
    return ast.unparse([n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]) + "\n"


def test_every_python_substitution_is_used():
    text = "".join(code for p in USER_PAGES for _, code in fenced_blocks(p, ("python",)))
    unused = [a for a in PYTHON_SUBSTITUTIONS if a not in text]
    assert not unused, f"python examples changed; update PYTHON_SUBSTITUTIONS: {unused}"
    commands = " ".join(c for _, c in USER_COMMANDS)
    assert all(a in commands for a in WALKTHROUGH_SUBSTITUTIONS)
