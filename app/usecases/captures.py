"""Capture sessions: a capture (frames with their poses in the device's own frame) aligned to
a map and added to it as references, or refused with the reason.

A session is created ``open``; its frames are uploaded one by one (each image and depth kept in
the blob store under the keys of the reference it will become); once submitted it is
``queued``, then a background job ``aligning`` it localizes a spread of its frames against the
map and estimates ``map_from_session`` (``services.capture.alignment``). When the alignment is
well determined, the job is ``adding``: every frame is described and stored as a reference
with its pose mapped into the map, one transaction per frame that inserts the reference and
removes the waiting frame (so the frame's blobs always have exactly one row); then ``added``.
Otherwise the session ends ``refused`` and its frames are removed: nothing is added.

On an empty map the session defines the map's frame (``bootstrap``): every frame is added with
its session pose; the session must be metric.

A restart resumes what it interrupted: a session ``queued`` or ``aligning`` is aligned again
from its start (nothing was added yet); one ``adding`` adds the frames left. A session that
fails while adding is rolled back: the references it added are deleted.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy.exc import IntegrityError, SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import ConflictError, NameTakenError, NotFoundError
from app.usecases.freshness import flag_stale
from app.usecases.geo import estimate_map_registration
from app.usecases.localize import LocalizeContext, LocalizeRequest, localize
from app.usecases.maps import require_map
from app.usecases.served_features import map_localizer
from db.blobs import BlobStore
from db.models import CaptureFrame, CaptureSession
from db.originals import StoredOriginals, remove_blobs, write_originals
from db.repositories.captures import ACTIVE, CaptureRepository
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.store import camera_of, gps_of, pose_of
from services.capture.alignment import (
    Alignment,
    CheckedFrame,
    Similarity,
    align,
    check_count,
    check_indices,
    densify,
    path_length,
)
from services.capture.drift import REACH_M, anchored, corrected_poses
from services.capture.freshness import (
    MIN_EVIDENCE,
    Vote,
    best_inliers,
    covering,
    frame_votes,
    reusable_inliers,
)
from services.capture.spacing import map_spacing, new_views
from services.components import Localizers
from services.errors import InvalidInputError
from services.features.base import LocalFeatures
from services.geo.gps import GpsFix, gps_from_exif
from services.geo.registration import DEFAULT_MAX_ERROR_M, MIN_GPS_REFERENCES
from services.geometry.camera import Camera, default_camera
from services.geometry.rigid import Rigid3d, matrix_to_quaternion
from services.imaging.decode import check_pixel_limit, decode_image_reduced
from services.localization.answer import LocalizationResult
from services.localization.localizer import Localizer
from services.localization.stages import check_camera_matches, decode_depth_for
from services.retrieval.training import BackgroundTrainer
from services.runtime.worker_slots import holding

logger = logging.getLogger(__name__)

# references retrieved for each checked frame
CHECK_TOP_K = 10


@dataclass(frozen=True)
class NewFrame:
    """An uploaded frame: its name in the session (None: its position, ``00000``…), its
    camera (None: the default camera for the image size), its ``cam_from_session``
    (COLMAP camera axes) and its GPS fix."""

    name: str | None
    camera: Camera | None
    cam_from_session: Rigid3d
    # the device's GPS fix when the frame was taken; None: the image's EXIF GPS, if any
    gps: GpsFix | None = None


def create_session(
    sessions: sessionmaker[Session],
    map_id: str,
    name: str | None,
    metric: bool,
    keep_all: bool = False,
) -> CaptureSession:
    """A new ``open`` session of the map (``name`` None: a random one). ``keep_all``: every
    frame is added, not only those that add a view (``services.capture.spacing``).

    Raises:
        NotFoundError: unknown map.
        NameTakenError: the map has a session of that name.
    """
    name = name or f"session-{uuid.uuid4().hex[:8]}"
    try:
        with sessions.begin() as session:
            require_map(session, map_id)
            repository = CaptureRepository(session)
            if repository.name_exists(map_id, name):
                raise NameTakenError(f"map already has a capture session named {name!r}")
            row = repository.create(map_id, name, metric, keep_all)
            session.expunge(row)
            return row
    except IntegrityError as exc:  # created meanwhile by another request
        raise NameTakenError(f"map already has a capture session named {name!r}") from exc


def add_frame(
    sessions: sessionmaker[Session],
    localizers: Localizers,
    blobs: BlobStore,
    map_id: str,
    session_id: str,
    frame: NewFrame,
    image_bytes: bytes,
    depth_bytes: bytes | None,
    max_frames: int,
) -> CaptureFrame:
    """Store one frame of an open session: its image (decoded here, so that a frame the job
    could not describe is refused now) and depth in the blob store, then its row. Without a
    GPS fix, the one in the image's EXIF is kept.

    Raises:
        NotFoundError: unknown map or session.
        ConflictError: the session is no longer open, holds ``max_frames`` frames, or has a
            frame of that name.
        ImageTooLargeError: the image's header claims more than the pixel limit.
        InvalidInputError: the image, depth or camera is unusable.
        BlobStoreError: the blob store cannot be reached or refuses the write.
    """
    served = localizers.served
    check_pixel_limit(image_bytes, served.max_pixels)
    # EXIF is read only once the header passed the pixel limit
    gps = frame.gps if frame.gps is not None else gps_from_exif(image_bytes)
    image = decode_image_reduced(image_bytes, served.max_pixels, served.extractor.max_side)
    camera = frame.camera or default_camera(image.width, image.height)
    check_camera_matches(camera, image)
    decode_depth_for(depth_bytes, camera, served.max_pixels)
    with sessions() as session:
        _check_open(_require_session(session, map_id, session_id), max_frames)
    frame_id = str(uuid.uuid4())
    originals = write_originals(blobs, map_id, frame_id, image_bytes, depth_bytes)
    try:
        with sessions.begin() as session:
            repository = CaptureRepository(session)
            locked = repository.lock(session_id)
            if locked is None or locked.map_id != map_id:
                raise NotFoundError("capture session", session_id)
            _check_open(locked, max_frames)
            name = frame.name or f"{locked.frame_count:05d}"
            if repository.frame_name_exists(session_id, name):
                raise NameTakenError(f"the session already has a frame named {name!r}")
            stored = repository.add_frame(
                locked, frame_id, name, camera, frame.cam_from_session, originals, gps
            )
            session.expunge(stored)
            return stored
    except BaseException:
        remove_blobs(blobs, originals.keys)
        raise


def submit_session(
    sessions: sessionmaker[Session], map_id: str, session_id: str, runner: CaptureRunner | None
) -> CaptureSession:
    """Closes an open session and queues its alignment.

    Raises:
        NotFoundError: unknown map or session.
        ConflictError: the session is not open, or has no frame.
        InvalidInputError: a session of unknown scale sent to an empty map (it would define
            the map's frame without metres).
    """
    with sessions.begin() as session:
        repository = CaptureRepository(session)
        row = _lock_session(session, map_id, session_id)
        if row.state != "open":
            raise ConflictError(f"the capture session is {row.state}, not open")
        if row.frame_count == 0:
            raise ConflictError("the capture session has no frame: upload its frames first")
        if not row.metric and not MapRepository(session).image_counts([map_id]).get(map_id):
            raise InvalidInputError(
                "metric: the map is empty, so this session would define its frame; a session "
                "of unknown scale cannot (its map would not be in metres)"
            )
        repository.set_state(session_id, "queued", ("open",))
        session.flush()
        session.refresh(row)
        session.expunge(row)
    if runner is not None:
        runner.schedule(session_id)
    return row


def get_session(sessions: sessionmaker[Session], map_id: str, session_id: str) -> CaptureSession:
    """Raises: NotFoundError: unknown map or session."""
    with sessions() as session:
        row = _require_session(session, map_id, session_id)
        session.expunge(row)
        return row


def list_sessions(
    sessions: sessionmaker[Session], map_id: str, offset: int, limit: int
) -> tuple[list[CaptureSession], int]:
    """The map's capture sessions, newest first. Raises: NotFoundError: unknown map."""
    with sessions() as session:
        require_map(session, map_id)
        rows, total = CaptureRepository(session).page(map_id, offset, limit)
        session.expunge_all()
        return rows, total


def delete_session(
    sessions: sessionmaker[Session], blobs: BlobStore, map_id: str, session_id: str
) -> None:
    """Deletes a session and its frames not added (then their blobs). One being aligned
    stops; the references a session added stay (delete them as images).

    Raises:
        NotFoundError: unknown map or session.
        ConflictError: the session's frames are being added (wait for it to end).
    """
    with sessions.begin() as session:
        repository = CaptureRepository(session)
        row = _lock_session(session, map_id, session_id)
        if row.state == "adding":
            raise ConflictError(
                "the capture session's frames are being added to the map: delete it once it "
                "has ended"
            )
        keys = repository.blob_keys(map_id, session_id)
        session.delete(row)
    remove_blobs(blobs, keys)


def _require_session(session: Session, map_id: str, session_id: str) -> CaptureSession:
    row = CaptureRepository(session).get(map_id, session_id)
    if row is None:
        require_map(session, map_id)
        raise NotFoundError("capture session", session_id)
    return row


def _lock_session(session: Session, map_id: str, session_id: str) -> CaptureSession:
    """The map's session, its row locked until the transaction ends.

    Raises:
        NotFoundError: unknown map or session.
    """
    row = CaptureRepository(session).lock(session_id)
    if row is None or row.map_id != map_id:
        require_map(session, map_id)
        raise NotFoundError("capture session", session_id)
    return row


def _check_open(row: CaptureSession, max_frames: int) -> None:
    if row.state != "open":
        raise ConflictError(f"the capture session is {row.state}: it takes no more frames")
    if row.frame_count >= max_frames:
        raise ConflictError(
            f"the capture session holds {max_frames} frames, the most one may "
            "(SLLOC_MAX_SESSION_FRAMES): submit it and send the rest as another session"
        )


class SessionStoppedError(Exception):
    """The session was deleted, or the server is stopping."""


def similarity_json(similarity: Similarity) -> dict[str, Any]:
    return {
        "rotation": [float(v) for v in matrix_to_quaternion(similarity.rotation)],
        "translation": [float(v) for v in similarity.translation],
        "scale": float(similarity.scale),
    }


def similarity_of(stored: dict[str, Any]) -> Similarity:
    rigid = Rigid3d.from_quaternion(np.array(stored["rotation"]), np.array(stored["translation"]))
    return Similarity(rigid.rotation, rigid.translation, float(stored["scale"]))


class CaptureRunner:
    """Aligns and adds the submitted sessions, one at a time, on a background thread at the
    lowest CPU priority."""

    def __init__(
        self,
        context: LocalizeContext,
        blobs: BlobStore,
        on_added: Callable[[str, Localizer], None] | None = None,
    ) -> None:
        """``context``: how the checked frames are localized (the localize requests'
        engine, slots and caches); ``on_added``: called with the map's id once a session's
        frames are added, and the localizer that described them (its vocabulary and
        self-evaluation may be due)."""
        self.context = context
        self.sessions = context.sessions
        self.localizers: Localizers = context.localizers
        self.blobs = blobs
        self.on_added = on_added
        self.worker = BackgroundTrainer("capture sessions")
        self.finished: dict[str, int] = {}  # sessions ended since start-up, by state
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def resume(self) -> None:
        """Schedules the sessions a restart interrupted (read in the background)."""
        self.worker.schedule("resume", self._resume)

    def _resume(self) -> None:
        try:
            with self.sessions() as session:
                unfinished = CaptureRepository(session).unfinished()
        except SQLAlchemyError as exc:
            logger.warning("capture sessions not resumed, the database is unreachable: %s", exc)
            return
        for session_id in unfinished:
            self.schedule(session_id)

    def schedule(self, session_id: str) -> None:
        self.worker.schedule(session_id, lambda: self.run(session_id))

    def run(self, session_id: str) -> None:
        """Runs the session to its end: ``added``, ``refused``, ``failed`` (rolled back), or
        nothing when it was deleted meanwhile."""
        try:
            self._run(session_id)
        except (SessionStoppedError, NotFoundError):
            logger.info("capture session %s stopped", session_id)
        except Exception as exc:  # a background job: whatever stops it ends it, never stuck
            logger.exception("capture session %s failed", session_id)
            self._roll_back(session_id, str(exc) or type(exc).__name__)

    def _run(self, session_id: str) -> None:
        with self.sessions() as session:
            row = session.get(CaptureSession, session_id)
            if row is None or row.state not in ACTIVE:
                return
            state, map_id = row.state, row.map_id
        if state == "adding" or self._align(session_id, map_id):
            self._add(session_id, map_id)

    def _align(self, session_id: str, map_id: str) -> bool:
        """Aligns the session; True when its frames are to be added (the session is then
        ``adding`` with its alignment stored), False when it was refused."""
        with self.sessions.begin() as session:
            row = session.get(CaptureSession, session_id)
            if row is None:
                raise SessionStoppedError
            require_map(session, map_id)
            frames = CaptureRepository(session).frames(session_id)
            metric, name, keep_all = row.metric, row.name, row.keep_all
            empty = not MapRepository(session).image_counts([map_id]).get(map_id)
            poses = [pose_of(frame) for frame in frames]
            checked = [] if empty else check_indices(len(frames), check_count(len(frames)))
            CaptureRepository(session).set_state(
                session_id, "aligning", ACTIVE, done=0, total=len(checked) + len(frames)
            )
        path_m = path_length(poses)
        ids = [frame.id for frame in frames]
        if empty and not metric:  # the map lost its references after the session was submitted
            reason = "the map is empty: a session of unknown scale cannot define its frame"
            result_empty = {"mode": "bootstrap", "map_from_session": None, "reason": reason}
            return self._decided(
                session_id, map_id, result_empty | {"path_length_m": path_m, "checked": []}, None
            )
        if empty:
            logger.info("capture session %s (%r) bootstraps map %s", session_id, name, map_id)
            result: dict[str, Any] = {
                "mode": "bootstrap",
                "map_from_session": similarity_json(Similarity.identity()),
                "path_length_m": path_m,
                "checked": [],
                "frame_ids": ids,
            }
            return self._decided(session_id, map_id, result, dict(zip(ids, poses, strict=True)))
        # each checked frame's localization: how well the place matched, and the inliers its
        # retrieved references gave
        checks: dict[int, LocalizationResult] = {}
        localized = [
            self._check(session_id, map_id, frames[i], i, n, checks) for n, i in enumerate(checked)
        ]
        # a session that overlaps the map over a short stretch (it extends the map): the
        # frames around those the map localized are checked too
        found = [f.index for f in localized if f.cam_from_map is not None]
        more = densify(checked, found, len(frames))
        if more:
            with self.sessions.begin() as session:
                row = session.get(CaptureSession, session_id)
                if row is None:
                    raise SessionStoppedError
                row.total += len(more)
            offset = len(localized)
            localized += [
                self._check(session_id, map_id, frames[i], i, offset + n, checks)
                for n, i in enumerate(more)
            ]
            localized.sort(key=lambda f: f.index)
        alignment = align(localized, path_m, metric)
        result = _alignment_json(alignment, localized, frames, path_m) | {"frame_ids": ids}
        placed: dict[str, Rigid3d] | None = None
        if alignment.map_from_session is not None:
            agreeing = {r.index for r in alignment.residuals if r.agrees}
            anchors = {
                f.index: f.cam_from_map
                for f in localized
                if f.index in agreeing and f.cam_from_map is not None
            }
            corrected, shifts = corrected_poses(alignment.map_from_session, poses, anchors)
            # frames beyond an anchor's reach carry drift nothing measured
            reach = REACH_M / alignment.map_from_session.scale
            kept = anchored(poses, sorted(anchors), reach)
            result["unanchored"] = len(frames) - len(kept)
            if not keep_all:
                references = self._reference_ids_and_poses(map_id)[1]
                spacing = map_spacing(np.array([p.center for p in references]))
                if spacing is not None:
                    views = new_views([corrected[i] for i in kept], references, spacing)
                    kept = [kept[j] for j in views]
                    result["spacing_m"] = spacing
            placed = {ids[i]: corrected[i] for i in kept}
            result["skipped"] = len(frames) - len(kept)  # unanchored included
            result["stale"] = self._freshness(map_id, name, frames, anchors, checks)
            result["drift_correction_m"] = {
                "median": float(np.median(shifts)),
                "max": float(shifts.max()),
            }
        logger.info(
            "capture session %s (%r) of map %s: %s",
            session_id,
            name,
            map_id,
            alignment.reason or f"aligned on {alignment.agreeing} of {len(localized)} frames",
        )
        return self._decided(session_id, map_id, result, placed)

    def _freshness(
        self,
        map_id: str,
        session_name: str,
        frames: list[CaptureFrame],
        anchors: dict[int, Rigid3d],
        checks: dict[int, LocalizationResult],
    ) -> list[dict[str, Any]]:
        """The votes of the anchors on the references that cover them
        (``services.capture.freshness``), from their localizations (``checks``), stored by
        ``flag_stale``: the stale ones, as the result lists them."""
        localizer, _, store = self.context.map_engine(map_id, LocalizeRequest())
        ids, poses = self._reference_ids_and_poses(map_id)
        spacing = map_spacing(np.array([p.center for p in poses]))
        if spacing is None:
            return []
        votes: list[Vote] = []
        for index, cam_from_map in sorted(anchors.items()):
            check = checks[index]
            evidence = best_inliers(check)
            near = covering(cam_from_map, poses, spacing)
            if evidence < MIN_EVIDENCE or not near:
                continue
            frame = frames[index]
            camera = camera_of(frame)

            def describe(frame: CaptureFrame = frame, camera: Camera = camera) -> LocalFeatures:
                original = self.blobs.get(frame.original_key)
                return localizer.describe_reference(original, camera).features

            memory = localizer.memory_mib(camera.width, camera.height, False, len(near))
            with holding(self.context.slots, memory):
                votes += frame_votes(
                    frame.name,
                    camera,
                    cam_from_map,
                    store.load_references([ids[i] for i in near]),
                    reusable_inliers(check, camera),
                    describe,
                    localizer.matcher,
                    evidence,
                )
        return flag_stale(
            self.sessions,
            self.blobs,
            self.context.features_cache,
            map_id,
            votes,
            f"capture session {session_name!r}",
        )

    def _reference_ids_and_poses(self, map_id: str) -> tuple[list[str], list[Rigid3d]]:
        with self.sessions() as session:
            poses = ImageRepository(session).poses(map_id)
        return list(poses), list(poses.values())

    def _check(
        self,
        session_id: str,
        map_id: str,
        frame: CaptureFrame,
        index: int,
        done: int,
        checks: dict[int, LocalizationResult],
    ) -> CheckedFrame:
        """The frame localized against the map as a query with its own camera; ``checks``
        gets its localization."""
        answer = localize(
            self.context,
            map_id,
            LocalizeRequest(camera=camera_of(frame), top_k=CHECK_TOP_K),
            self.blobs.get(frame.original_key),
        )
        checks[index] = answer
        self._progress(session_id, done + 1)
        return CheckedFrame(
            index,
            pose_of(frame),
            answer.cam_from_world if answer.localized else None,
            answer.confidence,
        )

    def _decided(
        self,
        session_id: str,
        map_id: str,
        result: dict[str, Any],
        placed: dict[str, Rigid3d] | None,
    ) -> bool:
        """Stores the decision: with ``placed`` (each frame's pose in the map, by frame id)
        the session goes on ``adding``; without, it is ``refused`` and its frames removed."""
        if placed is None:
            with self.sessions.begin() as session:
                repository = CaptureRepository(session)
                keys = repository.blob_keys(map_id, session_id)
                # its progress ends where the checks did: no frame is added
                done = CaptureSession.done
                if not repository.set_state(
                    session_id, "refused", ACTIVE, result=result, total=done
                ):
                    raise SessionStoppedError
                repository.delete_frames(session_id)
            remove_blobs(self.blobs, keys)
            self._count("refused")
            return False
        skipped: list[str] = []
        with self.sessions.begin() as session:
            repository = CaptureRepository(session)
            if not repository.set_state(
                session_id, "adding", ACTIVE, result=result, total=CaptureSession.done + len(placed)
            ):
                raise SessionStoppedError
            for frame in repository.frames(session_id):
                pose = placed.get(frame.id)
                if pose is None:  # its view is in the map already
                    skipped += [k for k in (frame.original_key, frame.depth_key) if k]
                    session.delete(frame)
                else:
                    frame.placed = [*map(float, pose.quaternion), *map(float, pose.translation)]
        remove_blobs(self.blobs, skipped)
        return True

    def _add(self, session_id: str, map_id: str) -> None:
        with self.sessions() as session:
            row = session.get(CaptureSession, session_id)
            if row is None or row.result is None:
                raise SessionStoppedError
            prefix, done = row.name, row.done
            bootstrap = row.result.get("mode") == "bootstrap"
            localizer = map_localizer(self.localizers, require_map(session, map_id))
            frames = CaptureRepository(session).frames(session_id)
            session.expunge_all()
        added = 0
        for frame in frames:
            if self._stopping.is_set():
                raise SessionStoppedError  # resumed at the next start
            image = self.blobs.get(frame.original_key)
            depth = self.blobs.get(frame.depth_key) if frame.depth_key else None
            camera = camera_of(frame)
            with holding(self.context.slots, localizer.upload_memory_mib(image, depth is not None)):
                data = localizer.describe_reference(image, camera, depth)
            if frame.placed is None:
                raise ValueError(f"frame {frame.name!r} of an aligned session has no pose")
            pose = Rigid3d.from_quaternion(np.array(frame.placed[:4]), np.array(frame.placed[4:]))
            originals = StoredOriginals(frame.original_key, frame.original_sha256, frame.depth_key)
            with self.sessions.begin() as session:
                repository = ImageRepository(session)
                name = f"{prefix}/{frame.name}"
                if repository.name_exists(map_id, name):
                    name = f"{name}~{frame.id[:8]}"
                repository.add(
                    map_id,
                    name,
                    camera,
                    pose,
                    data,
                    gps_of(frame),
                    image_id=frame.id,
                    originals=originals,
                )
                waiting = session.get(CaptureFrame, frame.id)
                if waiting is not None:
                    session.delete(waiting)
                row = session.get(CaptureSession, session_id)
                if row is None:
                    raise SessionStoppedError
                row.done += 1
            added += 1
        # a session that defined the map's frame may place it on the globe too
        geo = self._geo_register(session_id, map_id) if bootstrap else None
        with self.sessions.begin() as session:
            row = session.get(CaptureSession, session_id)
            if row is None:
                raise SessionStoppedError
            result: dict[str, Any] = dict(row.result or {})
            result["added"] = row.frame_count - int(result.get("skipped") or 0)
            if geo is not None:
                result["geo_registration"] = geo
            CaptureRepository(session).set_state(session_id, "added", ("adding",), result=result)
        self._count("added")
        logger.info(
            "capture session %s: %d frames added to map %s (%d before a restart)",
            session_id,
            added,
            map_id,
            done,
        )
        if self.on_added is not None:
            self.on_added(map_id, localizer)

    def _geo_register(self, session_id: str, map_id: str) -> dict[str, Any]:
        """The geo-registration of a map a session bootstrapped, estimated from its
        references' GPS (``estimate_map_registration``) and stored when the map has none yet
        and at least 3 references carry GPS with height; what happened, as the session's
        result reports it. An estimate that fails leaves the map without a registration and
        the session unharmed."""
        try:
            with self.sessions() as session:
                registered = require_map(session, map_id).geo_registration is not None
                fixes = [gps_of(row) for row in ImageRepository(session).with_gps(map_id)]
            if registered:  # set meanwhile by hand: kept
                return {"set": False, "reason": "the map has a geo-registration already"}
            with_height = sum(f is not None and f.height is not None for f in fixes)
            if with_height < MIN_GPS_REFERENCES:
                reason = f"fewer than {MIN_GPS_REFERENCES} frames carry GPS with height"
                return {"set": False, "reason": reason}
            stored, _ = estimate_map_registration(self.sessions, map_id, DEFAULT_MAX_ERROR_M)
        except InvalidInputError as exc:
            logger.info(
                "capture session %s: map %s not geo-registered: %s", session_id, map_id, exc
            )
            return {"set": False, "reason": str(exc)}
        except Exception as exc:  # the frames are added: the estimate never fails the session
            logger.exception(
                "capture session %s: geo-registering map %s failed", session_id, map_id
            )
            return {"set": False, "reason": f"the estimate failed: {exc}"}
        logger.info(
            "capture session %s: map %s geo-registered from %s references (%s inliers, RMS %.3f m)",
            session_id,
            map_id,
            stored.num_references,
            stored.num_inliers,
            stored.residual_rms_m,
        )
        return {
            "set": True,
            "num_references": stored.num_references,
            "num_inliers": stored.num_inliers,
            "residual_rms_m": stored.residual_rms_m,
        }

    def _roll_back(self, session_id: str, error: str) -> None:
        """Ends a failed session ``failed``: the references it added deleted, its frames and
        their blobs removed."""
        try:
            with self.sessions.begin() as session:
                row = session.get(CaptureSession, session_id)
                if row is None:
                    return
                map_id = row.map_id
                ids = [str(i) for i in (row.result or {}).get("frame_ids", [])]  # type: ignore[attr-defined]
                repository = CaptureRepository(session)
                keys = repository.blob_keys(map_id, session_id)
                images = ImageRepository(session)
                for image_id in ids:
                    keys += images.blob_keys(map_id, image_id)
                    images.delete(map_id, image_id)
                repository.delete_frames(session_id)
                repository.set_state(session_id, "failed", ACTIVE, error=error)
        except SQLAlchemyError as exc:
            logger.warning("capture session %s: its failure was not stored: %s", session_id, exc)
            return
        if self.context.features_cache is not None:
            self.context.features_cache.discard(map_id, ids)
        remove_blobs(self.blobs, keys)
        self._count("failed")

    def _progress(self, session_id: str, done: int) -> None:
        if self._stopping.is_set():
            raise SessionStoppedError
        with self.sessions.begin() as session:
            row = session.get(CaptureSession, session_id)
            if row is None or row.state != "aligning":
                raise SessionStoppedError
            row.done = done

    def _count(self, state: str) -> None:
        with self._lock:
            self.finished[state] = self.finished.get(state, 0) + 1

    def shutdown(self) -> None:
        self._stopping.set()
        self.worker.shutdown()


def _alignment_json(
    alignment: Alignment, checked: list[CheckedFrame], frames: list[CaptureFrame], path_m: float
) -> dict[str, Any]:
    residuals = {r.index: r for r in alignment.residuals}
    rows = []
    for frame in checked:
        residual = residuals.get(frame.index)
        rows.append(
            {
                "frame": frames[frame.index].name,
                "localized": frame.cam_from_map is not None,
                "confidence": round(float(frame.confidence), 4),
                "position_error_m": residual.position_m if residual else None,
                "rotation_error_deg": residual.rotation_deg if residual else None,
                "agrees": residual.agrees if residual else False,
            }
        )
    return {
        "mode": "aligned",
        "map_from_session": (
            similarity_json(alignment.map_from_session)
            if alignment.map_from_session is not None
            else None
        ),
        "reason": alignment.reason,
        "path_length_m": path_m,
        "tolerance_m": alignment.tolerance_m,
        "confident": alignment.confident,
        "agreeing": alignment.agreeing,
        "rms_position_m": alignment.rms_position_m,
        "rms_rotation_deg": alignment.rms_rotation_deg,
        "position_stderr_m": alignment.position_stderr_m,
        "rotation_stderr_deg": alignment.rotation_stderr_deg,
        "checked": rows,
    }
