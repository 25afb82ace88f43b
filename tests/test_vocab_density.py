"""Density-weighted k-disks (a given disk radius) and per-type vocabulary sizes."""

from __future__ import annotations

import numpy as np

from smart_marl.tokens import load_motion_vocabulary
from smart_marl.tokens.kdisks import kdisks, kdisks_pass, mean_point_distance


def _dense_core_and_sparse_tail(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """9000 samples packed near the origin and 1000 spread widely: (samples [M, 4, 2], is_core [M])."""
    rng = np.random.default_rng(seed)
    core = rng.normal(size=(9000, 1, 2)) * 0.5 + rng.normal(size=(9000, 4, 2)) * 0.05
    tail = rng.normal(size=(1000, 1, 2)) * 20.0 + rng.normal(size=(1000, 4, 2)) * 0.05
    return np.concatenate([core, tail]).astype(np.float32), np.arange(10000) < 9000


def test_given_tolerance_keeps_the_first_centres_of_that_pass_and_puts_them_where_samples_are_dense():
    x, is_core = _dense_core_and_sparse_tail()
    covering = kdisks(x, 60, seed=3, progress=False)
    given = kdisks(x, 60, seed=3, progress=False, tolerance_m=0.1)
    assert given.tolerance_m == 0.1 < covering.tolerance_m
    assert given.centre_indices.tolist() == kdisks_pass(x, 0.1, 60, seed=3)[0].tolist()
    c = x[given.centre_indices]
    assert (mean_point_distance(c[:, None], c[None])[~np.eye(60, dtype=bool)] > 0.1).all()
    # the covering radius spends most tokens on the wide tail; the given one on the dense core
    assert is_core[covering.centre_indices].mean() < 0.5 < 0.8 < is_core[given.centre_indices].mean()
    core_error = lambda res: mean_point_distance(x[is_core][:, None], x[res.centre_indices][None]).min(1).mean()  # noqa: E731
    assert core_error(given) < 0.5 * core_error(covering)


def test_given_tolerance_that_covers_everything_with_fewer_centres_falls_back_to_the_search():
    x, _ = _dense_core_and_sparse_tail()
    res = kdisks(x, 60, seed=3, progress=False, tolerance_m=100.0)
    assert len(res.centre_indices) == 60 and res.tolerance_m < 100.0


def test_cli_vocab_build_takes_per_type_sizes_and_tolerances(sample_scene_file, tmp_path):
    from smart_marl.cli import main

    src = sample_scene_file  # 16 vehicles, 3 pedestrians, 3 cyclists
    assert main(["vocab", "build", str(src), "--sizes", "48/16/16", "--tolerance", "0.05/0/0", "--road-size", "0",
                 "--out", str(tmp_path), "--no-progress"]) == 0
    v = load_motion_vocabulary(tmp_path / "motion_48-16-16")
    assert v.sizes() == {"vehicle": 48, "pedestrian": 16, "cyclist": 16}
    assert v[0].tolerance_m == 0.05 and v[1].tolerance_m != 0.05
    assert main(["vocab", "build", str(src), "--sizes", "48/16", "--out", str(tmp_path), "--no-progress"]) == 2
