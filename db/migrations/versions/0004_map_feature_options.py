"""Per-map feature options: keypoint budget and longer image side.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22
"""

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(sa.Column("max_keypoints", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("max_side", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("max_side")
        batch.drop_column("max_keypoints")
