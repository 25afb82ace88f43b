"""What-if scripts from untrusted files (issue 15 items 5, 6): every key's value is checked when the
script is loaded (a string where a time goes, a ragged path, an infinite deceleration...), tokens
against the prior's vocabulary before any rollout, the rollout length is bounded; and the fuzz:
mutated copies of the example scripts load and apply, or raise a WhatIfError naming the file."""

from __future__ import annotations

import json
import sys

import pytest
from hypothesis import strategies as st

from agents import whatif as whatif_module
from agents.whatif import edits as whatif_edits
from agents.whatif import EXAMPLES_DIR, MAX_STEPS, WhatIf, WhatIfError, load_script, prepare, run_whatif
from fuzzing import mutate_bytes, mutate_structure, run_fuzz
from smart_marl.errors import SmartMarlError

EXAMPLES = EXAMPLES_DIR  # written for the embedded sample scene sumo-7-000000-03
BUDGET = [pytest.param("default", id="default"), pytest.param("long", id="long", marks=pytest.mark.slow)]

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.mark.parametrize("text, problem", [
    ("edits: [{kind: brake, agent: 1609, at_s: soon}]", "edit 0: brake: at_s must be a finite number, got 'soon'"),
    ("edits: [{kind: brake, agent: 1609, decel_mps2: .inf}]", "brake: decel_mps2 must be a finite number, got inf"),
    ("edits: [{kind: follow, agent: 1645, path: [[0, 0], [20]]}]", "follow: path must be points of 2 numbers each"),
    ("edits: [{kind: insert, path: [[0, 0], [1, 1]], speed_mps: -3}]", "insert: speed_mps must be >= 0.0, got -3"),
    ("edits: [{kind: jaywalker, start: [0, 0], end: [1, nan]}]", "jaywalker: end must be 2 finite numbers"),
    ("edits: [{kind: brake, agent: [1609]}]", "brake: agent must be a track id or 'sdc'"),
    ("edits: [{kind: follow, agent: 1645, tokens: [1, -2]}]", "follow: tokens must be a non-empty list of token ids"),
    ("edits: [{kind: remove, agents: [1609], at_s: 1e999}]", "remove: at_s must be a finite number"),
])
def test_bad_values_in_a_script_are_named_when_it_is_loaded(tmp_path, text, problem):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(WhatIfError) as info:
        load_script(path)
    assert str(path) in str(info.value) and problem in str(info.value), str(info.value)


def test_out_of_vocabulary_tokens_are_refused_before_any_rollout(sample_scenes, sample_vocab, sample_model, tmp_path, monkeypatch):
    """Before: a follow with tokens outside the vocabulary failed after the baseline rollouts."""
    def no_rollout(*args, **kwargs):
        raise AssertionError("a rollout ran before the script was checked")

    monkeypatch.setattr(sys.modules["agents.whatif.compare"], "simulate", no_rollout)  # what run_whatif calls
    path = tmp_path / "tokens.yaml"
    path.write_text("edits: [{kind: follow, agent: 51, tokens: [3, 32, 40]}]")  # 51: sumo-7-000000-00's SDC, a vehicle
    with pytest.raises(WhatIfError, match=r"tokens.yaml: edit 0: tokens \[32, 40\] are outside the vehicle vocabulary \[0, 32\)"):
        run_whatif(sample_model, sample_scenes[0], load_script(path), num_rollouts=1, num_steps=2)
    with pytest.raises(WhatIfError, match=f"num_steps must be 1..{MAX_STEPS}"):
        run_whatif(sample_model, sample_scenes[0], load_script(path), num_rollouts=1, num_steps=1000)


def test_whatif_command_refuses_an_existing_file_as_out_before_simulating(sample_scene_file, tmp_path, capsys):
    from smart_marl.cli import main

    out = tmp_path / "table.csv"
    out.write_text("keep me")
    code = None
    try:
        code = main(["whatif", str(sample_scene_file), "--script",
                     str(EXAMPLES / "brake_hard.yaml"), "--out", str(out)])
    except SystemExit as exc:
        code = exc.code
    assert code == 2 and "argument --out" in capsys.readouterr().err and out.read_text() == "keep me"


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_whatif_scripts_apply_or_raise_a_named_error(tmp_path, budget):
    import yaml

    from smart_marl.embedded import sample_scenarios
    from smart_marl.model.checkpoint import load_prior

    scene = next(s for s in sample_scenarios() if s.scenario_id == "sumo-7-000000-03")
    vocab = load_prior("embedded")[1]

    bases = {p.name: yaml.safe_load(p.read_text()) for p in sorted(EXAMPLES.glob("*.yaml"))}
    names = sorted(bases)
    path = tmp_path / "script.yaml"

    def check(data):
        name = names[data.draw(st.integers(0, len(names) - 1), label="script")]
        if data.draw(st.integers(0, 2), label="structural?"):
            # JSON is YAML: the mutated structure written as JSON keeps NaN/Infinity readable (.nan / .inf in YAML)
            text = json.dumps(mutate_structure(data, bases[name]), default=str).replace("NaN", ".nan").replace("Infinity", ".inf")
            path.write_text(text)
        else:
            path.write_bytes(mutate_bytes(data, (EXAMPLES / name).read_bytes()))
        try:
            prepare(scene, load_script(path), vocab)
        except SmartMarlError as exc:
            assert isinstance(exc, WhatIfError) and str(path) in str(exc), f"{type(exc).__name__}: {exc}"

    run_fuzz(budget, check)


def test_every_kind_has_a_value_rule_for_every_key():
    import dataclasses

    for cls in whatif_module.KINDS.values():
        keys = {f.name for f in dataclasses.fields(cls)}
        assert keys == set(whatif_edits._PLACEMENT) | set(whatif_edits._EDIT_RULES[cls]), cls.__name__
    assert isinstance(WhatIf([]), WhatIf)
