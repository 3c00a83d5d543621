"""The app config the app-level tests build (one builder: tests/test_app.py,
tests/test_sequential.py and tests/test_evaluate_run.py), on the two tiny simulated datasets
that conftest.py's session fixtures root.

``TINY``: Helsinki only, no drives (16/8/8 frames). ``TINY_DRIVES``: 4/4/4 frames plus two short
Helsinki validation drives (``drives_val``, 4-7 frames each)."""

from __future__ import annotations

TINY = {
    "name": "tiny",
    "test_city": None,
    "num_val_drives": 0,  # no drive splits: not rendered
    "num_train": 16,
    "num_val": 8,
    "num_test": 8,
    "shard_size": 8,
    "render_batch": 8,
}
TINY_DRIVES = {
    "name": "tiny_seq",
    "test_city": None,
    "num_train": 4,
    "num_val": 4,
    "num_test": 4,
    "shard_size": 8,
    "render_batch": 8,
    "num_val_drives": 2,  # drives_val: two short Helsinki drives
    "drive_length_m": 30.0,  # 4-7 frames each
    "min_val_drive_m": 15.0,
}
# The filter's splits on TINY_DRIVES (no test city: no drives, no drives_val_unseen).
DRIVES_EVAL = {
    "sequential_splits": ["drives_val"],
    "calibration_split": "drives_val",
    "temperature_drives": "drives_val",
}


def app_tree(data_root: str, name: str, data: dict, *, train=None, eval_=None) -> dict:
    """The resolved config tree of a tiny app run: a LiDAR-only tiny model, 64 rotations,
    batches of 2, 2 training steps checkpointed at the end; ``train`` and ``eval_`` update
    their sections (one level deep)."""
    return {
        "name": name,
        "data": {**data, "root": data_root},
        "map": {"kind": "hd"},
        "loader": {"max_points": 4096, "num_threads": 0},
        "model": {"modality": "lidar"},
        "solver": {"num_rotations": 64},
        "train": {
            "batch_size": 2,
            "num_steps": 2,
            "num_devices": 1,
            "eval_every": 0,
            "val_batches": 1,
            "log_every": 1,
            "optim": {"warmup_steps": 1},
            "checkpoint": {"every_steps": 2},
            **(train or {}),
        },
        "eval": dict(eval_ or {}),
    }
