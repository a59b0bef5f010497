"""A log of every body a run evaluates: one SQLite table, written as the run goes.

Table `bodies`, one row per evaluation: step (0: m0 as the run's reset evaluated it), evolution
(which of the N parallel evolutions), body (its canonical name, `Space.canonical`: equal for
equal shapes), fitness, fitness_std (over the K controllers, or the evaluation episodes),
diverged, parent (the canonical name of the body it was mutated from; NULL at step 0), distance
and upright (the gait of its evaluation episodes, `FitnessResult`; NULL where none ran). With
controller inheritance a body's fitness depends on its lineage, so this is a log, not a cache:
the same body appears once per evaluation. Table `shapes` keeps each body once (body, morphology
as `Space.to_json`), so that a body of the log can be evaluated again (`run`'s confirm stage).

The log proves itself: `BodyLog.proof` is the count of its evaluations and the SHA-256 of their
rows in the order they were added (step, then evolution), which every checkpoint records; a
--resume recomputes it from the file up to the checkpoint's step (`proof`) and refuses a log
that was changed, damaged or replaced.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import sqlite3
from pathlib import Path

import numpy as np

from evojax_morph.morphology import Morphology
from evojax_morph.records.checkpoints import Damaged
from evojax_morph.spaces import Space

SCHEMA = """CREATE TABLE IF NOT EXISTS bodies (
  step INTEGER NOT NULL, evolution INTEGER NOT NULL, body TEXT NOT NULL, fitness REAL NOT NULL,
  fitness_std REAL NOT NULL, diverged INTEGER NOT NULL, parent TEXT, distance REAL, upright REAL
);
CREATE TABLE IF NOT EXISTS shapes (body TEXT PRIMARY KEY, morphology TEXT NOT NULL)"""
COLUMNS = "step, evolution, body, fitness, fitness_std, diverged, parent, distance, upright"


def _digest(rows, found) -> int:
    """Updates the running SHA-256 `found` (hashlib's) with the log's `rows` (tuples of
    COLUMNS), each as a line of JSON (floats written exactly); returns how many there were."""
    count = 0
    for row in rows:
        found.update((json.dumps(list(row)) + "\n").encode())
        count += 1
    return count


def _read(db: sqlite3.Connection, step: int):
    """(rows, running SHA-256) of the log in `db` up to `step`, in the order they were added."""
    found = hashlib.sha256()
    return _digest(db.execute(f"SELECT {COLUMNS} FROM bodies WHERE step <= ? "
                              "ORDER BY step, evolution", (step,)), found), found


def proof(path: Path, step: int) -> dict:
    """{"rows", "sha256"} of the log in the file `path` up to `step` (`BodyLog.proof`), read
    without changing it, except that a write a kill cut short is rolled back (its hot journal,
    PATH-journal, which SQLite rolls back on any open that may write, and a read-only open
    fails on); a missing file holds no rows. Raises sqlite3's error where it does not read
    (damaged, cut short)."""
    if not Path(path).exists():
        return {"rows": 0, "sha256": hashlib.sha256().hexdigest()}
    journal = Path(f"{path}-journal").exists()
    db = sqlite3.connect(f"file:{path}?mode={'rw' if journal else 'ro'}", uri=True)
    try:
        rows, found = _read(db, step)
    finally:
        db.close()
    return {"rows": rows, "sha256": found.hexdigest()}


# SQLite's errors of a write the machine refused, as the OSError they are (`written`).
WRITE_ERRORS = {sqlite3.SQLITE_READONLY: errno.EROFS, sqlite3.SQLITE_FULL: errno.ENOSPC,
                sqlite3.SQLITE_IOERR: errno.EIO, sqlite3.SQLITE_CANTOPEN: errno.EACCES}


@contextlib.contextmanager
def written(path: Path):
    """SQLite's error of a write to `path` that the machine refused (a folder made read-only,
    a full disk, an I/O error) raised as an OSError naming `path`, as a failed write of any
    other run file is (`python -m evojax_morph.run` says it in one line, exit 1)."""
    try:
        yield
    except sqlite3.OperationalError as e:
        code = WRITE_ERRORS.get(getattr(e, "sqlite_errorcode", 0) & 0xFF)
        if code is None:
            raise
        raise OSError(code, str(e), str(path)) from e


class BodyLog:
    """The log of one run in the SQLite file `path` (created if missing); its writes fail as
    OSError (`written`)."""

    def __init__(self, path: Path, space: Space):
        self.space, self.path = space, Path(path)
        with written(self.path):
            self.db = sqlite3.connect(str(path))
            self.db.executescript(SCHEMA)
            self.db.execute("CREATE INDEX IF NOT EXISTS by_body ON bodies (body)")
            columns = {row[1] for row in self.db.execute("PRAGMA table_info(bodies)")}
            for gait in ("distance", "upright"):  # a log begun before the gait was kept
                if gait not in columns:
                    self.db.execute(f"ALTER TABLE bodies ADD COLUMN {gait} REAL")
            self.db.commit()
        self._names: dict[bytes, str] = {}
        self._rows, self._hash = 0, hashlib.sha256()  # what `proof` says

    def name(self, m: Morphology) -> str:
        """The canonical name of one host-side body, computed once per distinct array."""
        raw = b"".join(np.ascontiguousarray(x).tobytes() for x in
                       (m.active, m.parent, m.kind, m.site, m.attrs))
        if raw not in self._names:
            self._names[raw] = self.space.canonical(m)
            self.db.execute("INSERT OR IGNORE INTO shapes VALUES (?, ?)",
                            (self._names[raw], self.space.to_json(m)))
        return self._names[raw]

    def add(self, step: int, morphs: Morphology, fitness, fitness_std, diverged,
            parents: Morphology | None = None, distance=None, upright=None) -> None:
        """One step's evaluations: host-side (N, ...) bodies and (N,) results."""
        gait = lambda x, i: None if x is None or not np.isfinite(x[i]) else float(x[i])  # noqa: E731
        at = lambda tree, i: Morphology(*(np.asarray(x)[i] for x in (  # noqa: E731
            tree.active, tree.parent, tree.kind, tree.site, tree.attrs)))
        with written(self.path):
            rows = [
                (step, i, self.name(at(morphs, i)), float(fitness[i]), float(fitness_std[i]),
                 int(bool(diverged[i])), None if parents is None else self.name(at(parents, i)),
                 gait(distance, i), gait(upright, i))
                for i in range(len(fitness))
            ]
            self.db.executemany(
                f"INSERT INTO bodies ({COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", rows)
        self._rows += _digest(rows, self._hash)

    def proof(self) -> dict:
        """{"rows": the evaluations added, "sha256": of their rows in order}: what a checkpoint
        records and `proof` recomputes from the file."""
        return {"rows": self._rows, "sha256": self._hash.hexdigest()}

    def commit(self) -> None:
        with written(self.path):
            self.db.commit()

    def resume(self, step: int) -> None:
        """Forgets the steps after `step` (a resumed run redoes them; -1: every step) and goes
        on from the proof of those before."""
        with written(self.path):
            self.db.execute("DELETE FROM bodies WHERE step > ?", (step,))
            self.db.commit()
        self._rows, self._hash = _read(self.db, step)

    def close(self) -> None:
        self.db.close()


