"""SIFT's default budget went from 2048 to 4096 keypoints: maps whose references SIFT
described at the old default keep it as their own option, so that they go on serving their
stored features (SIFT at another budget describes queries under another name).

A map whose references SIFT described at 2048 keypoints, with no budget of its own, gets
``max_keypoints`` 2048. A ``PATCH /v1/maps/{id}`` with another budget describes them anew from
their originals.

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-30
"""

import sqlalchemy as sa
from alembic import op

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None

OLD_BUDGET = 2048


def upgrade() -> None:
    op.execute(
        sa.text(
            "UPDATE maps SET max_keypoints = :budget WHERE max_keypoints IS NULL AND EXISTS "
            "(SELECT 1 FROM reference_images r WHERE r.map_id = maps.id "
            "AND r.feature_model LIKE :described)"
        ).bindparams(budget=OLD_BUDGET, described=f"sift-rootsift-{OLD_BUDGET}-%")
    )


def downgrade() -> None:
    # the pinned budget is the old default: a downgraded server describes as before
    pass
