"""Grid points claimed atomically in the study's database, so that workers sharing a study never run a point twice.

Several workers (one per workspace, on one machine or many) share one Optuna study through its RDB storage: SQLite on
one machine, PostgreSQL across machines. Optuna's samplers cannot keep them apart: they pick a trial's params after the
trial exists, from the trials they can see, so two workers sampling at the same moment can both pick the same untried
point (brute force), or skip one (the grid sampler). Here a worker first claims a point, and only then creates the
trial that runs it.

A claim is a row of the table ``carp_sweep_claims``:

- ``(study_id, point)`` is its primary key, so a point is claimed at most once;
- ``(study_id, slot)`` is unique, and a new claim takes a free slot in ``0 .. num_trials - 1``, so at most
  ``num_trials`` points are ever claimed, however many workers there are: the budget holds across workers.

Why this is atomic: a claim is one ``INSERT`` in its own transaction, and the database enforces both unique indexes
when the row is written, whatever the transaction isolation. PostgreSQL makes a second insert of the same key wait
until the first transaction ends and then rejects it with a unique violation; SQLite lets one writer at a time in.
The loser gets ``IntegrityError``, reads the table again and tries the next free point and slot. A scheme that reads
"unclaimed" and then writes (under PostgreSQL's default READ COMMITTED, or in two separate transactions) leaves a window
in which both workers read the same point as free; an insert checked by a unique index has no such window and needs no
row lock.

A claim follows its point through retries: the worker that takes up a retried trial (one that Optuna's heartbeat
callback queued after its worker died, or that an interrupted worker queued on its way out) moves the claim from the
failed trial to the retry. Only one worker can take up a queued trial (Optuna moves it from WAITING to RUNNING under a
row lock), so only one moves the claim.

A worker killed between claiming and creating the trial leaves a claim without a trial. Once that claim is older than
the heartbeat grace period, another worker may take it over: the takeover is an ``UPDATE`` that sets a new random
``owner`` token only where the token is still the one it read (compare and swap); PostgreSQL re-checks that condition
after waiting for a concurrent update of the same row, and SQLite serializes writers, so one worker wins. The slow
original owner then fails to attach its trial (:meth:`ClaimStore.assign` checks the token) and must not run it.

The table ``carp_sweep_values`` keeps a few per-study values that the first writer decides (the MLflow parent run).
"""

import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

import sqlalchemy
from sqlalchemy import Column, DateTime, Integer, MetaData, String, Table, UniqueConstraint, func, select
from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError

# Optuna keeps study names and attribute keys in columns of this length; points and values are short.
MAX_KEY_LENGTH = 512
# Concurrent workers conflict at most once per other worker per attempt; this only bounds a pathological loop.
MAX_ATTEMPTS = 1000

_metadata = MetaData()
CLAIMS = Table(
    "carp_sweep_claims",
    _metadata,
    Column("study_id", Integer, primary_key=True),
    Column("point", String(MAX_KEY_LENGTH), primary_key=True),
    Column("slot", Integer, nullable=False),
    Column("trial_number", Integer, nullable=True),
    Column("owner", String(64), nullable=False),
    Column("claimed_at", DateTime(timezone=True), nullable=False),
    UniqueConstraint("study_id", "slot", name="carp_sweep_claims_slot"),
)
VALUES = Table(
    "carp_sweep_values",
    _metadata,
    Column("study_id", Integer, primary_key=True),
    Column("key", String(MAX_KEY_LENGTH), primary_key=True),
    Column("value", String(MAX_KEY_LENGTH), nullable=False),
)


@dataclass(frozen=True)
class Claim:
    """One claimed grid point.

    Attributes:
        point: the point's key (see :func:`carp.sweep.space.point_key`).
        slot: its budget slot; new claims take slots below ``num_trials``.
        trial_number: the Optuna trial that runs (or ran) it; ``None`` between claiming and creating that trial.
        owner: random token of the worker that claimed it last.
        age_seconds: time since it was claimed or taken over, by the database's clock.
    """

    point: str
    slot: int
    trial_number: int | None
    owner: str
    age_seconds: float


class ClaimLostError(RuntimeError):
    """Another worker took over this worker's claim before its trial was attached (see the module docstring)."""


