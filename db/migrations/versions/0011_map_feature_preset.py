"""Maps choose their feature configuration.

The one their references are described with (null: the server's, ``SLLOC_FEATURES``), the one
they are being re-described with, and whether the map follows its self-evaluation's
recommendation (``features: auto``). Maps made before keep the server's configuration and do
not follow.

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-26
"""

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None

MAP_COLUMNS = (
    ("feature_preset", sa.String(64), None),
    ("pending_preset", sa.String(64), None),
    ("features_auto", sa.Boolean(), sa.false()),
)


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends (no table rebuild: see 0009)
    for name, type_, default in MAP_COLUMNS:
        op.add_column(
            "maps",
            sa.Column(name, type_, nullable=default is None, server_default=default),
        )


def downgrade() -> None:
    sqlite = op.get_bind().dialect.name == "sqlite"
    for name, _, _ in reversed(MAP_COLUMNS):
        if sqlite:
            op.execute(f"ALTER TABLE maps DROP COLUMN {name}")
        else:
            op.drop_column("maps", name)
