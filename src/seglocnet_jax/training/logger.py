"""Scalar logging: TensorBoard event files (tensorboardX) and a JSON-lines file."""

from __future__ import annotations

import json
import os

from tensorboardX import SummaryWriter


class MetricsLogger:
    """Writes ``<workdir>/tb/`` (TensorBoard-readable) and ``<workdir>/metrics.jsonl``."""

    def __init__(self, workdir: str, enabled: bool = True):
        self.enabled = enabled
        self.path = os.path.join(workdir, "metrics.jsonl")
        self.writer = SummaryWriter(os.path.join(workdir, "tb")) if enabled else None

    def write(self, step: int, prefix: str, scalars: dict[str, float]):
        if not self.enabled:
            return
        for key, value in scalars.items():
            self.writer.add_scalar(f"{prefix}/{key}", float(value), step)
        with open(self.path, "a") as f:
            f.write(json.dumps({"step": int(step), "split": prefix, **scalars}) + "\n")
        self.writer.flush()

    def close(self):
        if self.writer is not None:
            self.writer.close()
