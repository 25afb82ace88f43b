"""Vocabulary files (tokens stage): the versioned on-disk form of motion and road vocabularies.

A vocabulary is two files side by side: ``NAME.npz`` (the arrays) and ``NAME.json`` (format name,
version, kind, per-type sizes, tolerances, box sizes, the data it was built from, and the content
hash). Checkpoints refer to a vocabulary by its content hash (:func:`motion_vocabulary_hash`,
:func:`road_vocabulary_hash`): a SHA-256 over the token arrays and the box sizes only, so the same
tokens give the same hash whatever the provenance text says. Loading validates everything: the
format and version, the arrays' shapes, that contours are the boxes at the stored poses, and the
hash.

Also here: :func:`load_reference_motion_vocabulary`, which reads the SMART authors' published
``cluster_frame_5_2048.pkl`` (through a restricted unpickler) as a yardstick for our own
vocabularies, never a substitute for building them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ScenarioReadError, SmartMarlError, regular_file_problem
from ..readers.safe_pickle import NUMPY_GLOBALS, load_restricted
from ..scenario import AgentType
from ..version import __version__
from .motion import (
    BOX_SIZE_M, POSES_PER_TOKEN, TYPE_KEYS, VOCABULARY_VERSION, MotionVocabulary, TypeVocab, box_contour,
    motion_vocabulary_hash,
)
from .road import RoadVocabulary, road_vocabulary_hash

__all__ = [
    "FORMAT", "VERSION", "VocabularyFileError", "load_motion_vocabulary", "load_reference_motion_vocabulary",
    "load_road_vocabulary", "motion_vocabulary_hash", "road_vocabulary_hash", "save_motion_vocabulary",
    "save_road_vocabulary", "vocabulary_paths",
]

FORMAT = "smart-marl-vocabulary"
VERSION = VOCABULARY_VERSION
_KEY_TYPES = {v: k for k, v in TYPE_KEYS.items()}
_TYPE_NAMES = [t.name.lower() for t in TYPE_KEYS]


class VocabularyFileError(SmartMarlError, ValueError):
    """A vocabulary file that is missing, of another format or version, or inconsistent."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path, self.problem = os.fspath(path), problem
        super().__init__(f"{self.path}: {problem}")


def vocabulary_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """(NAME.npz, NAME.json) for ``path`` given with either suffix or none."""
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".npz", ".json") else p
    return stem.with_name(stem.name + ".npz"), stem.with_name(stem.name + ".json")


