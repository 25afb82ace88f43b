"""Motion-token reconstruction error on the real scenes: tokenize the ground truth by rolling
matching, rebuild 10 Hz poses from the tokens, compare.

Vocabularies are built from other scenes than the ones evaluated: the real scenes in
../shared/data are split into two halves (alternating, in path order); each half is evaluated with
the vocabulary built from the other half (vocab_source "half_a" / "half_b", names the scenes it was
built from). Methods: "kdisks" (ours) and "uniform_grid" (the MotionLM-style baseline: a uniform
grid over the end pose (dx, dy, dheading) with the same number of tokens). As a labelled yardstick
only, the SMART authors' published vocabulary (built from all of WOMD) is evaluated on all scenes
(vocab_source "reference_smart_womd"). With --noise-topk K, k-disks is also run with top-K noise.
With --generated PATH (scenes made by ``smart-marl generate-sumo``), k-disks and the grid are also
built from those generated scenes and evaluated on every real scene (vocab_source "sumo...": the
cross-domain case).

Prints one JSON line per (vocab_source, method, vocab_size, agent_type): mean_pos_err_m (over every
valid 10 Hz frame a valid token covers, anchors excluded), p95_pos_err_m, final_pos_err_m (per
agent, at the last frame its token sequence reaches, averaged), mean_heading_err_rad,
mean_boundary_pos_err_m (at token boundaries only, the reference's published figure's measure),
frames, agents.

    .venv/bin/python benchmarks/token_reconstruction.py [--sizes 2048] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from smart_marl import read_scenarios  # noqa: E402
from smart_marl.readers import expand_paths  # noqa: E402
from smart_marl.scenario import AgentType, wrap_angle  # noqa: E402
from smart_marl.tokens import (  # noqa: E402
    MOTION_TYPES, build_motion_vocabulary, collect_snippets, load_reference_motion_vocabulary, reconstruct,
    tokenize_motion, uniform_grid_vocabulary,
)

SCENE_FOLDERS = ("av2", "gpudrive_json", "nocturne_json", "scenarionet", "smart_pkl", "womd_tfrecord")


def load_real_scenes(data: Path) -> list:
    """Every scene in the scene folders of ``data`` (vocabulary pickles and submissions left out)."""
    scenes = []
    for folder in SCENE_FOLDERS:
        if not (data / folder).is_dir():
            continue
        for path in expand_paths(data / folder):
            try:
                for sc in read_scenarios(path):
                    sc.metadata.setdefault("path", str(Path(path).relative_to(data)))
                    scenes.append(sc)
            except Exception as exc:  # a reader that has not landed or rejects the file: say so
                print(f"# skipped {path}: {type(exc).__name__}: {exc}", file=sys.stderr)
    return scenes


def reconstruction_errors(scenes, vocab, **tok_kwargs) -> dict:
    """Per agent type: arrays of position / heading errors (m, rad) and per-agent final errors."""
    acc = {t: {"pos": [], "head": [], "final": [], "boundary": [], "agents": 0} for t in MOTION_TYPES}
    for sc in scenes:
        tok = tokenize_motion(sc, vocab, **tok_kwargs)
        poses, pvalid = reconstruct(tok, vocab, sc.num_frames)
        gt_valid = sc.tracks.valid
        anchor = np.zeros_like(pvalid)
        b = tok.boundaries
        for k in range(tok.num_steps):  # anchors: the start frame of tokens that do not continue a valid one
            starts = tok.valid[:, k] & ~(tok.valid[:, k - 1] if k > 0 else np.zeros(len(tok.valid), bool))
            anchor[starts, b[k]] = True
        cover = pvalid & gt_valid & ~anchor
        pos_err = np.linalg.norm(poses[..., :2] - sc.tracks.position[..., :2], axis=-1)
        head_err = np.abs(wrap_angle(poses[..., 2].astype(np.float64) - sc.tracks.heading))
        on_boundary = np.zeros(sc.num_frames, bool)
        on_boundary[b] = True
        for t in MOTION_TYPES:
            rows = sc.tracks.types == t
            c = cover & rows[:, None]
            acc[t]["pos"].append(pos_err[c])
            acc[t]["head"].append(head_err[c])
            acc[t]["boundary"].append(pos_err[c & on_boundary[None]])
            has = c.any(1)
            last = sc.num_frames - 1 - np.argmax(c[:, ::-1], axis=1)
            acc[t]["final"].append(pos_err[np.flatnonzero(has), last[has]])
            acc[t]["agents"] += int(has.sum())
    return {t: {k: (np.concatenate(v) if isinstance(v, list) and v else v) for k, v in d.items()} for t, d in acc.items()}


def report(errors: dict, vocab, method: str, source: str, extra: dict | None = None) -> None:
    for t in MOTION_TYPES:
        e = errors[t]
        if len(e["pos"]) == 0:
            continue
        line = {
            "agent_type": AgentType(t).name.lower(), "vocab_size": vocab[t].size, "method": method,
            "mean_pos_err_m": round(float(e["pos"].mean()), 4), "p95_pos_err_m": round(float(np.percentile(e["pos"], 95)), 4),
            "final_pos_err_m": round(float(e["final"].mean()), 4), "mean_heading_err_rad": round(float(e["head"].mean()), 4),
            "mean_boundary_pos_err_m": round(float(e["boundary"].mean()), 4), "vocab_source": source,
            "frames": int(len(e["pos"])), "agents": int(e["agents"]),
        }
        line.update(extra or {})
        print(json.dumps(line), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--sizes", default="2048", help="comma-separated vocabulary sizes")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise-topk", type=int, default=5, help="also evaluate k-disks with top-K noise (0: skip)")
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--generated", type=Path, default=None,
                    help="generated scenes (e.g. a generate-sumo cache) to build cross-domain vocabularies from")
    ap.add_argument("--generated-scenes", type=int, default=500, help="how many generated scenes to build from")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    t0 = time.time()
    scenes = load_real_scenes(args.data)
    if len(scenes) < 2:
        print(f"need at least 2 real scenes under {args.data}, found {len(scenes)}", file=sys.stderr)
        return 1
    halves = {"half_a": scenes[0::2], "half_b": scenes[1::2]}
    print(f"# {len(scenes)} scenes read in {time.time() - t0:.1f}s; half_a {len(halves['half_a'])}, half_b {len(halves['half_b'])}", file=sys.stderr)
    for src, other in (("half_a", "half_b"), ("half_b", "half_a")):
        snippets, prov = collect_snippets(halves[src])
        print(f"# {src}: snippets {prov['snippets']}", file=sys.stderr)
        for size in sizes:
            t1 = time.time()
            kd = build_motion_vocabulary(snippets, size, seed=args.seed, provenance=prov, progress=False)
            print(f"# {src} k-disks {size} built in {time.time() - t1:.1f}s, tolerances "
                  + ", ".join(f"{AgentType(t).name.lower()} {kd[t].tolerance_m:.4f} m" for t in MOTION_TYPES), file=sys.stderr)
            grid = uniform_grid_vocabulary(snippets, size, provenance=prov)
            label = f"{src} (built from {len(halves[src])} scenes, evaluated on {other})"
            report(reconstruction_errors(halves[other], kd), kd, "kdisks", label)
            report(reconstruction_errors(halves[other], grid), grid, "uniform_grid", label)
            if args.noise_topk > 1:
                report(reconstruction_errors(halves[other], kd, noise_topk=args.noise_topk, rng=args.seed), kd, "kdisks", label,
                       {"noise_topk": args.noise_topk})
    if args.generated is not None:
        generated = []
        for sc in read_scenarios(args.generated):
            generated.append(sc)
            if len(generated) >= args.generated_scenes:
                break
        snippets, prov = collect_snippets(generated)
        print(f"# generated: {len(generated)} scenes, snippets {prov['snippets']}", file=sys.stderr)
        for size in sizes:
            kd = build_motion_vocabulary(snippets, size, seed=args.seed, provenance=prov, progress=False)
            grid = uniform_grid_vocabulary(snippets, size, provenance=prov)
            label = f"sumo (built from {len(generated)} generated scenes of {args.generated}, evaluated on all {len(scenes)} real scenes)"
            report(reconstruction_errors(scenes, kd), kd, "kdisks", label)
            report(reconstruction_errors(scenes, grid), grid, "uniform_grid", label)
    ref_path = args.data / "smart_tokens" / "cluster_frame_5_2048.pkl"
    if not args.no_reference and ref_path.is_file():
        ref = load_reference_motion_vocabulary(ref_path)
        report(reconstruction_errors(scenes, ref), ref, "kdisks", "reference_smart_womd (yardstick: the SMART authors' published vocabulary, all of WOMD; evaluated on all scenes)")
    print(f"# total {time.time() - t0:.1f}s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
