"""smart-marl: SMART (next-token prediction over motion tokens) as a behaviour prior for multi-agent
driving environments.

The data flow (README.md and docs/): driving logs -> :class:`Scenario` -> scene cache -> tokens ->
SMART model -> rollouts -> PettingZoo environment -> fine-tuning -> metrics.
"""

from .errors import ScenarioReadError, ScenarioValidationError, SmartMarlError, UnknownFormatError
from .readers import detect_format, read_scenario, read_scenarios
from .scenario import (
    CURRENT_FRAME,
    DT_S,
    AgentType,
    LaneType,
    LinkType,
    MapFeatureType,
    RoadEdgeType,
    RoadLineType,
    RoadMap,
    SceneFrame,
    Scenario,
    SignalState,
    TrafficLights,
    Tracks,
)
from .version import __version__

__all__ = [
    "CURRENT_FRAME", "DT_S", "AgentType", "LaneType", "LinkType", "MapFeatureType", "RoadEdgeType", "RoadLineType",
    "RoadMap", "SceneFrame", "Scenario", "SignalState", "TrafficLights", "Tracks",
    "ScenarioReadError", "ScenarioValidationError", "SmartMarlError", "UnknownFormatError",
    "detect_format", "read_scenario", "read_scenarios", "__version__",
]
