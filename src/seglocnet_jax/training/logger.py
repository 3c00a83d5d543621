"""Scalar logging: TensorBoard event files (tensorboardX) and a JSON-lines file.

A resumed run says where it resumes (``resume_step``): rows of ``metrics.jsonl`` logged after
that checkpoint (``step > resume_step``) are dropped first (the file is rewritten atomically),
since the run logs those steps again; a row of ``resume_step`` itself that is logged again (the
final validation of a finished run re-run) replaces the old one. TensorBoard is told the same
with ``purge_step``. A line cut off by a kill is dropped as well.
"""

from __future__ import annotations

import json
import os
import re

from tensorboardX import SummaryWriter

from seglocnet_jax import fileio


class MetricsLogger:
    """Writes ``<workdir>/tb/`` (TensorBoard-readable) and ``<workdir>/metrics.jsonl``.

    Args:
      workdir: the run directory.
      enabled: False on processes other than 0 (nothing is written).
      resume_step: the step of the checkpoint the run resumes from (None: not resuming, the file
        is appended to as it is). Rows with a larger step are removed.
    """

    def __init__(self, workdir: str, enabled: bool = True, resume_step: int | None = None):
        self.enabled = enabled
        self.path = os.path.join(workdir, "metrics.jsonl")
        self.resume_step = None if resume_step is None else int(resume_step)
        self._stale: set[tuple[int, str]] = set()  # (step, split) rows a resume logs again
        self.writer = None
        if not enabled:
            return
        self._trim()
        purge = None if self.resume_step is None else self.resume_step + 1
        self.writer = SummaryWriter(os.path.join(workdir, "tb"), purge_step=purge)

    def _read_rows(self) -> tuple[list[tuple[str, dict]], bool]:
        """``([(line, row)], changed)``: the parsable rows; ``changed`` when a line was not."""
        if not os.path.exists(self.path):
            return [], False
        with open(self.path, encoding="utf-8") as f:
            text = f.read()
        rows, changed = [], bool(text) and not text.endswith("\n")
        for line in text.splitlines():
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                int(row["step"])
            except (ValueError, TypeError, KeyError):
                changed = True  # cut off by a kill (or not ours): dropped
                continue
            rows.append((line, row))
        return rows, changed

    def _rewrite(self, rows: list[tuple[str, dict]]) -> None:
        fileio.write_text_atomic(self.path, "".join(line + "\n" for line, _ in rows))

    def _trim(self) -> None:
        rows, changed = self._read_rows()
        if self.resume_step is not None:
            kept = [(ln, r) for ln, r in rows if int(r["step"]) <= self.resume_step]
            changed |= len(kept) != len(rows)
            rows = kept
            self._stale = {
                (int(r["step"]), str(r.get("split")))
                for _, r in rows
                if int(r["step"]) == self.resume_step
            }
        if changed:
            self._rewrite(rows)

    def write(self, step: int, prefix: str, scalars: dict[str, float]):
        if not self.enabled:
            return
        for key, value in _flatten(scalars):
            self.writer.add_scalar(_tag(f"{prefix}/{key}"), float(value), step)
        key = (int(step), str(prefix))
        if key in self._stale:  # logged before the resume at this very step: replace it
            self._stale.discard(key)
            rows, _ = self._read_rows()
            self._rewrite(
                [(ln, r) for ln, r in rows if (int(r["step"]), str(r.get("split"))) != key]
            )
        with open(self.path, "a", encoding="utf-8") as f:
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