def _write(path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> tuple[Path, Path]:
    npz, js = vocabulary_paths(path)
    npz.parent.mkdir(parents=True, exist_ok=True)
    with open(npz, "wb") as f:
        np.savez(f, **arrays)
    js.write_text(json.dumps(meta, indent=2, sort_keys=False) + "\n")
    return npz, js


def _read(path, kind: str) -> tuple[dict[str, np.ndarray], dict[str, Any], Path]:
    npz, js = vocabulary_paths(path)
    for p in (npz, js):
        if not p.exists():
            raise VocabularyFileError(p, "no such file (a vocabulary is NAME.npz plus NAME.json)")
        problem = regular_file_problem(p)
        if problem:
            raise VocabularyFileError(p, problem)
    try:
        meta = json.loads(js.read_text())
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise VocabularyFileError(js, f"not JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise VocabularyFileError(js, f"holds a JSON {type(meta).__name__}, not a vocabulary description")
    if meta.get("format") != FORMAT:
        raise VocabularyFileError(js, f"format is {meta.get('format')!r}, expected {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise VocabularyFileError(js, f"version {meta.get('version')!r} is not supported (this code reads version {VERSION})")
    if meta.get("kind") != kind:
        raise VocabularyFileError(js, f"holds a {meta.get('kind')!r} vocabulary, expected {kind!r}")
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error...
        raise VocabularyFileError(npz, f"cannot read the arrays: {type(exc).__name__}: {exc}") from exc
    return arrays, meta, js


def _numbers_problem(info: Any, integers: tuple[str, ...], reals: tuple[str, ...]) -> str | None:
    """What is wrong with the numeric fields of a vocabulary's JSON (``integers`` >= 0 when present,
    ``reals`` finite and >= 0 and required), or None."""
    if not isinstance(info, dict):
        return f"expected an object, got {type(info).__name__}"
    for key in integers:
        value = info.get(key, 0)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            return f"{key} is {value!r}, expected an integer >= 0"
    for key in reals:
        value = info.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
            return f"{key} is {value!r}, expected a finite number >= 0"
    return None


def save_motion_vocabulary(vocab: MotionVocabulary, path: str | os.PathLike) -> tuple[Path, Path]:
    """Write NAME.npz and NAME.json; returns both paths."""
    arrays, types = {}, {}
    for t in sorted(vocab.types, key=int):
        v, key = vocab.types[t], TYPE_KEYS[t]
        arrays[f"{key}.poses"] = v.poses.astype(np.float32)
        arrays[f"{key}.contour"] = v.contour.astype(np.float32)
        types[AgentType(t).name.lower()] = {
            "key": key, "size": v.size, "requested_size": int(v.requested_size), "tolerance_m": float(v.tolerance_m),
            "box_length_m": float(v.length_m), "box_width_m": float(v.width_m),
            "num_samples": int(v.num_samples), "num_real_samples": int(v.num_real_samples),
        }
    meta = {
        "format": FORMAT, "version": VERSION, "kind": "motion", "method": vocab.method, "seed": vocab.seed,
        "frames_per_token": POSES_PER_TOKEN - 1, "poses": "x_m, y_m, heading_rad in the token's start frame",
        "contour_corners": "left-front, right-front, right-back, left-back",
        "content_hash": motion_vocabulary_hash(vocab), "types": types, "provenance": vocab.provenance,
        "written_by": f"smart-marl {__version__}",
    }
    return _write(path, arrays, meta)


def load_motion_vocabulary(path: str | os.PathLike, expected_hash: str | None = None) -> MotionVocabulary:
    """Read and validate a motion vocabulary; ``expected_hash`` (from a checkpoint) must match if given."""
    arrays, meta, js = _read(path, "motion")
    types = {}
    entries = meta.get("types", {})
    if not isinstance(entries, dict):
        raise VocabularyFileError(js, "'types' is not an object keyed by agent type")
    for name, info in entries.items():
        try:
            t = AgentType[name.upper()]
            key = info["key"]
            poses, contour = arrays[f"{key}.poses"], arrays[f"{key}.contour"]
        except (KeyError, TypeError) as exc:
            raise VocabularyFileError(js, f"type {name!r}: missing {exc}") from exc
        if t not in TYPE_KEYS:
            raise VocabularyFileError(js, f"type {name!r} has no motion tokens (only {', '.join(_TYPE_NAMES)} do)")
        problem = _numbers_problem(info, ("size", "requested_size", "num_samples", "num_real_samples"),
                                   ("box_length_m", "box_width_m", "tolerance_m"))
        if problem:
            raise VocabularyFileError(js, f"type {name}: {problem}")
        v = int(info["size"])
        if v < 1:
            raise VocabularyFileError(js, f"type {name}: size {v}; a type in a vocabulary has at least one token")
        if poses.dtype.kind != "f" or contour.dtype.kind != "f":
            raise VocabularyFileError(js, f"type {name}: poses and contours must be floats, got {poses.dtype} / {contour.dtype}")
        if poses.shape != (v, POSES_PER_TOKEN, 3) or contour.shape != (v, POSES_PER_TOKEN, 4, 2):
            raise VocabularyFileError(js, f"type {name}: poses {poses.shape} / contour {contour.shape} disagree with size {v}")
        if not (np.isfinite(poses).all() and np.isfinite(contour).all()):
            raise VocabularyFileError(js, f"type {name}: non-finite values")
        expect = box_contour(poses.astype(np.float64), info["box_length_m"], info["box_width_m"])
        if np.abs(expect - contour).max(initial=0.0) > 1e-3:
            raise VocabularyFileError(js, f"type {name}: contours are not the {info['box_length_m']} x {info['box_width_m']} m boxes at the stored poses")
        types[t] = TypeVocab(poses=poses, contour=contour, length_m=float(info["box_length_m"]), width_m=float(info["box_width_m"]),
                             tolerance_m=float(info["tolerance_m"]), requested_size=int(info.get("requested_size", v)),
                             num_samples=int(info.get("num_samples", 0)), num_real_samples=int(info.get("num_real_samples", 0)))
    if not types:
        raise VocabularyFileError(js, "no types")
    vocab = MotionVocabulary(types=types, method=meta.get("method", "kdisks"), seed=meta.get("seed"), provenance=meta.get("provenance", {}))
    got = motion_vocabulary_hash(vocab)
    if got != meta.get("content_hash"):
        raise VocabularyFileError(js, f"content hash {got[:12]}... differs from the recorded {str(meta.get('content_hash'))[:12]}... (arrays changed)")
    if expected_hash is not None and got != expected_hash:
        raise VocabularyFileError(js, f"content hash {got[:12]}... is not the expected {expected_hash[:12]}...")
    return vocab


def save_road_vocabulary(vocab: RoadVocabulary, path: str | os.PathLike) -> tuple[Path, Path]:
    """Write NAME.npz and NAME.json; returns both paths."""
    meta = {
        "format": FORMAT, "version": VERSION, "kind": "road", "method": "kdisks", "seed": vocab.seed,
        "size": vocab.size, "requested_size": int(vocab.requested_size), "tolerance_m": float(vocab.tolerance_m),
        "points_per_piece": int(vocab.points.shape[1]), "max_piece_length_m": float(vocab.max_piece_length_m),
        "points": "x_m, y_m in the piece's frame (origin at its first point, +x towards its last point)",
        "num_samples": int(vocab.num_samples), "content_hash": road_vocabulary_hash(vocab),
        "provenance": vocab.provenance, "written_by": f"smart-marl {__version__}",
    }
    return _write(path, {"points": vocab.points.astype(np.float32)}, meta)


def load_road_vocabulary(path: str | os.PathLike, expected_hash: str | None = None) -> RoadVocabulary:
    """Read and validate a road vocabulary; ``expected_hash`` (from a checkpoint) must match if given."""
    arrays, meta, js = _read(path, "road")
    points = arrays.get("points")
    problem = _numbers_problem(meta, ("size", "requested_size", "num_samples"), ("tolerance_m", "max_piece_length_m"))
    if problem:
        raise VocabularyFileError(js, problem)
    if points is None or points.ndim != 3 or points.shape[0] != meta.get("size") or points.shape[2] != 2 or points.dtype.kind != "f":
        raise VocabularyFileError(js, f"points {None if points is None else points.shape} disagree with size {meta.get('size')}")
    if not np.isfinite(points).all():
        raise VocabularyFileError(js, "points are not all finite")
    vocab = RoadVocabulary(points=points, tolerance_m=float(meta["tolerance_m"]), requested_size=int(meta.get("requested_size", len(points))),
                           max_piece_length_m=float(meta["max_piece_length_m"]), num_samples=int(meta.get("num_samples", 0)),
                           seed=meta.get("seed"), provenance=meta.get("provenance", {}))
    got = road_vocabulary_hash(vocab)
    if got != meta.get("content_hash") or (expected_hash is not None and got != expected_hash):
        raise VocabularyFileError(js, f"content hash {got[:12]}... does not match")
    return vocab


# ------------------------------------------------------------------------ the reference file
def _load_pickle(path: Path) -> Any:
    """Unpickle through the project's restricted unpickler, numpy arrays and plain containers only."""
    return load_restricted(path, NUMPY_GLOBALS)


def load_reference_motion_vocabulary(path: str | os.PathLike) -> MotionVocabulary:
    """The SMART authors' ``cluster_frame_5_{size}.pkl`` (per type 'veh'/'ped'/'cyc': ``traj``
    [V, 6, 3], ``token_all`` [V, 6, 4, 2]) as a :class:`MotionVocabulary` with method "reference".

    Poses come from ``traj``; contours are recomputed from them with :data:`BOX_SIZE_M` and checked
    against ``token_all`` (the same boxes). A yardstick only."""
    path = Path(path)
    try:
        data = _load_pickle(path)
        types = {}
        for key, t in _KEY_TYPES.items():
            traj = np.asarray(data["traj"][key], np.float32)
            if traj.ndim != 3 or traj.shape[1:] != (POSES_PER_TOKEN, 3):
                raise VocabularyFileError(path, f"traj[{key!r}] has shape {traj.shape}, expected [V, 6, 3]")
            length, width = BOX_SIZE_M[t]
            v = TypeVocab.from_poses(traj, length, width, requested_size=len(traj))
            ref = np.asarray(data["token_all"][key], np.float32)
            if ref.shape != v.contour.shape or np.abs(ref - v.contour).max() > 1e-2:
                raise VocabularyFileError(path, f"token_all[{key!r}] is not the {length} x {width} m box at traj")
            types[t] = v
    except (ScenarioReadError, KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise VocabularyFileError(path, f"not a SMART reference vocabulary pickle: {exc}") from exc
    return MotionVocabulary(types=types, method="reference", provenance={"source": str(path), "note": "rainmaker22/SMART published vocabulary, built from all of WOMD"})
