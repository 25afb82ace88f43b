"""Agents stage, what-if scenarios: edits of a scene or of a running rollout, run against the
unperturbed rollouts with the same seeds, and a table of what changed.

What comes in: a :class:`~smart_marl.scenario.Scenario`, a SMART prior (model, Checkpoint or
checkpoint path) and a :class:`WhatIf` (a list of edits, built in Python or read from a small YAML
file with :func:`load_script`). What goes out: a :class:`WhatIfResult` holding the baseline and
the perturbed rollouts (10 Hz poses of every track, local frame), the comparison table
(:func:`compare`: collisions, minimum distances and speeds of the affected agents, speeds of the
vehicles behind a braking or stalled one and of those approaching an overridden light, sim-agents
realism) and, with :func:`render_comparison`, a side-by-side animation.

In Python::

    from agents.whatif import Brake, Jaywalker, WhatIf, run_whatif
    result = run_whatif("runs/smart/last.json", scene, WhatIf([Brake(agent=52, at_s=1.0),
                        Jaywalker(relative_to="sdc", start=(30, -8), end=(30, 6))]), num_rollouts=8, seed=0)
    print(format_table(result.table)); render_comparison(result, "out/whatif.gif")

Two kinds of edits:

* **scene edits**, applied to the Scenario before the rollout (the prior then sees them in the
  history it conditions on): ``remove`` at ``at_s = 0`` drops the tracks
  (``Scenario.select_tracks``); ``insert``, ``jaywalker`` and ``stalled_vehicle`` with a ``pose``
  add a track whose history is made up (constant velocity back from its first pose; standing
  still for a stalled vehicle or a waiting pedestrian) and whose logged future is the script;
  ``traffic_light`` writes the forced state into the scene's signal states from its onset frame.
* **forced tokens** during the rollout (:meth:`RolloutState.step`'s ``forced_tokens``): ``brake``,
  ``stop``, ``cut_in``, ``follow``, ``stalled_vehicle`` and the motion of inserted agents. Each
  0.5 s step the scripted agent takes the token of its type's vocabulary closest to the next 5
  frames of its target path, looking one token ahead (:func:`smart_marl.tokens.motion.match_token_path`),
  from the pose it actually reached; given ``tokens`` are forced as they are. ``remove`` with
  ``at_s > 0`` takes the agents out of the running rollout (:meth:`RolloutState.set_agent_valid`): gone from every later frame
  and from everyone's neighbourhoods.

Traffic lights: the SMART model sees a signal only through the light embedding of the road
pieces of the controlled lane (``smart_marl.model.batch.scene_road`` reads the state at the
scene's *current frame* into ``road_light``; RoadNet embeds it once per scene). An override at
``at_s = 0`` is a scene edit, so RoadNet sees it from the start. An override at a later time
sets the lane's pieces' light codes with ``RolloutState.set_road_light`` at that step (RoadNet
re-runs, the KV cache's map-attention keys and values are re-projected; :func:`override_road_lights`),
so every later step's map attention reads the new light; the steps already taken keep the old one.

Times: ``at_s`` counts seconds after the current frame; an edit takes effect at token step
``round(at_s / 0.5)`` (token steps are 0.5 s). Agents are named by their track id or ``"sdc"``.
Positions are in the scene's source coordinates (``frame: source``, the default), the local frame
(``frame: local``), or the frame of an agent at the current frame (``relative_to: AGENT``: x
forward, y left, heading relative to the agent's).

The YAML format (one file per scenario; the package's examples, one per kind, are in ``agents/whatif/examples/``,
:data:`EXAMPLES_DIR`, written for the embedded sample scene ``sumo-7-000000-03``)::

    name: lead car brakes hard
    description: free text
    edits:
      - {kind: brake, agent: sdc, at_s: 1.0, decel_mps2: 8.0}
      - {kind: remove, agents: [1234, 5678], at_s: 0.0}
      - {kind: insert, type: vehicle, relative_to: sdc, path: [[20, 3.5], [80, 3.5]], speed_mps: 8}
      - {kind: traffic_light, lanes: all, state: stop, at_s: 0.0}

Kinds and their keys: :data:`KINDS` (the dataclasses in :mod:`.edits` document each key).

The package, one module per job, in the order they run:

* :mod:`.edits`: the edit dataclasses, :class:`WhatIf` and the YAML reader :func:`load_script`;
* :mod:`.prepare`: :func:`prepare`, scene edits and per-step actions (:class:`Prepared`);
* :mod:`.simulate`: :func:`simulate`, the prepared what-if driven through the rollout engine's
  stepping API (:meth:`RolloutState.run`) -> :class:`SimRollouts`;
* :mod:`.compare`: :func:`run_whatif` and :func:`compare`, the table of what changed (geometry from
  :mod:`smart_marl.geometry`, realism from :mod:`smart_marl.metrics`);
* :mod:`.output`: :func:`format_table`, :func:`write_table_csv` and :func:`render_comparison`.
"""

from .compare import WhatIfResult, agent_min_distance_m, colliding_agents, compare, run_whatif
from .edits import (
    EXAMPLES_DIR, KINDS, MAX_STEPS, Brake, CutIn, Follow, Insert, Jaywalker, Placement, Remove, StalledVehicle, Stop,
    TrafficLightOverride, WhatIf, WhatIfError, check_edit, example_scripts, load_script, script_path,
)
from .output import format_table, render_comparison, write_table_csv
from .prepare import Prepared, prepare
from .simulate import SimRollouts, override_road_lights, simulate

__all__ = [
    "EXAMPLES_DIR", "KINDS", "MAX_STEPS", "Brake", "CutIn", "Follow", "Insert", "Jaywalker", "Placement", "Prepared", "Remove", "SimRollouts",
    "StalledVehicle", "Stop", "TrafficLightOverride", "WhatIf", "WhatIfError", "WhatIfResult", "agent_min_distance_m",
    "check_edit", "colliding_agents", "compare", "example_scripts", "format_table", "load_script", "override_road_lights", "prepare", "render_comparison",
    "run_whatif", "script_path", "simulate", "write_table_csv",
]
