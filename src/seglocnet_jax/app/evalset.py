"""An evaluation's output set, written whole or not at all: ``results.json``, the per-frame
arrays (``sequential/``), the figures (``figures/``) and, for the ``evaluate`` app, its
``config.json``. The train app's final evaluation and the ``evaluate`` app share it.

The set is written into a fresh staging directory ``<dir>/evaluation.staging-<pid>`` and moved
into place when it is complete (:meth:`OutputSet.commit`): the previous set, if there is one,
is first moved aside to ``<dir>/evaluation.discarded-<UTC time>/`` (said on stdout; nothing is
deleted), then the new items are moved in, ``results.json`` last. While items move, the file
``<dir>/INCOMPLETE`` says so; a process killed then leaves a directory that names itself
incomplete, which readers refuse (:func:`incomplete`; ``experiments/collect_results.py``,
``experiments/paper_tables.py``) and which the next evaluation into it moves aside. A process
killed before the move leaves the previous complete set as it was, and a staging directory that
the next run into the directory removes.
"""

from __future__ import annotations

import os
import re
import shutil
import time

from seglocnet_jax import fileio

RESULTS = "results.json"
RUN_CONFIG = "config.json"
INCOMPLETE = "INCOMPLETE"
STAGING = "evaluation.staging"
DISCARDED = "evaluation"  # moved aside to <dir>/evaluation.discarded-<time>
FIGURES, ARRAYS = "figures", "sequential"
TRAIN_ITEMS = (FIGURES, ARRAYS, RESULTS)  # the run's config.json is the run's, not the set's
EVAL_ITEMS = (RUN_CONFIG, FIGURES, ARRAYS, RESULTS)
_STAGING_RE = re.compile(re.escape(STAGING) + r"-(\d+)$")


def _move(src: str, dst: str) -> None:
    os.rename(src, dst)  # one name for the tests to cut the move short, as a kill would


def progress(msg: str) -> None:
    print(f"[seglocnet] {msg}", flush=True)


def incomplete(directory: str) -> str | None:
    """``<directory>/INCOMPLETE`` when an evaluation was cut off while moving its set into
    ``directory`` (its files may mix two evaluations), else None."""
    path = os.path.join(directory, INCOMPLETE)
    return path if os.path.exists(path) else None


def is_aside(name: str) -> bool:
    """Whether a directory entry is a set moved aside or being staged (not a result to read)."""
    return ".discarded-" in name or _STAGING_RE.match(name) is not None


class OutputSet:
    """The evaluation set of ``directory`` with the entries ``items`` (``results.json`` last).

    Usage: ``staging = s.open()``; write every item under ``staging``; ``s.commit()``
    (``s.abandon()`` on an error). The caller holds the directory's lock throughout.
    """

    def __init__(self, directory: str, items: tuple[str, ...]):
        if items[-1] != RESULTS:
            raise ValueError(f"{RESULTS} must be the last item moved in, got {items}")
        self.directory = os.path.abspath(directory)
        self.items = items
        self.staging = os.path.join(self.directory, f"{STAGING}-{os.getpid()}")

    def present(self) -> list[str]:
        """The items of a set in the directory now."""
        return [n for n in self.items if os.path.lexists(os.path.join(self.directory, n))]

    def open(self) -> str:
        """Removes staging directories of killed processes, moves aside the files of a set
        that was cut off while moving in, and returns a fresh, empty staging directory."""
        os.makedirs(self.directory, exist_ok=True)
        for name in sorted(os.listdir(self.directory)):
            m = _STAGING_RE.match(name)
            if m and (int(m.group(1)) == os.getpid() or not fileio.pid_alive(int(m.group(1)))):
                shutil.rmtree(os.path.join(self.directory, name))
                progress(f"removed {name}, the unfinished evaluation of a killed process")
        marker = incomplete(self.directory)
        if marker is not None:
            dest = self._move_aside(self.present())
            os.remove(marker)
            progress(
                f"{self.directory}: an evaluation was cut off while moving its files in; moved "
                f"what it left to {dest}"
            )
        os.makedirs(self.staging)
        return self.staging

    def _move_aside(self, names: list[str]) -> str | None:
        if not names:
            return None
        dest = fileio.discarded_path(os.path.join(self.directory, DISCARDED))
        os.makedirs(dest)
        for name in names:
            _move(os.path.join(self.directory, name), os.path.join(dest, name))
        return dest

    def commit(self) -> str | None:
        """Moves the staged set into place (the previous one aside first); returns where the
        previous set went (None: there was none)."""
        staged = sorted(os.listdir(self.staging))
        unknown = [n for n in staged if n not in self.items]
        if unknown or RESULTS not in staged:
            raise RuntimeError(
                f"{self.staging}: an evaluation set holds {list(self.items)} ending with "
                f"{RESULTS}; found {staged}"
            )
        fileio.write_text_atomic(
            os.path.join(self.directory, INCOMPLETE),
            f"pid {os.getpid()} began moving an evaluation set into this directory at "
            f"{time.strftime('%Y-%m-%dT%H:%M:%S')} and did not finish: its files may belong to "
            "two evaluations. Run the evaluation again (it moves them aside).\n",
        )
        moved = self._move_aside(self.present())
        if moved:
            progress(f"moved the previous evaluation set of {self.directory} to {moved}")
        for name in self.items:  # results.json last
            if name in staged:
                _move(os.path.join(self.staging, name), os.path.join(self.directory, name))
        os.remove(os.path.join(self.directory, INCOMPLETE))
        os.rmdir(self.staging)
        return moved

    def abandon(self) -> None:
        """Removes the staging directory (an error stopped the evaluation)."""
        shutil.rmtree(self.staging, ignore_errors=True)
