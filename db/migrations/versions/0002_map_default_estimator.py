"""Per-map default estimator.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(
            sa.Column("default_estimator", sa.String(64), nullable=False, server_default="e5p1")
        )


def downgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("default_estimator")
