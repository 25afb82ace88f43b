"""Model stage, on disk: SMART checkpoints (safetensors weights + a JSON description).

A checkpoint ``NAME`` is, side by side:

* ``NAME.safetensors``: the weights (including the motion vocabularies' contours, which the token
  embedding reads);
* ``NAME.json``: format and version, the model config, the vocabularies (content hashes and the
  names of the vocabulary files stored next to it), the data provenance, the step and the metrics;
* ``NAME.motion_vocab.{npz,json}`` and ``NAME.road_vocab.{npz,json}``: the vocabulary files
  (:mod:`smart_marl.tokens.vocab_io`), so a checkpoint is self-contained;
* for training runs, ``NAME.train_state.pt``: optimizer, scheduler and RNG states (exact resume).

:func:`load_checkpoint` checks that the stored vocabularies hash to what the JSON says and that a
vocabulary the caller brings matches the model's.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from ..errors import SmartMarlError
from ..tokens import BOX_SIZE_M, MOTION_TYPES, MotionVocabulary, TypeVocab, token_poses_from_contours
from ..tokens.road import RoadVocabulary
from ..tokens.vocab_io import load_motion_vocabulary, load_road_vocabulary, save_motion_vocabulary, save_road_vocabulary
from ..version import __version__
from .smart import SMART, get_config

FORMAT = "smart-marl-checkpoint"
VERSION = 1


class CheckpointError(SmartMarlError, ValueError):
    """A checkpoint that is missing, of another format, or inconsistent with what it is used with."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path, self.problem = os.fspath(path), problem
        super().__init__(f"{self.path}: {problem}")


class VocabularyMismatchError(CheckpointError):
    """A vocabulary that is not the one the checkpoint's model was trained with."""


def checkpoint_paths(path: str | os.PathLike) -> dict[str, Path]:
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".json", ".safetensors") else p
    name = stem.name
    return {
        "weights": stem.with_name(name + ".safetensors"), "meta": stem.with_name(name + ".json"),
        "motion_vocab": stem.with_name(name + ".motion_vocab"), "road_vocab": stem.with_name(name + ".road_vocab"),
        "train_state": stem.with_name(name + ".train_state.pt"),
    }


@dataclass
class Checkpoint:
    model: SMART
    motion_vocab: MotionVocabulary
    road_vocab: RoadVocabulary
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def step(self) -> int:
        return int(self.meta.get("step", 0))


def save_checkpoint(path: str | os.PathLike, model: SMART, motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary,
                    step: int = 0, metrics: dict[str, Any] | None = None, data: dict[str, Any] | None = None,
                    train_config: dict[str, Any] | None = None, train_state: dict[str, Any] | None = None) -> Path:
    """Write the checkpoint files (each atomically: temporary name, then rename); returns the JSON path."""
    paths = checkpoint_paths(path)
    paths["meta"].parent.mkdir(parents=True, exist_ok=True)
    _check_vocab_matches_model(paths["meta"], model, motion_vocab, road_vocab)
    tmp = lambda p: p.with_name(f".{p.name}.tmp-{os.getpid()}")  # noqa: E731
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, tmp(paths["weights"]))
    os.replace(tmp(paths["weights"]), paths["weights"])
    for key, vocab, saver in (("motion_vocab", motion_vocab, save_motion_vocabulary), ("road_vocab", road_vocab, save_road_vocabulary)):
        written = saver(vocab, tmp(paths[key]))
        for w, suffix in zip(written, (".npz", ".json")):
            os.replace(w, paths[key].with_name(paths[key].name + suffix))
    if train_state is not None:
        torch.save(train_state, tmp(paths["train_state"]))
        os.replace(tmp(paths["train_state"]), paths["train_state"])
    meta = {
        "format": FORMAT, "version": VERSION, "step": int(step), "model_config": model.config.to_dict(),
        "num_parameters": sum(p.numel() for p in model.parameters()),
        "vocabularies": {
            "motion": {"content_hash": motion_vocab.content_hash(), "file": paths["motion_vocab"].name, "sizes": motion_vocab.sizes()},
            "road": {"content_hash": road_vocab.content_hash(), "file": paths["road_vocab"].name, "size": road_vocab.size},
        },
        "data": data or {}, "metrics": metrics or {}, "train_config": train_config or {},
        "has_train_state": train_state is not None, "written_by": f"smart-marl {__version__}",
    }
    paths["meta"].with_name(paths["meta"].name + ".tmp").write_text(json.dumps(meta, indent=1, default=str))
    os.replace(paths["meta"].with_name(paths["meta"].name + ".tmp"), paths["meta"])
    return paths["meta"]


