"""The LO-RANSAC loop of our own solvers, and what every robust loop shares: the time budget,
MSAC scoring and the adaptive iteration count.

A problem (``LoRansacProblem``) draws batches of minimal-sample hypotheses, measures errors,
and locally optimises a model; the loop scores each batch on a fixed random subset of the data
(preemptive scoring bounds the cost), scores the batch's best on all data, and runs the local
optimisation whenever that beats the best model so far (PoseLib's LO-RANSAC, batched).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np

from services.estimators.options import RansacOptions
from services.types import BoolArray, FloatArray, IntArray

Model = TypeVar("Model")
Batch = TypeVar("Batch")


class DeadlinePassedError(Exception):
    """The deadline passed inside a long computation (``Deadline.check``), whose result would
    come too late: the request's answer is ``time_budget_exceeded``."""


class Deadline:
    """Wall-clock budget of one request (``EstimatorOptions.time_budget_s``; None = none)."""

    def __init__(self, budget_s: float | None) -> None:
        self._end = None if budget_s is None else time.perf_counter() + budget_s

    def expired(self) -> bool:
        return self._end is not None and time.perf_counter() > self._end

    def remaining_s(self) -> float:
        return float("inf") if self._end is None else self._end - time.perf_counter()

    def check(self) -> None:
        """Polled between the chunks of a long pass.

        Raises:
            DeadlinePassedError: the deadline has passed.
        """
        if self.expired():
            raise DeadlinePassedError


def required_iterations(inlier_ratio: float, sample_size: int, success_prob: float = 0.9999) -> int:
    """Iterations after which an all-inlier sample was drawn with ``success_prob``."""
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0 - 1e-12:
        return 1
    if p_good <= 1e-12:
        return 2**31
    return int(np.ceil(np.log(1.0 - success_prob) / np.log(1.0 - p_good)))


def searched_in_vain(stats: Mapping[str, float], options: RansacOptions) -> bool:
    """Whether the robust loop that wrote ``stats`` (its ``iterations``) drew every hypothesis
    ``options`` allow: no pose it found had enough agreeing data to stop it earlier (at the
    default cap, under 4.5 % of the points for local triangulation's 3-point samples). An image
    of nothing in the map ends there; a search cut short by the time budget does not count."""
    return stats.get("iterations", 0.0) >= options.max_iterations


def msac_score(errors: FloatArray, threshold: float) -> FloatArray:
    """Truncated squared error summed over the last axis ((..., N) → (...)); lower is better."""
    return np.asarray((np.minimum(errors, threshold) ** 2).sum(axis=-1), dtype=np.float64)


class LoRansacProblem(Protocol[Batch, Model]):
    """What the loop needs of a problem. Errors are in the threshold's unit.

    Attributes:
        num_data: N, the correspondences errors are measured on.
        sample_size: correspondences in a minimal sample (for the adaptive stopping).
        batch_size: hypotheses drawn per batch (counted as iterations).
        scoring_subset: batches are scored on at most this many correspondences.
    """

    num_data: int
    sample_size: int
    batch_size: int
    scoring_subset: int

    def hypotheses(self, rng: np.random.Generator) -> Batch | None:
        """A batch of minimal-sample models; None when the batch held no valid sample."""
        ...

    def batch_errors(self, batch: Batch, subset: IntArray) -> FloatArray:
        """(B, S) errors of the batch's models on the correspondences ``subset``."""
        ...

    def select(self, batch: Batch, k: int) -> Model:
        """The batch's ``k``-th model."""
        ...

    def errors(self, model: Model) -> FloatArray:
        """(N,) errors of one model on all correspondences."""
        ...

    def local_optimisation(self, model: Model, errors: FloatArray) -> tuple[Model, FloatArray]:
        """A model at least as good as ``model`` (whose errors are given), with its errors."""
        ...


@dataclass(frozen=True)
class RansacResult(Generic[Model]):
    """The best model (None when no batch gave one), its (N,) inliers (error below the
    threshold), and the iterations run."""

    model: Model | None
    inliers: BoolArray
    iterations: int


def lo_ransac(
    problem: LoRansacProblem[Batch, Model],
    threshold: float,
    options: RansacOptions,
    rng: np.random.Generator,
    deadline: Deadline,
) -> RansacResult[Model]:
    """Run LO-RANSAC until the adaptive iteration count (within the options' bounds) is
    reached or the deadline, checked before every batch, has passed; past the deadline a
    better model is kept without its local optimisation (on 100k matches it takes ~0.5 s).

    Raises:
        DeadlinePassedError: from the problem, whose passes over all data may poll the
            deadline (``Deadline.check``): a model found then would come too late.
    """
    n = problem.num_data
    subset = (
        np.arange(n)
        if n <= problem.scoring_subset
        else rng.choice(n, problem.scoring_subset, replace=False)
    )
    best: Model | None = None
    best_errors = np.zeros(0)
    best_score = np.inf
    iterations = 0
    needed = options.min_iterations
    while iterations < min(max(needed, options.min_iterations), options.max_iterations):
        if deadline.expired():
            break
        iterations += problem.batch_size
        batch = problem.hypotheses(rng)
        if batch is None:
            continue
        k = int(np.argmin(msac_score(problem.batch_errors(batch, subset), threshold)))
        candidate = problem.select(batch, k)
        errors = problem.errors(candidate)
        if float(msac_score(errors, threshold)) < best_score:
            best, best_errors = (
                (candidate, errors)
                if deadline.expired()
                else problem.local_optimisation(candidate, errors)
            )
            best_score = float(msac_score(best_errors, threshold))
            needed = required_iterations(
                float((best_errors < threshold).mean()), problem.sample_size, options.success_prob
            )
    return RansacResult(best, best_errors < threshold, iterations)
