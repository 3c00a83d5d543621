"""Scalar logging: TensorBoard event files (tensorboardX) and a JSON-lines file."""

from __future__ import annotations

import json
import os
import re

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
        for key, value in _flatten(scalars):
            self.writer.add_scalar(_tag(f"{prefix}/{key}"), float(value), step)
        with open(self.path, "a") as f:
            f.write(json.dumps({"step": int(step), "split": prefix, **scalars}) + "\n")
        self.writer.flush()

    def close(self):
        if self.writer is not None:
            self.writer.close()


def _tag(name: str) -> str:
    """TensorBoard tags allow ``[A-Za-z0-9_./-]``: ``val/R@5m`` -> ``val/R_at_5m``."""
    name = name.replace("@", "_at_").replace("°", "deg").replace(" ", "_")
    return re.sub(r"[^A-Za-z0-9_./-]", "_", name)


def _flatten(scalars: dict, prefix: str = ""):
    """``(name, number)`` pairs; nested dicts become ``outer/inner``, None values are skipped."""
    for key, value in scalars.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}/")
        elif value is not None:
            yield f"{prefix}{key}", value
