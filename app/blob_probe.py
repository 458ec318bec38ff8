"""Whether the blob store takes writes: one probe, cached a while and bounded in time, shared
by ``/v1/health``, ``/readyz`` and ``/metrics``."""

from __future__ import annotations

import logging
import time

from anyio import move_on_after, to_thread
from starlette.datastructures import State

from db.blobs import BlobStore, BlobStoreError

logger = logging.getLogger(__name__)

# how long a probe's answer is reused, and how long it may take before the store counts as
# unavailable
BLOB_PROBE_TTL_S = 15.0
BLOB_PROBE_TIMEOUT_S = 2.0


def blob_probe_ready(state: State) -> bool:
    """Whether the app's lifespan has set up the store and its probe's limiter."""
    return getattr(state, "blob_probe_threads", None) is not None


async def blob_store_ok(state: State) -> bool:
    """Whether the blob store takes writes, probed at most every BLOB_PROBE_TTL_S seconds and
    for at most BLOB_PROBE_TIMEOUT_S (no answer by then: unavailable), on the app's probe
    limiter (a store that hangs holds one thread). The answer is kept in ``state.blob_probe``
    as (monotonic time, ok); a change is logged, with the reason."""
    cached: tuple[float, bool] | None = getattr(state, "blob_probe", None)
    now = time.monotonic()
    if cached is not None and now - cached[0] < BLOB_PROBE_TTL_S:
        return cached[1]
    problem: str | None = f"no answer within {BLOB_PROBE_TIMEOUT_S:g} s"
    with move_on_after(BLOB_PROBE_TIMEOUT_S):
        problem = await to_thread.run_sync(
            _problem, state.blobs, limiter=state.blob_probe_threads, abandon_on_cancel=True
        )
    ok = problem is None
    if cached is None or cached[1] != ok:
        if ok:
            logger.info("blob store: takes writes")
        else:
            logger.warning("blob store: unavailable, adds answer 503: %s", problem)
    state.blob_probe = (now, ok)
    return ok


def _problem(blobs: BlobStore) -> str | None:
    try:
        blobs.check()
    except BlobStoreError as exc:
        return str(exc)
    return None
