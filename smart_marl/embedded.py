"""What the package ships so that it runs with no data on disk: a few sample scenes generated with
SUMO (``smart_marl/samples/*.smsc``) and the pretrained prior (``smart_marl/checkpoints/embedded/``,
loaded by :func:`smart_marl.model.checkpoint.load_embedded`)."""

from __future__ import annotations

from pathlib import Path

from .errors import ScenarioReadError
from .readers import read_scenarios
from .scenario import Scenario

SAMPLES_DIR = Path(__file__).resolve().parent / "samples"


def sample_scenarios() -> list[Scenario]:
    """The package's sample scenes (SUMO-generated, 91 frames at 10 Hz, current frame 10)."""
    files = sorted(SAMPLES_DIR.glob("*.smsc"))
    if not files:
        raise ScenarioReadError(SAMPLES_DIR, "this installation ships no sample scenes")
    return [s for f in files for s in read_scenarios(f)]