def _check_vocab_matches_model(path, model: SMART, motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary) -> None:
    sizes = tuple(motion_vocab[t].size for t in range(3))
    if sizes != tuple(model.config.motion_vocab_sizes):
        raise VocabularyMismatchError(path, f"motion vocabulary sizes {sizes} (vehicle, pedestrian, cyclist) do not match the "
                                            f"model's {tuple(model.config.motion_vocab_sizes)}")
    for t, c in enumerate(model.motion_contours):
        if not torch.allclose(c.cpu(), torch.as_tensor(motion_vocab[t].contour, dtype=torch.float32), atol=1e-5):
            raise VocabularyMismatchError(path, f"motion vocabulary of type {t} is not the one in the model's weights")
    if road_vocab.size != model.config.road_vocab_size:
        raise VocabularyMismatchError(path, f"road vocabulary size {road_vocab.size} does not match the model's {model.config.road_vocab_size}")


def read_meta(path: str | os.PathLike) -> dict[str, Any]:
    paths = checkpoint_paths(path)
    if not paths["meta"].is_file():
        raise CheckpointError(paths["meta"], "no such checkpoint (expected NAME.json next to NAME.safetensors)")
    try:
        meta = json.loads(paths["meta"].read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(paths["meta"], f"not valid JSON: {exc}") from exc
    if meta.get("format") != FORMAT:
        raise CheckpointError(paths["meta"], f"not a smart-marl checkpoint (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise CheckpointError(paths["meta"], f"checkpoint version {meta.get('version')!r} is not supported (this code reads {VERSION})")
    return meta


def load_checkpoint(path: str | os.PathLike, motion_vocab: MotionVocabulary | None = None, road_vocab: RoadVocabulary | None = None,
                    map_location: str | torch.device = "cpu", **config_overrides: Any) -> Checkpoint:
    """Load a checkpoint. ``motion_vocab``/``road_vocab``, when given, must be the model's
    (same content hash), else :class:`VocabularyMismatchError`. ``config_overrides`` may change
    fields that do not touch the weights' shapes (dropout, neighbourhood sizes). ``path`` may be
    ``"embedded"``, the package's prior."""
    path = resolve_checkpoint_path(path)
    paths = checkpoint_paths(path)
    meta = read_meta(path)
    vocabs = meta["vocabularies"]
    for kind, given in (("motion", motion_vocab), ("road", road_vocab)):
        if given is not None and given.content_hash() != vocabs[kind]["content_hash"]:
            raise VocabularyMismatchError(paths["meta"], f"the {kind} vocabulary given (hash {given.content_hash()[:12]}...) is not the one "
                                                        f"this model was trained with (hash {vocabs[kind]['content_hash'][:12]}...)")
    try:
        mv = motion_vocab or load_motion_vocabulary(paths["meta"].with_name(vocabs["motion"]["file"]), vocabs["motion"]["content_hash"])
        rv = road_vocab or load_road_vocabulary(paths["meta"].with_name(vocabs["road"]["file"]), vocabs["road"]["content_hash"])
    except ValueError as exc:
        raise VocabularyMismatchError(paths["meta"], f"stored vocabulary: {exc}") from exc
    cfg = get_config(meta["model_config"], **config_overrides)
    model = SMART(cfg)
    if not paths["weights"].is_file():
        raise CheckpointError(paths["weights"], "weights file missing")
    state = load_file(str(paths["weights"]), device=str(map_location))
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise CheckpointError(paths["weights"], f"weights do not fit the config: missing {missing[:5]}, unexpected {unexpected[:5]}")
    _check_vocab_matches_model(paths["meta"], model, mv, rv)
    return Checkpoint(model=model.to(map_location), motion_vocab=mv, road_vocab=rv, meta=meta, path=paths["meta"])


def load_train_state(path: str | os.PathLike) -> dict[str, Any]:
    p = checkpoint_paths(path)["train_state"]
    if not p.is_file():
        raise CheckpointError(p, "no training state next to this checkpoint (it cannot be resumed, only used with --init)")
    return torch.load(p, map_location="cpu", weights_only=False)  # our own file, written by save_checkpoint


EMBEDDED_DIR = Path(__file__).resolve().parents[1] / "checkpoints" / "embedded"
"""Where the package ships its pretrained prior (``prior="embedded"``)."""
EMBEDDED = "embedded"
"""The name that stands for the package's embedded prior wherever a checkpoint path is taken."""


def embedded_checkpoint_path() -> Path:
    """The embedded prior's checkpoint (its ``.json``); a clear error when the package has none."""
    found = sorted(EMBEDDED_DIR.glob("*.json")) if EMBEDDED_DIR.is_dir() else []
    metas = [p for p in found if not p.name.endswith((".motion_vocab.json", ".road_vocab.json"))]
    if not metas:
        raise CheckpointError(EMBEDDED_DIR, "this installation ships no embedded SMART checkpoint; pass a checkpoint path")
    return metas[0]


def resolve_checkpoint_path(path: str | os.PathLike) -> str | os.PathLike:
    """``path``, or the embedded prior's checkpoint for ``"embedded"``."""
    return embedded_checkpoint_path() if isinstance(path, str) and path == EMBEDDED else path


def load_embedded(map_location: str | torch.device = "cpu", **config_overrides: Any) -> Checkpoint:
    """The package's pretrained SMART prior (see the model card in the README)."""
    return load_checkpoint(EMBEDDED, map_location=map_location, **config_overrides)


def motion_vocabulary_from_model(model: SMART) -> MotionVocabulary:
    """The motion vocabulary a model's contour buffers stand for (poses from the contours), for
    rolling matching of the history when no vocabulary file is at hand."""
    types = {}
    for t, c in zip(MOTION_TYPES, model.motion_contours):
        poses = token_poses_from_contours(c.detach().cpu().float()).numpy()
        types[t] = TypeVocab.from_poses(poses, *BOX_SIZE_M[t])
    return MotionVocabulary(types=types, method="from_model")


def load_prior(prior, map_location: str | torch.device = "cpu") -> tuple[SMART, MotionVocabulary]:
    """The one way to get a SMART prior: (model in eval mode on ``map_location``, its motion
    vocabulary) from ``"embedded"`` (the package's prior), a checkpoint path (``NAME`` or
    ``NAME.json``), a :class:`Checkpoint`, or a SMART model (its vocabulary rebuilt from its contour
    buffers). A path with no checkpoint raises :class:`CheckpointError`."""
    if isinstance(prior, (str, os.PathLike)):
        path = resolve_checkpoint_path(prior)
        meta = checkpoint_paths(path)["meta"]
        if not meta.is_file():
            raise CheckpointError(path, f"no checkpoint at this path (expected {meta.name} next to its .safetensors)")
        prior = load_checkpoint(path, map_location=map_location)
    if isinstance(prior, Checkpoint):
        model, vocab = prior.model, prior.motion_vocab
    else:
        model, vocab = prior, None
    model = model.to(map_location).eval()
    return model, vocab if vocab is not None else motion_vocabulary_from_model(model)


def export_checkpoint(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copy a training checkpoint to ``dst`` for inference: weights, vocabularies, config and
    provenance under the new name, without the optimizer/RNG training state. Returns the JSON path."""
    ck = load_checkpoint(src)
    meta = ck.meta
    return save_checkpoint(dst, ck.model, ck.motion_vocab, ck.road_vocab, step=ck.step, metrics=meta.get("metrics"),
                           data={**meta.get("data", {}), "exported_from": str(checkpoint_paths(src)["meta"])},
                           train_config=meta.get("train_config"))
