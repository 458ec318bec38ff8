"""The clock and budget of one localization: stage timings, and the time budget checked
between the stages."""

from __future__ import annotations

import time
from dataclasses import replace

from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline

STAGES = ("decode", "extract", "retrieve", "match", "estimate")


class OutOfTimeError(Exception):
    """The localization's time budget ran out between stages."""


class StageClock:
    """Times the stages (milliseconds) and enforces the time budget between them."""

    def __init__(self, budget_s: float | None) -> None:
        self.deadline = Deadline(budget_s)
        self._budgeted = budget_s is not None
        self._left_at_lap = budget_s
        self._timings: dict[str, float] = {}
        self._start = self._lap_start = time.perf_counter()

    def lap(self, stage: str, check: bool = True) -> None:
        """Records ``stage`` as ended now (a stage run again adds up).

        Raises:
            OutOfTimeError: ``check`` and the budget is spent.
        """
        now = time.perf_counter()
        self._timings[stage] = self._timings.get(stage, 0.0) + (now - self._lap_start) * 1000.0
        self._lap_start = now
        self._left_at_lap = self.deadline.remaining_s() if self._budgeted else None
        if check and self.deadline.expired():
            raise OutOfTimeError

    def branch(self) -> StageClock:
        """A clock that goes on from now as this one would, with the stages timed so far and
        what is left of the budget, as though the time since the last lap had not passed."""
        now = time.perf_counter()
        clone = StageClock(None)
        clone.deadline = Deadline(self._left_at_lap)
        clone._timings = dict(self._timings)
        clone._start = now - (self._lap_start - self._start)
        clone._lap_start = now
        return clone

    def bound(self, options: EstimatorOptions) -> EstimatorOptions:
        """``options`` with an estimator budget no longer than what is left of this one."""
        left = self.deadline.remaining_s()
        if left == float("inf"):
            return options
        own = options.time_budget_s
        return replace(options, time_budget_s=max(0.0, left if own is None else min(own, left)))

    def finish(self) -> dict[str, float]:
        """The stage timings (0 for the stages not reached) and their ``total``."""
        timings = {stage: self._timings.get(stage, 0.0) for stage in STAGES}
        timings["total"] = (time.perf_counter() - self._start) * 1000.0
        return timings
