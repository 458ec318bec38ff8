"""Maps with ``features: auto`` take the feature configuration their self-evaluation
recommends (``services/self_evaluation/summary.recommend``), and are evaluated again on their
own when they have changed enough.

The rule: a map is evaluated once it has ``min_references`` references with their originals,
then again after adds and deletes numbering at least ``MIN_CHANGES`` or ``CHANGE_FRACTION`` of
the references it had when last evaluated, whichever is more; when those changes left its
size within ``CHANGE_FRACTION`` of what it was (references replaced rather than added), not
before ``CHURN_INTERVAL_S`` since its last evaluation started. Until its first evaluation a map
is served with the server's configuration (``SLLOC_FEATURES``). When an evaluation recommends
another configuration, the map's references are described anew with it from their originals
(``app/usecases/reextraction``), and the map switches once they all are.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import ConflictError, NotFoundError
from app.usecases.maps import FeatureChoice
from app.usecases.reextraction import Reextractor, change_feature_options
from db.models import Map
from db.repositories.evaluations import ACTIVE, EvaluationRepository
from services.components import Localizers
from services.errors import InvalidInputError

logger = logging.getLogger(__name__)

# a map is evaluated again after this many adds and deletes, or this fraction of the
# references it had at its last evaluation, whichever is more
MIN_CHANGES = 10
CHANGE_FRACTION = 0.25
# a map whose references are replaced rather than added is evaluated at most this often (s)
CHURN_INTERVAL_S = 600.0


@dataclass
class AutoEvaluation:
    """When maps that take their configuration from their self-evaluation are evaluated, and
    what follows a finished evaluation.

    Attributes:
        min_references: references with originals before a map is first evaluated on its
            own (``SLLOC_AUTO_EVALUATION_REFERENCES``; 0: never on its own).
    """

    sessions: sessionmaker[Session]
    localizers: Localizers
    reextractor: Reextractor | None
    min_references: int

    def wanted(self, session: Session, map_row: Map) -> bool:
        """Whether the map is due an evaluation of its own: it follows its evaluation, is
        neither re-describing its references nor being evaluated, has enough references,
        and has changed enough since its last evaluation (of any outcome)."""
        if not map_row.features_auto or self.min_references <= 0 or map_row.reextracting:
            return False
        repository = EvaluationRepository(session)
        count = repository.reference_count(map_row.id)
        if count < self.min_references:
            return False
        last = repository.latest(map_row.id)
        if last is None:
            return True
        if last.state in ACTIVE:
            return False
        then = last.request.get("revision")
        evaluated = (last.result or {}).get("references", 0)
        if not isinstance(then, int) or not isinstance(evaluated, int):
            return True
        if map_row.revision - then < max(MIN_CHANGES, CHANGE_FRACTION * evaluated):
            return False
        if abs(count - evaluated) >= CHANGE_FRACTION * evaluated:
            return True  # grown or shrunk
        return (datetime.now(UTC) - last.created_at).total_seconds() >= CHURN_INTERVAL_S

    def finished(self, map_id: str, recommended: str | None) -> None:
        """A map's evaluation finished: a map that follows it takes the configuration it
        recommends, its references described anew in the background (at the
        configuration's default options)."""
        if recommended is None:
            return
        with self.sessions() as session:
            row = session.get(Map, map_id)
            if row is None or not row.features_auto:
                return
            current = row.feature_preset or self.localizers.features
        if recommended == current:
            return
        try:
            change_feature_options(
                self.sessions,
                self.localizers,
                map_id,
                FeatureChoice(recommended, None, None),
                self.reextractor,
            )
        except (NotFoundError, ConflictError, InvalidInputError) as exc:
            logger.warning("map %s: %s recommended but not taken: %s", map_id, recommended, exc)
            return
        logger.info("map %s: takes %s, its self-evaluation's recommendation", map_id, recommended)
