"""training.study: an Optuna study created before sweep workers start,
safely even by many workers released at the same instant on a new SQLite file (optuna#4621:
Optuna's own create_study races there)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna")

from training.study import ensure_study, main  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

# waits for a shared start time, then calls the function under test on the storage
WORKER = """
import sys, time
import optuna
optuna.logging.set_verbosity(optuna.logging.WARNING)
from training.study import ensure_study
storage, go = sys.argv[1], float(sys.argv[2])
while time.time() < go:
    pass
ensure_study(storage, "race")
"""


def test_workers_released_together_on_a_new_file_all_get_the_study(tmp_path):
    """Four rounds of two processes released at the same instant on a new file. Optuna's
    create_study(load_if_exists=True) alone failed in 6 of 10 such pairs ("table studies
    already exists" / UNIQUE constraint failed: alembic_version.version_num)."""
    for k in range(4):
        storage = f"sqlite:///{tmp_path / f'race{k}.db'}"
        go = time.time() + 5.0        # after both interpreters have imported optuna
        procs = [subprocess.Popen([sys.executable, "-c", WORKER, storage, str(go)], cwd=ROOT,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for _ in range(2)]
        for p in procs:
            _, err = p.communicate(timeout=120)
            assert p.returncode == 0, err[-2000:]
        study = optuna.load_study(study_name="race", storage=storage)
        assert study.direction == optuna.study.StudyDirection.MAXIMIZE and not study.trials


def test_the_command_creates_then_loads_and_refuses_another_direction(tmp_path, capsys):
    storage = f"sqlite:///{tmp_path / 'one.db'}"
    assert main(["--storage", storage, "--study-name", "s"]) == 0
    assert main(["--storage", storage, "--study-name", "s"]) == 0     # exists: loaded
    assert "0 trial(s)" in capsys.readouterr().out
    assert len(optuna.get_all_study_names(storage)) == 1
    with pytest.raises(ValueError, match="exists with direction.*maximize.*not 'minimize'"):
        ensure_study(storage, "s", direction="minimize")
    with pytest.raises(ValueError, match="study_name must be a non-empty string"):
        ensure_study(storage, "")
    with pytest.raises(ValueError, match="direction must be 'maximize' or 'minimize'"):
        ensure_study(storage, "t", direction="up")
