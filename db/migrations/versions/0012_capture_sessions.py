"""Capture sessions that extend maps, their frames waiting to be added, the stale flag their
frames set on references that no longer match (and maps that retire those at once), and maps
that grow from their queries.

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-26
"""

import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

# a frame's cam_from_session: quaternion [w, x, y, z] and translation
POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx", "ty", "tz")


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends (no table rebuild: see 0009)
    op.add_column("reference_images", sa.Column("stale_since", sa.DateTime(timezone=True)))
    op.add_column("reference_images", sa.Column("stale_reason", sa.Text()))
    for name in ("grow_from_queries", "retire_stale"):
        op.add_column(
            "maps", sa.Column(name, sa.Boolean(), nullable=False, server_default=sa.false())
        )
    op.create_table(
        "capture_sessions",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column(
            "map_id",
            sa.String(36),
            sa.ForeignKey("maps.id", ondelete="CASCADE"),
            nullable=False,
            index=True,
        ),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("metric", sa.Boolean(), nullable=False),
        sa.Column("keep_all", sa.Boolean(), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("frame_count", sa.Integer(), nullable=False),
        sa.Column("done", sa.Integer(), nullable=False),
        sa.Column("total", sa.Integer(), nullable=False),
        sa.Column("result", sa.JSON()),
        sa.Column("error", sa.Text()),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True)),
        sa.Column("finished_at", sa.DateTime(timezone=True)),
        sa.UniqueConstraint("map_id", "name", name="uq_capture_sessions_map_id_name"),
    )
    op.create_table(
        "capture_frames",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column(
            "session_id",
            sa.String(36),
            sa.ForeignKey("capture_sessions.id", ondelete="CASCADE"),
            nullable=False,
            index=True,
        ),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("camera_model", sa.String(32), nullable=False),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("camera_params", sa.JSON(), nullable=False),
        *(
            sa.Column(c, sa.Float(), nullable=False)
            for c in ("qw", "qx", "qy", "qz", "tx", "ty", "tz")
        ),
        sa.Column("original_key", sa.String(255), nullable=False),
        sa.Column("original_sha256", sa.String(64), nullable=False),
        sa.Column("depth_key", sa.String(255)),
        sa.Column("placed", sa.JSON()),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("session_id", "name", name="uq_capture_frames_session_name"),
    )


def downgrade() -> None:
    op.drop_table("capture_frames")
    op.drop_table("capture_sessions")
    sqlite = op.get_bind().dialect.name == "sqlite"
    for table, name in (
        ("maps", "retire_stale"),
        ("maps", "grow_from_queries"),
        ("reference_images", "stale_reason"),
        ("reference_images", "stale_since"),
    ):
        if sqlite:
            op.execute(f"ALTER TABLE {table} DROP COLUMN {name}")
        else:
            op.drop_column(table, name)