def ranked(mean, draws, first_step, name, n: int) -> list[int]:
    """The runs' rule for their best bodies, of the `run` command's log and of a study alike:
    the indices of the `n` best of some bodies by their mean fitness over their evaluations,
    a NaN mean last; ties go to the body evaluated more often, then to the one seen at the
    earlier step, then to the first by its canonical name (`morphology.canonical`).

    Args:
      mean, draws, first_step: (B,) per body: its mean fitness, its evaluations, the step of
        its first.
      name: name(i) -> body i's canonical name; asked only of bodies tied on all else.
    """
    mean = np.asarray(mean, np.float64)
    nan = np.isnan(mean)
    keys = np.stack([nan, -np.where(nan, 0.0, mean), -np.asarray(draws, np.float64),
                     np.asarray(first_step, np.float64)])
    order = np.lexsort(keys[::-1])  # lexsort sorts by its last key first
    found, i = [], 0
    while len(found) < n and i < len(order):
        j = i + 1
        while j < len(order) and (keys[:, order[j]] == keys[:, order[i]]).all():
            j += 1
        found += sorted(order[i:j].tolist(), key=name) if j > i + 1 else [int(order[i])]
        i = j
    return found[:n]


def best_bodies(path: Path, n: int = 10) -> list[dict]:
    """The `n` best distinct bodies of a log by `ranked`'s rule. Each with how often it was
    evaluated, its mean and best fitness, the step it was first seen, and its mean distance and
    upright (None where the fitness measures no gait).

    A body evaluated once ranks by that one draw, so a lucky draw can top this list: the mean
    of a few draws is still noisy, which `run`'s confirm stage settles with fresh evaluations.
    """
    db = sqlite3.connect(str(path))
    try:
        rows = db.execute(
            "SELECT body, COUNT(*), AVG(fitness), MAX(fitness), MIN(step), AVG(distance), "
            "AVG(upright) FROM bodies GROUP BY body"
        ).fetchall()
    finally:
        db.close()
    keys = ("body", "evaluations", "mean_fitness", "best_fitness", "first_step",
            "mean_distance", "mean_upright")
    if not rows:
        return []
    _, draws, mean, _, first_step, _, _ = zip(*rows)
    best = ranked(mean, draws, first_step, lambda i: rows[i][0], n)
    return [dict(zip(keys, rows[i])) for i in best]


def best_draw(path: Path) -> dict:
    """The highest single evaluation of a log (the earliest of equals): body, fitness, step."""
    db = sqlite3.connect(str(path))
    try:
        row = db.execute("SELECT body, fitness, step FROM bodies "
                         "ORDER BY fitness DESC, step, evolution LIMIT 1").fetchone()
    finally:
        db.close()
    return dict(zip(("body", "fitness", "step"), row))


def shapes(path: Path, space: Space, names: list[str]) -> dict[str, Morphology]:
    """The bodies of the log named `names`, as host-side morphologies; a name the log holds no
    shape of (a run begun before shapes were kept) is left out. Raises `checkpoints.Damaged`
    where a shape kept does not read or is another body's (its canonical name not its key): a
    run confirms no body its log did not evaluate."""
    db = sqlite3.connect(str(path))
    try:
        found = dict(db.execute(
            f"SELECT body, morphology FROM shapes WHERE body IN ({','.join('?' * len(names))})",
            names,
        ).fetchall())
    except sqlite3.OperationalError:  # no shapes table
        found = {}
    finally:
        db.close()
    kept = {}
    for name in (name for name in names if name in found):
        try:
            kept[name] = space.from_json(found[name])
            other = space.canonical(kept[name]) != name
        except Exception as e:
            raise Damaged(f"{path}: the shape of body {name} does not read "
                          f"({type(e).__name__}: {e})") from None
        if other:
            raise Damaged(f"{path}: the shape kept for body {name} is another body's")
    return kept
