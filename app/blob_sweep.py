"""The start-up reconciliation of the blob store with the database, in the background."""

from __future__ import annotations

import logging
import threading

from sqlalchemy.orm import Session, sessionmaker

from db.blobs import BlobStore
from db.originals import SweepReport, reconcile

logger = logging.getLogger(__name__)


class StartupSweep:
    """Runs :func:`db.originals.reconcile` once on a daemon thread: blobs without a row,
    last written more than ``grace_s`` seconds ago, are removed; rows whose blob is missing
    are logged. ``report`` holds the outcome once done (None before, or after a failure)."""

    def __init__(self, sessions: sessionmaker[Session], blobs: BlobStore, grace_s: float) -> None:
        self.report: SweepReport | None = None
        self.error: str | None = None
        self._thread = threading.Thread(
            target=self._run, args=(sessions, blobs, grace_s), name="blob-sweep", daemon=True
        )
        self._thread.start()

    def _run(self, sessions: sessionmaker[Session], blobs: BlobStore, grace_s: float) -> None:
        try:
            report = reconcile(sessions, blobs, grace_s)
        except Exception as exc:  # a store or database out of reach: the next start retries
            self.error = str(exc)
            logger.warning("blob sweep of %s failed: %s", blobs.description, exc)
            return
        self.report = report
        log = logger.error if report.missing else logger.info
        log("blob sweep: %s", report.summary())

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait for the sweep; whether it is done."""
        self._thread.join(timeout_s)
        return not self._thread.is_alive()
