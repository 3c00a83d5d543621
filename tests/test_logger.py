"""MetricsLogger: a resumed run leaves no duplicate rows in metrics.jsonl."""

import json

from seglocnet_jax.training.logger import MetricsLogger


def _rows(path):
    with open(path) as f:
        return [json.loads(line) for line in f]


def _keys(path):
    return [(r["step"], r["split"]) for r in _rows(path)]


def test_resume_drops_rows_logged_after_the_checkpoint(tmp_path):
    log = MetricsLogger(str(tmp_path))
    for step in (10, 20, 30):
        log.write(step, "train", {"loss": float(step)})
    log.write(20, "val", {"R@5m": 1.0})
    log.close()
    with open(log.path, "a") as f:
        f.write('{"step": 40, "split": "tr')  # a line cut off by the kill
    # The checkpoint the run resumes from is step 20: steps 30 and 40 are logged again.
    log = MetricsLogger(str(tmp_path), resume_step=20)
    assert _keys(log.path) == [(10, "train"), (20, "train"), (20, "val")]
    log.write(30, "train", {"loss": 3.5})
    log.close()
    assert _keys(log.path) == [(10, "train"), (20, "train"), (20, "val"), (30, "train")]
    assert _rows(log.path)[-1]["loss"] == 3.5


def test_rows_of_the_resume_step_logged_again_replace_the_old_ones(tmp_path):
    log = MetricsLogger(str(tmp_path))
    log.write(100, "train", {"loss": 1.0})
    log.write(100, "val", {"R@5m": 5.0})
    log.write(100, "test", {"R@5m": 6.0})
    log.close()
    log = MetricsLogger(str(tmp_path), resume_step=100)  # a finished run started again
    log.write(100, "val", {"R@5m": 5.5})
    log.write(100, "test", {"R@5m": 6.5})
    log.close()
    rows = _rows(log.path)
    assert sorted(_keys(log.path)) == [(100, "test"), (100, "train"), (100, "val")]
    assert {r["split"]: r.get("R@5m") for r in rows} == {"train": None, "val": 5.5, "test": 6.5}


def test_without_resume_step_the_file_is_appended_to(tmp_path):
    log = MetricsLogger(str(tmp_path))
    log.write(5, "train", {"loss": 1.0})
    log.close()
    log = MetricsLogger(str(tmp_path))
    log.write(3, "train", {"loss": 2.0})
    log.close()
    assert _keys(log.path) == [(5, "train"), (3, "train")]
    disabled = MetricsLogger(str(tmp_path / "other"), enabled=False, resume_step=0)
    disabled.write(1, "train", {"loss": 0.0})
    assert not (tmp_path / "other").exists()
