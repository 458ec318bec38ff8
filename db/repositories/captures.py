"""Queries on capture sessions and their frames."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from db.models import CaptureFrame, CaptureSession, is_stored_id
from db.originals import StoredOriginals
from services.geo.gps import GpsFix
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d

# a session in one of these states has frames to align or add
ACTIVE = ("queued", "aligning", "adding")
# one in these is over: its frames were added or removed
FINISHED = ("added", "refused", "failed")


class CaptureRepository:
    def __init__(self, session: Session) -> None:
        self.session = session

    def create(self, map_id: str, name: str, metric: bool, keep_all: bool) -> CaptureSession:
        row = CaptureSession(
            map_id=map_id,
            name=name,
            metric=metric,
            keep_all=keep_all,
            state="open",
            frame_count=0,
            done=0,
            total=0,
        )
        self.session.add(row)
        self.session.flush()
        return row

    def get(self, map_id: str, session_id: str) -> CaptureSession | None:
        if not is_stored_id(session_id):
            return None
        row = self.session.get(CaptureSession, session_id)
        return row if row is not None and row.map_id == map_id else None

    def lock(self, session_id: str) -> CaptureSession | None:
        """The session's row, locked until the transaction ends (PostgreSQL; SQLite
        serialises writers anyway)."""
        return self.session.scalar(
            select(CaptureSession).where(CaptureSession.id == session_id).with_for_update()
        )

    def name_exists(self, map_id: str, name: str) -> bool:
        return (
            self.session.scalar(
                select(CaptureSession.id).where(
                    CaptureSession.map_id == map_id, CaptureSession.name == name
                )
            )
            is not None
        )

    def page(self, map_id: str, offset: int, limit: int) -> tuple[list[CaptureSession], int]:
        """The map's sessions, newest first, and how many it has."""
        rows = self.session.scalars(
            select(CaptureSession)
            .where(CaptureSession.map_id == map_id)
            .order_by(CaptureSession.created_at.desc(), CaptureSession.id)
            .offset(offset)
            .limit(limit)
        )
        total = self.session.scalar(
            select(func.count()).select_from(CaptureSession).where(CaptureSession.map_id == map_id)
        )
        return list(rows), int(total or 0)

    def unfinished(self) -> list[str]:
        """Ids of the sessions a restart interrupted (queued, aligning or adding), oldest
        first."""
        return list(
            self.session.scalars(
                select(CaptureSession.id)
                .where(CaptureSession.state.in_(ACTIVE))
                .order_by(CaptureSession.created_at)
            )
        )

    def add_frame(
        self,
        session_row: CaptureSession,
        frame_id: str,
        name: str,
        camera: Camera,
        cam_from_session: Rigid3d,
        originals: StoredOriginals,
        gps: GpsFix | None = None,
    ) -> CaptureFrame:
        qw, qx, qy, qz = (float(v) for v in cam_from_session.quaternion)
        tx, ty, tz = (float(v) for v in cam_from_session.translation)
        row = CaptureFrame(
            id=frame_id,
            session_id=session_row.id,
            position=session_row.frame_count,
            name=name,
            camera_model=camera.model,
            width=camera.width,
            height=camera.height,
            camera_params=[float(p) for p in camera.params],
            qw=qw,
            qx=qx,
            qy=qy,
            qz=qz,
            tx=tx,
            ty=ty,
            tz=tz,
            original_key=originals.original_key,
            original_sha256=originals.original_sha256,
            depth_key=originals.depth_key,
            gps_latitude=gps.latitude if gps else None,
            gps_longitude=gps.longitude if gps else None,
            gps_height=gps.height if gps else None,
            gps_accuracy_m=gps.accuracy_m if gps else None,
        )
        self.session.add(row)
        session_row.frame_count += 1
        self.session.flush()
        return row

    def frame_name_exists(self, session_id: str, name: str) -> bool:
        return (
            self.session.scalar(
                select(CaptureFrame.id).where(
                    CaptureFrame.session_id == session_id, CaptureFrame.name == name
                )
            )
            is not None
        )

    def frames(self, session_id: str) -> list[CaptureFrame]:
        """The session's frames not added yet, in capture order."""
        return list(
            self.session.scalars(
                select(CaptureFrame)
                .where(CaptureFrame.session_id == session_id)
                .order_by(CaptureFrame.position)
            )
        )

    def blob_keys(self, map_id: str, session_id: str | None = None) -> list[str]:
        """The blob keys of the frames waiting in the map's sessions (of one session)."""
        if not is_stored_id(map_id):
            return []
        stmt = (
            select(CaptureFrame.original_key, CaptureFrame.depth_key)
            .join(CaptureSession, CaptureSession.id == CaptureFrame.session_id)
            .where(CaptureSession.map_id == map_id)
        )
        if session_id is not None:
            stmt = stmt.where(CaptureFrame.session_id == session_id)
        return [key for row in self.session.execute(stmt) for key in row if key is not None]

    def delete_frames(self, session_id: str) -> None:
        self.session.execute(delete(CaptureFrame).where(CaptureFrame.session_id == session_id))

    def set_state(
        self, session_id: str, state: str, from_states: tuple[str, ...], **values: object
    ) -> bool:
        """Moves the session from one of ``from_states`` to ``state`` with ``values``; False
        when it is in none of them (or gone)."""
        now = datetime.now(UTC)
        if state == "aligning":
            values.setdefault("started_at", now)
        elif state in FINISHED:
            values.setdefault("finished_at", now)
        updated = self.session.execute(
            update(CaptureSession)
            .where(CaptureSession.id == session_id, CaptureSession.state.in_(from_states))
            .values(state=state, **values)
        )
        return bool(getattr(updated, "rowcount", 0))
