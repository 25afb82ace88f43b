"""What the package ships so that it runs with no data on disk: a few sample scenes generated with
SUMO (``smart_marl/samples/*.smsc``) and the pretrained prior (``smart_marl/checkpoints/embedded/``,
loaded by :func:`smart_marl.model.checkpoint.load_prior` from the name :data:`EMBEDDED`).

The one resolver of the name ``"embedded"`` where scenes are taken: :func:`scene_sources` (a scene
source or a list of them -> readable paths, the samples' files in place of the name) and
:func:`sample_scenarios` (the scenes themselves)."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import ScenarioReadError
from .readers import read_scenarios
from .scenario import Scenario

EMBEDDED = "embedded"
"""The name that stands for what the package ships wherever a scene source (its sample scenes) or a
checkpoint path (its prior) is taken."""

SAMPLES_DIR = Path(__file__).resolve().parent / "samples"


def is_embedded(spec) -> bool:
    """Whether ``spec`` (a scene source, a checkpoint path, anything) is the name :data:`EMBEDDED`."""
    return isinstance(spec, str) and spec == EMBEDDED


def sample_files() -> list[Path]:
    """The sample scene files, in order; a :class:`ScenarioReadError` when the installation has none."""
    files = sorted(SAMPLES_DIR.glob("*.smsc"))
    if not files:
        raise ScenarioReadError(SAMPLES_DIR, "this installation ships no sample scenes")
    return files


def scene_sources(spec: str | os.PathLike | list) -> list[str | os.PathLike]:
    """``spec`` (a path or glob, a list of them, or :data:`EMBEDDED`) as a list of sources that
    :func:`~smart_marl.readers.read_scenarios` reads, every :data:`EMBEDDED` replaced in place by the
    sample files."""
    sources = [spec] if isinstance(spec, (str, os.PathLike)) else list(spec)
    out: list[str | os.PathLike] = []
    for src in sources:
        if is_embedded(src):
            out.extend(str(f) for f in sample_files())
        else:
            out.append(src)
    return out


def sample_scenarios() -> list[Scenario]:
    """The package's sample scenes (SUMO-generated, 91 frames at 10 Hz, current frame 10)."""
    return [s for f in sample_files() for s in read_scenarios(f)]