class ClaimStore:
    """The claims of one study, in the database of its Optuna storage.

    Args:
        url: the study's storage URL (``sqlite:////abs/optuna.db``, ``postgresql://user@host:port/db``).
        study_id: Optuna's id of the study (``storage.get_study_id_from_name``); a study deleted and created again
            under the same name gets a new id and starts without claims.
    """

    def __init__(self, url: str, study_id: int) -> None:
        self.engine = sqlalchemy.create_engine(url, pool_pre_ping=True)
        self.study_id = study_id
        self.owner = secrets.token_hex(16)
        self._create_tables()

    def close(self) -> None:
        """Release the database connections."""
        self.engine.dispose()

    def claims(self) -> list[Claim]:
        """Every claim of the study, by slot."""
        with self.engine.connect() as connection:
            now = connection.execute(select(func.now())).scalar_one()
            rows = connection.execute(
                select(CLAIMS).where(CLAIMS.c.study_id == self.study_id).order_by(CLAIMS.c.slot)
            ).all()
        return [
            Claim(row.point, row.slot, row.trial_number, row.owner, _seconds_between(now, row.claimed_at))
            for row in rows
        ]

    def claim(self, points: Sequence[str], num_slots: int, stale_seconds: float) -> str | None:
        """Claim the first point of ``points`` that is free, or whose claim was left without a trial.

        Args:
            points: candidate points in the order they should run.
            num_slots: the trial budget; a new claim needs a free slot below it.
            stale_seconds: a claim without a trial that is older than this may be taken over.

        Returns:
            The claimed point, owned by this store's token, with no trial yet (:meth:`assign` attaches one); ``None``
            when every point is claimed or the budget is spent.
        """
        for _ in range(MAX_ATTEMPTS):
            claims = {claim.point: claim for claim in self.claims()}
            free_slots = sorted(set(range(num_slots)) - {claim.slot for claim in claims.values()})
            candidates = [
                point
                for point in points
                if (point not in claims and free_slots)
                or (
                    point in claims and claims[point].trial_number is None and claims[point].age_seconds > stale_seconds
                )
            ]
            if not candidates:
                return None
            point = candidates[0]
            if point in claims:
                if self._take_over(claims[point]):
                    return point
            elif self._insert(point, free_slots[0], trial_number=None):
                return point
        raise RuntimeError(f"no claim settled after {MAX_ATTEMPTS} attempts")

    def assign(self, point: str, trial_number: int) -> None:
        """Attach the trial created for a point this store claimed.

        Raises:
            ClaimLostError: another worker took the claim over in the meantime; the trial must not run.
        """
        with self.engine.begin() as connection:
            updated = connection.execute(
                CLAIMS.update()
                .where(CLAIMS.c.study_id == self.study_id, CLAIMS.c.point == point, CLAIMS.c.owner == self.owner)
                .values(trial_number=trial_number)
            ).rowcount
        if updated != 1:
            raise ClaimLostError(f"the claim of {point} was taken over by another worker before trial {trial_number}")

    def transfer(self, failed_trial: int, retry_trial: int) -> str | None:
        """Move the claim of a failed trial to the trial that retries it; returns its point, ``None`` if unclaimed."""
        with self.engine.begin() as connection:
            connection.execute(
                CLAIMS.update()
                .where(CLAIMS.c.study_id == self.study_id, CLAIMS.c.trial_number == failed_trial)
                .values(trial_number=retry_trial, owner=self.owner)
            )
            return connection.execute(
                select(CLAIMS.c.point).where(CLAIMS.c.study_id == self.study_id, CLAIMS.c.trial_number == retry_trial)
            ).scalar_one_or_none()

    def record(self, point: str, trial_number: int) -> None:
        """Claim ``point`` for a trial that already runs or ran it, whatever the budget (trials made before claims).

        Nothing changes when the point is claimed already. The slot is the lowest free one, possibly beyond the
        budget: the trial happened, and it counts.
        """
        for _ in range(MAX_ATTEMPTS):
            claims = self.claims()
            if any(claim.point == point for claim in claims):
                return
            used = {claim.slot for claim in claims}
            slot = next(index for index in range(len(used) + 1) if index not in used)
            if self._insert(point, slot, trial_number):
                return
        raise RuntimeError(f"no claim settled after {MAX_ATTEMPTS} attempts")

    def get(self, key: str) -> str | None:
        """The value stored under ``key``, ``None`` when there is none."""
        with self.engine.connect() as connection:
            return connection.execute(
                select(VALUES.c.value).where(VALUES.c.study_id == self.study_id, VALUES.c.key == key)
            ).scalar_one_or_none()

    def setdefault(self, key: str, value: str) -> str:
        """Store ``value`` under ``key`` unless one is stored already; returns the stored one (first writer wins)."""
        try:
            with self.engine.begin() as connection:
                connection.execute(VALUES.insert().values(study_id=self.study_id, key=key, value=value))
        except IntegrityError:
            pass  # stored by another worker first
        stored = self.get(key)
        assert stored is not None
        return stored

    def _insert(self, point: str, slot: int, trial_number: int | None) -> bool:
        try:
            with self.engine.begin() as connection:
                connection.execute(
                    CLAIMS.insert().values(
                        study_id=self.study_id,
                        point=point,
                        slot=slot,
                        trial_number=trial_number,
                        owner=self.owner,
                        claimed_at=func.now(),
                    )
                )
        except IntegrityError:
            return False  # another worker claimed this point or this slot first
        return True

    def _take_over(self, claim: Claim) -> bool:
        with self.engine.begin() as connection:
            updated = connection.execute(
                CLAIMS.update()
                .where(
                    CLAIMS.c.study_id == self.study_id,
                    CLAIMS.c.point == claim.point,
                    CLAIMS.c.owner == claim.owner,
                    CLAIMS.c.trial_number.is_(None),
                )
                .values(owner=self.owner, claimed_at=func.now())
            ).rowcount
        return updated == 1

    def _create_tables(self) -> None:
        # Workers starting together may both try to create the tables; PostgreSQL then rejects the second CREATE
        # (a duplicate in its catalog) even though both checked first. The tables exist either way.
        try:
            _metadata.create_all(self.engine)
        except (IntegrityError, ProgrammingError, OperationalError):
            _metadata.create_all(self.engine)


def _seconds_between(later: datetime, earlier: datetime) -> float:
    # PostgreSQL returns timezone-aware times, SQLite naive ones (both UTC there); never a mix from one database.
    if (later.tzinfo is None) != (earlier.tzinfo is None):
        later, earlier = later.replace(tzinfo=None), earlier.replace(tzinfo=None)
    return (later - earlier).total_seconds()
