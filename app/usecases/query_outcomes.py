"""Where a map's queries fail: each single-frame query is counted against the reference it
resembled most (its best retrieved one), as localized or failed. The counts gather in memory
and reach the database every ``FLUSH_S`` seconds and at shutdown, so that no localize request
writes to the database; a crash loses at most the last ``FLUSH_S`` seconds of counts. The
map's coverage reads them (``app/usecases/coverage.py``)."""

from __future__ import annotations

import logging
import threading

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from db.repositories.images import ImageRepository
from services.estimators.base import FailureReason
from services.localization.answer import LocalizationResult

logger = logging.getLogger(__name__)

FLUSH_S = 10.0
# references with counts not yet written; past it a new reference's counts are dropped (a
# bounded memory whatever the database does)
MAX_PENDING = 100_000
# answers that say nothing about the place
NOT_COUNTED = frozenset({FailureReason.TIME_BUDGET_EXCEEDED.value})


class QueryOutcomes:
    """The counts not yet written, and the thread that writes them."""

    def __init__(self, sessions: sessionmaker[Session], flush_s: float = FLUSH_S) -> None:
        self.sessions = sessions
        self.flush_s = flush_s
        self.dropped = 0  # queries not counted: too many references waiting
        self._pending: dict[str, list[int]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="query outcomes", daemon=True)
        self._thread.start()

    def record(self, result: LocalizationResult) -> None:
        """Counts a single-frame answer against its best retrieved reference (none: not
        counted)."""
        if not result.retrieved or result.reason in NOT_COUNTED:
            return
        best = max(result.retrieved, key=lambda r: r.score).image_id
        with self._lock:
            counts = self._pending.get(best)
            if counts is None:
                if len(self._pending) >= MAX_PENDING:
                    self.dropped += 1
                    return
                counts = self._pending[best] = [0, 0]
            counts[0 if result.localized else 1] += 1

    def flush(self) -> None:
        """Writes the counts gathered; kept for the next flush when the database fails."""
        with self._lock:
            pending, self._pending = self._pending, {}
        if not pending:
            return
        try:
            with self.sessions.begin() as session:
                ImageRepository(session).add_query_outcomes(
                    {image_id: (ok, failed) for image_id, (ok, failed) in pending.items()}
                )
        except SQLAlchemyError as exc:
            logger.warning("query outcomes not written (kept for the next try): %s", exc)
            with self._lock:
                for image_id, (ok, failed) in pending.items():
                    if image_id in self._pending or len(self._pending) < MAX_PENDING:
                        counts = self._pending.setdefault(image_id, [0, 0])
                        counts[0] += ok
                        counts[1] += failed

    def _run(self) -> None:
        while not self._stop.wait(self.flush_s):
            self.flush()

    def shutdown(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.flush()
