"""Model stage, on disk: SMART checkpoints (safetensors weights + a JSON description).

A checkpoint ``NAME`` is, side by side:

* ``NAME.safetensors``: the weights (including the motion vocabularies' contours, which the token
  embedding reads);
* ``NAME.json``: format and version, the model config, the vocabularies (content hashes and the
  names of the vocabulary files stored next to it), the data provenance, the step and the metrics;
* ``NAME.motion_vocab.{npz,json}`` and ``NAME.road_vocab.{npz,json}``: the vocabulary files
  (:mod:`smart_marl.tokens.vocab_io`), so a checkpoint is self-contained;
* for training runs, ``NAME.train_state.pt``: optimizer, scheduler and RNG states (exact resume),
  tensors and plain values only.

Nothing here runs code from a file. :func:`load_checkpoint` checks the JSON (a dict with a model
config and the vocabularies), that the stored vocabularies hash to what the JSON says, that a
vocabulary the caller brings matches the model's, that the weights file is valid safetensors whose
tensors have the config's shapes, and that every weight is finite. :func:`load_train_state` loads
with ``torch.load(weights_only=True)`` (tensors, numbers, strings and containers: no pickled
object is constructed, no global is called) and checks the structure; a file that holds anything
else is refused with a :class:`CheckpointError` naming it.
"""

from __future__ import annotations

import json
import math
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from ..embedded import EMBEDDED, is_embedded
from ..errors import SmartMarlError, regular_file_problem
from ..tokens import BOX_SIZE_M, MOTION_TYPES, MotionVocabulary, TypeVocab, token_poses_from_contours
from ..tokens.road import RoadVocabulary
from ..tokens.vocab_io import (
    VocabularyFileError, load_motion_vocabulary, load_road_vocabulary, save_motion_vocabulary, save_road_vocabulary,
)
from ..version import __version__
from .smart import SMART, get_config

FORMAT = "smart-marl-checkpoint"
VERSION = 1
TRAIN_STATE_FORMAT = "smart-marl-train-state"
TRAIN_STATE_VERSION = 2  # 1: unversioned, with numpy/Python RNG states as pickled objects


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
        torch.save({"format": TRAIN_STATE_FORMAT, "version": TRAIN_STATE_VERSION, **train_state}, tmp(paths["train_state"]))
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


def _check_file(path: Path, what: str) -> None:
    if not path.exists():
        raise CheckpointError(path, f"{what} missing")
    problem = regular_file_problem(path)
    if problem:
        raise CheckpointError(path, problem)


