"""The log of a run (training, fine-tuning): one CSV file per split, always, and TensorBoard when
it is importable (the ``train`` extra).

``RunLog(out_dir, {"train": [...columns], "val": [...]})`` writes ``out_dir/train.csv`` and
``out_dir/val.csv`` (floats with 6 significant digits, missing columns empty) and the TensorBoard
scalars ``train/NAME``, ``val/NAME`` under ``out_dir/tensorboard``, indexed by the row's
``step_key`` column. On resume (``resume_step > 0``) the rows after the resumed step are dropped
and TensorBoard purges its later events, so the log reads as one uninterrupted run.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Mapping, Sequence


class RunLog:
    """CSV files per split (always) and TensorBoard (when importable) of one process."""

    def __init__(self, out_dir: Path, columns: Mapping[str, Sequence[str]], step_key: str = "step", resume_step: int = 0,
                 tensorboard: bool = True) -> None:
        self.step_key = step_key
        self.columns = {split: list(cols) for split, cols in columns.items()}
        self.files = {split: Path(out_dir) / f"{split}.csv" for split in self.columns}
        for split, path in self.files.items():
            rows = []
            if path.is_file() and resume_step:
                with open(path, newline="") as f:
                    rows = [r for r in csv.DictReader(f) if int(r[step_key]) <= resume_step]
            with open(path, "w", newline="") as f:
                w = csv.DictWriter(f, self.columns[split])
                w.writeheader()
                w.writerows(rows)
        self.tb = None
        self.note = None  # why there is no TensorBoard log, when it was asked for
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter  # optional: the train extra

                self.tb = SummaryWriter(str(Path(out_dir) / "tensorboard"), purge_step=resume_step + 1 if resume_step else None)
            except ImportError as exc:
                self.note = f"TensorBoard is not importable ({exc}); logging to CSV only (pip install 'smart-marl[train]')"

    def write(self, split: str, row: Mapping[str, float]) -> None:
        """Append ``row`` to the split's CSV (its columns only) and its numbers to TensorBoard."""
        columns = self.columns[split]
        with open(self.files[split], "a", newline="") as f:
            csv.DictWriter(f, columns, extrasaction="ignore").writerow(
                {k: (f"{row[k]:.6g}" if isinstance(row.get(k), float) else row.get(k, "")) for k in columns})
        if self.tb is not None:
            for k, v in row.items():
                if k != self.step_key and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"{split}/{k}", v, int(row[self.step_key]))

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
