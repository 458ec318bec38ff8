"""VLAD retrieval: a versioned vocabulary per (map, feature model), and the vocabulary
version each reference image's VLAD vector was encoded with.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-23
"""

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "map_vocabularies",
        sa.Column(
            "map_id", sa.String(36), sa.ForeignKey("maps.id", ondelete="CASCADE"), nullable=False
        ),
        sa.Column("feature_model", sa.String(128), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("trained_images", sa.Integer(), nullable=False),
        sa.Column("shape", sa.JSON(), nullable=False),
        sa.Column("centers", sa.LargeBinary(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("map_id", "feature_model"),
    )
    with op.batch_alter_table("reference_images") as batch:
        batch.add_column(sa.Column("vlad_version", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("reference_images") as batch:
        batch.drop_column("vlad_version")
    op.drop_table("map_vocabularies")