def read_meta(path: str | os.PathLike) -> dict[str, Any]:
    paths = checkpoint_paths(path)
    if not paths["meta"].exists():
        raise CheckpointError(paths["meta"], "no such checkpoint (expected NAME.json next to NAME.safetensors)")
    _check_file(paths["meta"], "checkpoint JSON")
    try:
        meta = json.loads(paths["meta"].read_text())
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise CheckpointError(paths["meta"], f"not valid JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise CheckpointError(paths["meta"], f"not a smart-marl checkpoint (the JSON is a {type(meta).__name__}, not an object)")
    if meta.get("format") != FORMAT:
        raise CheckpointError(paths["meta"], f"not a smart-marl checkpoint (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise CheckpointError(paths["meta"], f"checkpoint version {meta.get('version')!r} is not supported (this code reads {VERSION})")
    if not isinstance(meta.get("model_config"), dict):
        raise CheckpointError(paths["meta"], "the checkpoint has no model_config object")
    vocabs = meta.get("vocabularies")
    for kind in ("motion", "road"):
        entry = vocabs.get(kind) if isinstance(vocabs, dict) else None
        if not (isinstance(entry, dict) and isinstance(entry.get("file"), str) and isinstance(entry.get("content_hash"), str)):
            raise CheckpointError(paths["meta"], f"the checkpoint's vocabularies.{kind} (file and content_hash) is missing or malformed")
        if entry["file"] != os.path.basename(entry["file"]) or entry["file"] in ("", ".", ".."):
            raise CheckpointError(paths["meta"], f"vocabularies.{kind}.file {entry['file']!r} is not a file name next to the checkpoint")
    if not isinstance(meta.get("step", 0), int) or isinstance(meta.get("step", 0), bool):
        raise CheckpointError(paths["meta"], f"step {meta.get('step')!r} is not an integer")
    return meta


def _load_weights(path: Path, expected: dict[str, torch.Tensor], map_location) -> dict[str, torch.Tensor]:
    """The safetensors weights, checked against ``expected`` (a model's state dict, on the meta
    device): the same names, the same shapes, finite values."""
    try:
        state = load_file(str(path), device=str(map_location))
    except Exception as exc:  # noqa: BLE001 - SafetensorError (truncated, empty, huge header...), OSError
        raise CheckpointError(path, f"not a readable safetensors file: {type(exc).__name__}: {exc}") from exc
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(path, f"weights do not fit the config: missing {missing[:5]}, unexpected {unexpected[:5]}")
    for name, tensor in state.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise CheckpointError(path, f"weight {name} has shape {list(tensor.shape)}, the config needs {list(expected[name].shape)}")
        if tensor.is_floating_point() != expected[name].is_floating_point():
            raise CheckpointError(path, f"weight {name} has dtype {tensor.dtype}, the config needs {expected[name].dtype}")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(path, f"weight {name} holds NaN or infinite values")
    return state


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
    except VocabularyFileError as exc:
        raise VocabularyMismatchError(paths["meta"], f"stored vocabulary: {exc}") from exc
    try:
        cfg = get_config(meta["model_config"], **config_overrides)
        with torch.device("meta"):  # shapes only: a config is checked against the weights before anything is allocated
            expected = SMART(cfg).state_dict()
    except (TypeError, ValueError, KeyError, RuntimeError, OverflowError, MemoryError) as exc:
        raise CheckpointError(paths["meta"], f"model_config does not make a SMART model: {type(exc).__name__}: {exc}") from exc
    _check_file(paths["weights"], "weights file")
    values, size = sum(t.numel() for t in expected.values()), paths["weights"].stat().st_size
    if 2 * values > size:  # at least 2 bytes per value (fp16/bf16; the checkpoints hold float32)
        raise CheckpointError(paths["weights"], f"holds {size} bytes, too few for the {values} values of the model_config's weights")
    state = _load_weights(paths["weights"], expected, map_location)
    model = SMART(cfg)
    model.load_state_dict(state)
    _check_vocab_matches_model(paths["meta"], model, mv, rv)
    return Checkpoint(model=model.to(map_location), motion_vocab=mv, road_vocab=rv, meta=meta, path=paths["meta"])


# The only globals a version-1 training state (numpy's RNG state pickled as an array) may use: numpy
# array reconstruction, which builds arrays of numbers and calls nothing else.
_LEGACY_TRAIN_STATE_GLOBALS = [np.ndarray, np.dtype, type(np.dtype(np.uint32)),
                               (np._core.multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
                               np._core.multiarray._reconstruct]


def load_train_state(path: str | os.PathLike) -> dict[str, Any]:
    """The training state next to a checkpoint: ``{"optimizer", "scheduler", "rng", "step"}``.

    Loaded with ``torch.load(weights_only=True)``: tensors and plain values only. A state written
    before version 2 (numpy's RNG state as a pickled array) is read with numpy's array
    reconstruction allowed, and nothing else. Any other file is refused with :class:`CheckpointError`
    before anything in it is constructed or called."""
    p = checkpoint_paths(path)["train_state"]
    if not p.exists():
        raise CheckpointError(p, "no training state next to this checkpoint (it cannot be resumed, only used with --init)")
    _check_file(p, "training state")
    try:
        unsafe = set(torch.serialization.get_unsafe_globals_in_checkpoint(str(p)))
    except Exception as exc:  # noqa: BLE001 - not a torch zip file at all
        raise CheckpointError(p, f"not a readable training state: {type(exc).__name__}: {exc}") from exc
    legacy_names = {"numpy._core.multiarray._reconstruct", "numpy.core.multiarray._reconstruct", "numpy.ndarray", "numpy.dtype",
                    f"numpy.dtypes.{type(np.dtype(np.uint32)).__name__}"}
    if unsafe - legacy_names:
        raise CheckpointError(p, f"refused: the training state would construct or call {sorted(unsafe - legacy_names)[:3]}, "
                                 f"which a smart-marl training state never holds (a crafted or foreign file); nothing in it was run")
    try:
        with torch.serialization.safe_globals(_LEGACY_TRAIN_STATE_GLOBALS if unsafe else []):
            state = torch.load(p, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, ValueError, TypeError, EOFError, OSError, KeyError, AttributeError,
            IndexError, MemoryError, RecursionError) as exc:
        raise CheckpointError(p, f"not a readable training state (only tensors and plain values load): "
                                 f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from exc
    return _checked_train_state(p, state)


def _checked_train_state(p: Path, state: Any) -> dict[str, Any]:
    """The structure :func:`smart_marl.train.train` resumes from, or CheckpointError naming what is off."""
    if not isinstance(state, dict):
        raise CheckpointError(p, f"the training state is a {type(state).__name__}, not a dict")
    for key, kind in (("optimizer", dict), ("scheduler", dict), ("rng", dict), ("step", int)):
        if not isinstance(state.get(key), kind) or isinstance(state.get(key), bool):
            raise CheckpointError(p, f"the training state's {key!r} is missing or not a {kind.__name__}")
    if state["step"] < 0:
        raise CheckpointError(p, f"the training state's step is {state['step']}")
    optimizer = state["optimizer"]
    if not (isinstance(optimizer.get("state"), dict) and isinstance(optimizer.get("param_groups"), list)):
        raise CheckpointError(p, "the training state's optimizer has no 'state' and 'param_groups'")
    rng = state["rng"]
    if "numpy" in rng and isinstance(rng["numpy"], tuple):  # version 1: numpy's and Python's states as pickled
        try:
            _, keys, pos, has_gauss, cached = rng["numpy"]
            version, internal, gauss_next = rng["python"]
            rng = {**rng, "numpy": {"keys": torch.from_numpy(np.asarray(keys, np.int64)), "pos": int(pos),
                                    "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
                   "python": {"version": int(version), "internal": torch.tensor(internal, dtype=torch.int64),
                              "gauss_next": gauss_next}}
        except (ValueError, TypeError, KeyError, OverflowError) as exc:
            raise CheckpointError(p, f"the training state's RNG states are malformed: {exc}") from exc
        state = {**state, "rng": rng}
    problem = rng_problem(rng)
    if problem:
        raise CheckpointError(p, f"the training state's RNG states are malformed: {problem}")
    return state


def rng_problem(rng: dict) -> str | None:
    torch_state, numpy_state, python_state = rng.get("torch"), rng.get("numpy"), rng.get("python")
    if not (isinstance(torch_state, torch.Tensor) and torch_state.dtype == torch.uint8 and torch_state.dim() == 1):
        return "torch: expected a byte tensor"
    if not (isinstance(numpy_state, dict) and isinstance(numpy_state.get("keys"), torch.Tensor)
            and tuple(numpy_state["keys"].shape) == (624,) and isinstance(numpy_state.get("pos"), int)
            and isinstance(numpy_state.get("has_gauss"), int) and isinstance(numpy_state.get("cached_gaussian"), float)):
        return "numpy: expected keys [624], pos, has_gauss, cached_gaussian"
    if not (0 <= int(numpy_state["keys"].min()) and int(numpy_state["keys"].max()) < 2**32 and 0 <= numpy_state["pos"] <= 624):
        return "numpy: keys or pos out of range"
    gauss = python_state.get("gauss_next") if isinstance(python_state, dict) else None
    if not (isinstance(python_state, dict) and isinstance(python_state.get("version"), int)
            and isinstance(python_state.get("internal"), torch.Tensor) and tuple(python_state["internal"].shape) == (625,)
            and (gauss is None or (isinstance(gauss, float) and math.isfinite(gauss)))):
        return "python: expected version, internal [625], gauss_next"
    cuda = rng.get("cuda")
    if cuda is not None and not (isinstance(cuda, list) and all(isinstance(t, torch.Tensor) for t in cuda)):
        return "cuda: expected a list of tensors"
    return None


EMBEDDED_DIR = Path(__file__).resolve().parents[1] / "checkpoints" / "embedded"
"""Where the package ships its pretrained prior (``prior="embedded"``)."""


def embedded_checkpoint_path() -> Path:
    """The embedded prior's checkpoint (its ``.json``); a clear error when the package has none."""
    found = sorted(EMBEDDED_DIR.glob("*.json")) if EMBEDDED_DIR.is_dir() else []
    metas = [p for p in found if not p.name.endswith((".motion_vocab.json", ".road_vocab.json"))]
    if not metas:
        raise CheckpointError(EMBEDDED_DIR, "this installation ships no embedded SMART checkpoint; pass a checkpoint path")
    return metas[0]


def resolve_checkpoint_path(path: str | os.PathLike) -> str | os.PathLike:
    """``path``, or the embedded prior's checkpoint for ``"embedded"``."""
    return embedded_checkpoint_path() if is_embedded(path) else path


def load_embedded(map_location: str | torch.device = "cpu", **config_overrides: Any) -> Checkpoint:
    """The package's pretrained SMART prior as a :class:`Checkpoint` (weights, both vocabularies and
    provenance; its model card: docs/model_card.md). To drive with it, :func:`load_prior` ``("embedded")``."""
    return load_checkpoint(EMBEDDED, map_location=map_location, **config_overrides)


def motion_vocabulary_from_model(model: SMART) -> MotionVocabulary:
    """The motion vocabulary a model's contour buffers stand for (poses from the contours), for
    rolling matching of the history when no vocabulary file is at hand."""
    types = {}
    for t, c in zip(MOTION_TYPES, model.motion_contours):
        poses = token_poses_from_contours(c.detach().cpu().float()).numpy()
        types[t] = TypeVocab.from_poses(poses, *BOX_SIZE_M[t])
    return MotionVocabulary(types=types, method="from_model")


class Prior(NamedTuple):
    """A SMART prior ready to drive: the model (eval mode) and the motion vocabulary its tokens are
    placed with. What :func:`load_prior` returns; unpacks as ``model, vocab = load_prior(...)``."""

    model: SMART
    motion_vocab: MotionVocabulary


def load_prior(prior, map_location: str | torch.device = "cpu") -> Prior:
    """The one way to get a SMART prior: (model in eval mode on ``map_location``, its motion
    vocabulary) from ``"embedded"`` (the package's prior), a checkpoint path (``NAME`` or
    ``NAME.json``), a :class:`Checkpoint`, a :class:`Prior`, or a SMART model (its vocabulary rebuilt
    from its contour buffers). A path with no checkpoint raises :class:`CheckpointError`."""
    if isinstance(prior, (str, os.PathLike)):
        path = resolve_checkpoint_path(prior)
        meta = checkpoint_paths(path)["meta"]
        if not meta.is_file():
            raise CheckpointError(path, f"no checkpoint at this path (expected {meta.name} next to its .safetensors)")
        prior = load_checkpoint(path, map_location=map_location)
    if isinstance(prior, (Checkpoint, Prior)):
        model, vocab = prior.model, prior.motion_vocab
    else:
        model, vocab = prior, None
    model = model.to(map_location).eval()
    return Prior(model, vocab if vocab is not None else motion_vocabulary_from_model(model))


def export_checkpoint(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copy a training checkpoint to ``dst`` for inference: weights, vocabularies, config and
    provenance under the new name, without the optimizer/RNG training state. Returns the JSON path."""
    ck = load_checkpoint(src)
    meta = ck.meta
    return save_checkpoint(dst, ck.model, ck.motion_vocab, ck.road_vocab, step=ck.step, metrics=meta.get("metrics"),
                           data={**meta.get("data", {}), "exported_from": str(checkpoint_paths(src)["meta"])},
                           train_config=meta.get("train_config"))
