"""Create an Optuna study before sweep workers start.

Two ``rl_zoo3 -optimize`` workers started at once on a NEW storage race while Optuna creates
its tables (upstream optuna#4621): one dies with ``sqlite3.IntegrityError: UNIQUE constraint
failed: alembic_version.version_num`` or ``OperationalError: table studies already exists``
(6 of 10 pairs of processes released together on a new SQLite file). Once the study exists,
workers only load it, which is safe. So create it first, once::

    python -m training.study --storage sqlite:///runs/optuna.db --study-name tqc-force

or prefix every worker's command with it (``python -m training.study ... && python -m
rl_zoo3.train ... -optimize ...``): this module is itself safe to run from many workers at
once (it retries the creation when another process wins the race). The direction is
``maximize``, the zoo's (it maximizes the mean evaluation reward); an existing study of
another direction is refused rather than silently loaded.
"""

from __future__ import annotations

import argparse
import random
import sys
import time

__all__ = ["ensure_study", "main"]


def ensure_study(storage: str, study_name: str, direction: str = "maximize",
                 attempts: int = 20):
    """The study ``study_name`` in ``storage`` (an SQLAlchemy URL such as
    ``sqlite:///runs/optuna.db``), created if it does not exist, else loaded; safe when many
    processes call it at once on a new storage (a creation that loses the race to another
    process is retried, with a short random back-off, up to ``attempts`` times). Raises
    ``ValueError`` for an empty name or URL, another ``direction`` than the existing study's
    or an unknown direction."""
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    if not isinstance(storage, str) or not storage.strip():
        raise ValueError(f"storage must be a database URL such as sqlite:///runs/optuna.db, "
                         f"got {storage!r}")
    if not isinstance(study_name, str) or not study_name.strip():
        raise ValueError(f"study_name must be a non-empty string, got {study_name!r}")
    if direction not in ("maximize", "minimize"):
        raise ValueError(f"direction must be 'maximize' or 'minimize', got {direction!r}")
    if not isinstance(attempts, int) or attempts < 1:
        raise ValueError(f"attempts must be an integer >= 1, got {attempts!r}")
    last: Exception | None = None
    for k in range(attempts):
        try:
            study = optuna.create_study(storage=storage, study_name=study_name,
                                        direction=direction, load_if_exists=True)
            break
        except (SQLAlchemyError, optuna.exceptions.DuplicatedStudyError) as e:
            # another process is creating the tables or the study: wait, then load it
            last = e
            time.sleep(0.05 * (k + 1) * (1 + random.random()))
    else:
        raise RuntimeError(f"could not create or load study {study_name!r} in {storage!r} "
                           f"after {attempts} attempts: {last}") from last
    want = optuna.study.StudyDirection.MAXIMIZE if direction == "maximize" \
        else optuna.study.StudyDirection.MINIMIZE
    if study.directions != [want]:
        raise ValueError(f"study {study_name!r} in {storage!r} exists with direction(s) "
                         f"{[d.name.lower() for d in study.directions]}, not {direction!r}: "
                         f"use another --study-name")
    return study


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m training.study",
        description="Create an Optuna study (if it does not exist) before sweep workers "
                    "start: workers started at once on a new storage race (optuna#4621).")
    p.add_argument("--storage", required=True, help="database URL, e.g. sqlite:///runs/optuna.db")
    p.add_argument("--study-name", required=True)
    p.add_argument("--direction", default="maximize", choices=["maximize", "minimize"],
                   help="maximize (default) is rl_zoo3's")
    args = p.parse_args(argv)
    import optuna
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = ensure_study(args.storage, args.study_name, args.direction)
    print(f"study {study.study_name!r} in {args.storage}: {len(study.trials)} trial(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
