"""Maps re-describe their references from the originals: the feature options a map moves to
while its references are re-described (null: none pending), and each reference's staged
description (the extractor that made its ``next:`` arrays).

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-26
"""

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

MAP_COLUMNS = (
    ("reextracting", sa.Boolean(), sa.false()),
    ("pending_max_keypoints", sa.Integer(), None),
    ("pending_max_side", sa.Integer(), None),
)


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends: no table rebuild (on SQLite a rebuild
    # drops the old table, which cascades to the references' feature arrays)
    for name, type_, default in MAP_COLUMNS:
        op.add_column(
            "maps",
            sa.Column(name, type_, nullable=default is None, server_default=default),
        )
    op.add_column("reference_images", sa.Column("next_feature_model", sa.String(128)))


def downgrade() -> None:
    sqlite = op.get_bind().dialect.name == "sqlite"  # SQLite >= 3.35 drops in place
    columns = [("reference_images", "next_feature_model")]
    columns += [("maps", name) for name, _, _ in reversed(MAP_COLUMNS)]
    for table, name in columns:
        if sqlite:
            op.execute(f"ALTER TABLE {table} DROP COLUMN {name}")
        else:
            op.drop_column(table, name)
