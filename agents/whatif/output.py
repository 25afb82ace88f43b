"""What-if scenarios, output: the comparison table as text and CSV, and the side-by-side animation.

Stage: agents (what-if), the end of the flow. What comes in: a
:class:`~agents.whatif.compare.WhatIfResult`. What goes out: a fixed-width table
(:func:`format_table`), ``table.csv`` (:func:`write_table_csv`) and a GIF or MP4 with the baseline
on the left and the what-if on the right (:func:`render_comparison`, :mod:`smart_marl.render`).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from smart_marl.render import BevRenderer, EpisodeRecorder
from smart_marl.scenario import DT_S

from .compare import WhatIfResult, box_size_m


def format_table(rows: list[dict]) -> str:
    lines = [f"{'quantity':<38} {'agent':<28} {'baseline':>10} {'what-if':>10} {'change':>10}"]
    for r in rows:
        lines.append(f"{r['quantity']:<38} {r['agent']:<28} {r['baseline']:>10.3f} {r['whatif']:>10.3f} {r['change']:>+10.3f}")
    return "\n".join(lines)


def write_table_csv(rows: list[dict], path: str | os.PathLike) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with p.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["quantity", "agent", "baseline", "whatif", "change"])
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return p


def render_comparison(result: WhatIfResult, path: str | os.PathLike, rollout_index: int = 0, size_px: int = 400,
                      view_radius_m: float = 50.0, fps: float = 10.0) -> Path:
    """A side-by-side animation (GIF or MP4 by extension): the baseline rollout on the left, the
    what-if on the right (same rollout index, same seed); affected agents drawn in strong colours,
    the view fixed on the first affected agent (else the self-driving car)."""
    base, pert = result.baseline, result.perturbed
    scene = pert.scene
    cf = scene.current_frame
    aff = [t for t in result.prepared.affected if np.isin(t, scene.tracks.ids)]
    if aff:
        k = int(np.flatnonzero(scene.tracks.ids == aff[0])[0])
    else:
        k = scene.sdc_index if scene.sdc_index >= 0 else int(np.flatnonzero(scene.tracks.valid[:, cf])[0])
    center = tuple(float(v) for v in scene.tracks.position[k, cf, :2])
    rec = EpisodeRecorder(path, fps=fps)
    sides = []
    for sim, label in ((base, "baseline"), (pert, result.whatif.name)):
        renderer = BevRenderer(sim.scene, size_px=size_px, view_radius_m=view_radius_m, center=center)
        ctrl = np.isin(sim.scene.tracks.ids, list(result.prepared.affected))
        sides.append((renderer, sim, ctrl, label))
    size = None
    for f in range(base.poses.shape[2]):
        images = []
        for renderer, sim, ctrl, label in sides:
            sc = sim.scene
            p, on = sim.poses[rollout_index, :, f], sim.present[rollout_index, :, f]
            trail_lo = max(0, f - 10)
            trail = sim.poses[rollout_index, :, trail_lo: f + 1, :2]
            tv = sim.present[rollout_index, :, trail_lo: f + 1]
            img = renderer.render(np.nan_to_num(p[:, :2]), np.nan_to_num(p[:, 2]), box_size_m(sc), on, sc.tracks.types, ctrl,
                                  ego_index=-1, trajectories=np.nan_to_num(trail), trajectories_valid=tv,
                                  light_states=sim.light_states[f] if sim.light_states.shape[1] else None,
                                  light_present=sim.light_present[f] if sim.light_states.shape[1] else None,
                                  text=f"{label}  t={DT_S * (f + 1):4.1f} s")
            images.append(img)
        frame = np.concatenate([images[0], np.full((images[0].shape[0], 4, 3), 255, np.uint8), images[1]], 1)
        size = size or frame.shape
        rec.add(frame)
    for renderer, *_ in sides:
        renderer.close()
    return rec.write()

