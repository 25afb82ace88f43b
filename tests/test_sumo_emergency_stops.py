"""Emergency stops in generated SUMO traffic (SumoConfig.emergency_stop_rate_per_min, sumo_sim.EmergencyStops;
issue 33): cars that brake hard to a standstill, and the same network and demand without them."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("libsumo", reason="SUMO is an optional extra: pip install 'smart-marl[sumo]'")
pytest.importorskip("sumolib", reason="SUMO is an optional extra: pip install 'smart-marl[sumo]'")
pytest.importorskip("shapely", reason="the SUMO source needs shapely (smart-marl[sumo])")

from smart_marl.scenario import AgentType  # noqa: E402
from smart_marl.sources.sumo import SumoConfig, simulate_scenes  # noqa: E402

SMALL = dict(scenes_per_sim=4, warmup_s=20.0, scene_spacing_s=3.0)


def _token_decels(scenes) -> np.ndarray:
    """Every moving vehicle's speed drop over 0.5 s (m/s2), over every scene's frames where it is logged."""
    out = []
    for sc in scenes:
        tr = sc.tracks
        veh = np.flatnonzero(tr.types == int(AgentType.VEHICLE))
        v = np.linalg.norm(np.diff(tr.position[veh, :, :2], axis=1), axis=-1) / 0.1  # [V, T-1]
        ok = tr.valid[veh, 1:] & tr.valid[veh, :-1]
        drop = (v[:, :-5] - v[:, 5:]) / 0.5
        out.append(drop[ok[:, :-5] & ok[:, 5:]])
    return np.concatenate(out)


def test_emergency_stops_add_hard_braking_to_the_same_traffic():
    calm = simulate_scenes(3, 0, SumoConfig(**SMALL))
    stops = simulate_scenes(3, 0, SumoConfig(**SMALL, emergency_stop_rate_per_min=6.0))
    assert calm and stops
    assert calm[0].metadata["network"] == stops[0].metadata["network"]  # the same network (the scenes are cut around other cars)
    hard_calm, hard_stops = (_token_decels(s) > 5.0 for s in (calm, stops))
    assert hard_stops.sum() > 3 * max(hard_calm.sum(), 1)
    assert _token_decels(stops).max() < 9.5  # within the emergency range (and SUMO's emergencyDecel of 9)


def test_emergency_stop_settings_are_checked():
    with pytest.raises(ValueError, match="emergency_stop_rate_per_min must be >= 0"):  # the SUMO config's rules
        SumoConfig(emergency_stop_rate_per_min=-1.0)
    with pytest.raises(ValueError, match="emergency_decel_mps2"):
        SumoConfig(emergency_decel_mps2=(6.0, 4.0))
