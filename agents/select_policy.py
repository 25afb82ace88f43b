"""Fine-tuning stage, checkpoint selection: which of a run's policy checkpoints to keep, judged on validation scenes
that are neither the run's training scenes nor the scenes it is finally tested on (issue 58).

What comes in: a fine-tuning run's folder (``OUT/checkpoints/policy_NNNN.{json,safetensors}``, written every
``checkpoint_every`` iterations, and ``policy_last``), validation scenes (any path the scene pool reads), and the
episodes (seeds) per scene and the first seed. What goes out: every checkpoint's row on those scenes
(:func:`agents.finetune.evaluate_finetuned` with ``baselines=False``: the fine-tuned policy alone, in the run's own
environment, shield and reward), its score, goal rate less collision rate less offroad rate (what the policy is
asked to raise and to keep down, in one number), the best checkpoint (the earliest among equal scores),
``OUT/checkpoints/selection.json`` with all of it, and ``OUT/checkpoints/policy_best.{json,safetensors}``, a copy of the
chosen checkpoint's files (``load_policy("OUT/checkpoints/policy_best")`` reads it). ``policy_last`` is scored only when
no numbered checkpoint holds its iteration. Validation scenes that are the run's training or test scenes are
refused by id. A selection run again (more checkpoints since, a run that goes on) scores only what it has not: a row
of the last ``selection.json`` is kept when its checkpoint's files (their SHA-256) and the validation settings are the
same, since a checkpoint's evaluation on the same scenes and seeds is the same.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

from .finetune import FinetuneError, _pool, evaluate_finetuned, load_finetune_config, load_policy, load_prior, training_pool
from .policy import FinetunedTensorPolicy

SELECTION_FILE = "selection.json"
BEST = "policy_best"
_NUMBERED = re.compile(r"policy_(\d+)\.json$")


def score(row: dict) -> float:
    """A checkpoint's validation score: goal rate - collision rate - offroad rate of its policy row."""
    return float(row["goal_rate"]) - float(row["collision_rate"]) - float(row["offroad_rate"])


def run_checkpoints(run_dir: str | Path) -> list[Path]:
    """The policy checkpoints of a run (their ``.json`` files), numbered ones by iteration, then ``policy_last`` when
    its iteration is not among theirs."""
    ckpt = Path(run_dir) / "checkpoints"
    numbered = sorted((int(m.group(1)), p) for p in ckpt.glob("policy_*.json") if (m := _NUMBERED.search(p.name)))
    out = [p for _, p in numbered]
    last = ckpt / "policy_last.json"
    if last.exists() and json.loads(last.read_text()).get("iteration") not in {i for i, _ in numbered}:
        out.append(last)
    if not out:
        raise FinetuneError(f"{ckpt}: no policy checkpoint (policy_NNNN.json or policy_last.json) to select from")
    return out


def select_policy(run_dir: str | Path, val_scenes: str | list, episodes: int | None = None, seed: int | None = None,
                  num_scenes: int | None = None) -> dict:
    """Score every checkpoint of the run in ``run_dir`` on ``val_scenes`` (the first ``num_scenes`` of them, default the
    run's ``eval_num_scenes``; ``episodes`` seeds from ``seed``, defaults the run's), write ``selection.json`` and
    ``policy_best`` beside the checkpoints and return the selection (module docstring)."""
    paths = run_checkpoints(run_dir)
    saved = load_policy(paths[0])[0]
    training = training_pool(saved).scenario_ids()
    validation = set(_pool(val_scenes, "val_scenes").scenario_ids())
    for name, ids in (("training", training), ("test (eval_scenes)", _pool(saved.eval_scenes, "eval_scenes").scenario_ids()
                                                                     if saved.eval_scenes else [])):
        overlap = sorted(validation & set(ids))
        if overlap:
            raise FinetuneError(f"val_scenes {val_scenes!r}: {len(overlap)} of its scenes are the run's {name} scenes "
                                f"({', '.join(overlap[:5])}); validate on scenes that are neither")
    settings = json.loads(json.dumps({"val_scenes": val_scenes, "episodes": episodes, "seed": seed, "num_scenes": num_scenes}))
    done = _scored(Path(run_dir) / "checkpoints" / SELECTION_FILE, settings)
    rows, prior = [], None
    for path in paths:
        digest = _digest(path)
        if digest in done:
            rows.append({**done[digest], "checkpoint": path.stem})
            continue
        saved, net, meta = load_policy(path)
        cfg = load_finetune_config(saved.to_dict(), {"eval_scenes": val_scenes, **({"eval_num_scenes": int(num_scenes)} if num_scenes else {})})
        prior = prior or load_prior(cfg.prior, cfg.device)  # one run, one prior: loaded once
        result = evaluate_finetuned(cfg, net.to(cfg.device), training=training, model=prior[0], vocab=prior[1], episodes=episodes,
                                    seed=seed, baselines=False)
        row = result["rows"][FinetunedTensorPolicy.name]
        rows.append({"checkpoint": path.stem, "iteration": meta.get("iteration"), "score": score(row), "row": row,
                     "scenes": len(result["scenes"]), "seeds": result["seeds"], "digest": digest})
    best = max(rows, key=lambda r: (r["score"], -rows.index(r)))  # the earliest of equal scores
    ckpt = Path(run_dir) / "checkpoints"
    for ext in ("json", "safetensors"):
        shutil.copyfile(ckpt / f"{best['checkpoint']}.{ext}", ckpt / f"{BEST}.{ext}.tmp")
        (ckpt / f"{BEST}.{ext}.tmp").replace(ckpt / f"{BEST}.{ext}")
    selection = {**settings, "score": "goal_rate - collision_rate - offroad_rate", "best": best["checkpoint"],
                 "best_iteration": best["iteration"], "checkpoints": rows}
    tmp = ckpt / f"{SELECTION_FILE}.tmp"
    tmp.write_text(json.dumps(selection, indent=1, default=float))
    tmp.replace(ckpt / SELECTION_FILE)
    return selection


def _digest(path: Path) -> str:
    """SHA-256 of a checkpoint's two files (``path`` its ``.json``)."""
    h = hashlib.sha256()
    for f in (path, path.with_suffix(".safetensors")):
        h.update(f.read_bytes())
    return h.hexdigest()


def _scored(selection_file: Path, settings: dict) -> dict:
    """The rows of an earlier selection with the same ``settings``, by checkpoint digest (none when it is missing,
    unreadable or was made with other settings: those checkpoints are scored again)."""
    try:
        earlier = json.loads(selection_file.read_text())
        if any(earlier.get(k) != v for k, v in settings.items()):
            return {}
        return {r["digest"]: r for r in earlier["checkpoints"] if isinstance(r, dict) and isinstance(r.get("digest"), str)}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


__all__ = ["BEST", "SELECTION_FILE", "run_checkpoints", "score", "select_policy"]
