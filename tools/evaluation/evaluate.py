"""The evaluation loop: per feature configuration, load the references into a fresh map once,
then localize every query with every estimator (in process, on one description and matching
of the query); summarize and write the outputs, also when interrupted (Ctrl-C leaves the
results so far)."""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.schemas.geometry import CameraSchema
from services.geometry.camera import CAMERA_MODELS, Camera
from services.geometry.intrinsics_adaptation import scale_camera
from services.imaging.decode import decode_image
from tools.evaluation.confidence_curve import curve_of, curve_summary
from tools.evaluation.datasets import PosedImage
from tools.evaluation.metrics import (
    QueryRecord,
    ReferencePoses,
    make_record,
    summarize,
)
from tools.evaluation.paired import paired_against_auto
from tools.evaluation.report import markdown_tables, write_json, write_plots
from tools.evaluation.runner import QueryOutcome, Runner
from tools.evaluation.split import Split
from tools.synthetic.scene import encode_png, unrelated_image


@dataclass(frozen=True)
class EvalOptions:
    """What to run: estimator names, the localize params they share, and which queries.

    Attributes:
        max_error_px: the API's ``max_error_px`` (None: the service default).
        use_depth: send depth maps where the dataset has them (references always, queries for
            the estimators that use depth).
        unrelated: also localize this many images of nothing in the map (false accepts).
        max_queries: localize only the first N queries of the split.
        wrong_focal: also localize the first N queries with a wrong focal length (×1.5 and
            ×0.67 in turn), as a client with wrong intrinsics does.
        unrelated_seed: the unrelated images are those of seeds ``unrelated_seed`` onwards.
        unrelated_images: also localize these images of another scene (with the first query's
            camera, its focal scaled to the image's width, principal point at the centre).
        send_intrinsics: send each query's camera (False: none, the service estimates the
            focal length).
        query_scale: send each query resized this many times, its camera scaled alike and
            without depth (a camera of another resolution than the map's).
    """

    estimators: Sequence[str]
    top_k: int = 10
    max_error_px: float | None = None
    use_depth: bool = True
    unrelated: int = 0
    max_queries: int | None = None
    wrong_focal: int = 0
    unrelated_seed: int = 0
    unrelated_images: Sequence[Path] = ()
    send_intrinsics: bool = True
    query_scale: float = 1.0


WRONG_FOCAL_SCALES = (1.5, 1 / 1.5)
MIN_QUERY_SCALE, MAX_QUERY_SCALE = 0.25, 4.0


@dataclass
class Evaluation:
    records: list[QueryRecord] = field(default_factory=list)
    summaries: dict[str, dict[str, Any]] = field(default_factory=dict)
    interrupted: bool = False
    error: str | None = None
    markdown: str = ""
    files: list[Path] = field(default_factory=list)


def _depth(image: PosedImage, wanted: bool) -> bytes | None:
    return image.depth_path.read_bytes() if wanted and image.depth_path is not None else None


def localize_params(
    camera: Camera | None, estimator: str, top_k: int, max_error_px: float | None = None
) -> dict[str, Any]:
    """The API's localize ``params`` object (without ``camera`` when ``camera`` is None)."""
    params: dict[str, Any] = {"estimator": estimator, "top_k": top_k}
    if camera is not None:
        params["camera"] = CameraSchema.from_camera(camera).model_dump()
    if max_error_px is not None:
        params["max_error_px"] = max_error_px
    return params


@dataclass(frozen=True)
class _Query:
    """A query of the split (``posed``), or an unrelated image (``posed`` None, PNG bytes)."""

    name: str
    camera: Camera
    posed: PosedImage | None
    unrelated_png: bytes = b""
    wrong_intrinsics: bool = False

    @property
    def resized(self) -> bool:
        """Sent at another size than its file's (``EvalOptions.query_scale``)."""
        return self.posed is not None and (self.camera.width, self.camera.height) != (
            self.posed.camera.width,
            self.posed.camera.height,
        )

    def image(self) -> bytes:
        """The upload: the unrelated image, the query's file, or the query resized to
        ``camera``'s size (as a PNG)."""
        if self.posed is None:
            return self.unrelated_png
        data = self.posed.image_path.read_bytes()
        if not self.resized:
            return data
        image = decode_image(data, 100_000_000)
        size = (self.camera.width, self.camera.height)
        shrink = size[0] < image.shape[1]
        resized = cv2.resize(
            image, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC
        )
        return encode_png(np.asarray(resized, dtype=np.uint8))


def scale_focal(camera: Camera, scale: float) -> Camera:
    """``camera`` with its focal length(s) multiplied by ``scale``."""
    focal = 1 if CAMERA_MODELS[camera.model][0] == "f" else 2
    params = tuple(v * scale for v in camera.params[:focal]) + camera.params[focal:]
    return replace(camera, params=params)


def _scaled(camera: Camera, scale: float) -> Camera:
    """``camera`` for its image resized ``scale`` times (itself at 1)."""
    if scale == 1.0:
        return camera
    size = (max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
    return scale_camera(camera, *size)


def _resized(camera: Camera, width: int, height: int) -> Camera:
    """A pinhole camera for a ``width`` × ``height`` image with ``camera``'s field of view."""
    f = camera.focal_lengths[0] * width / camera.width
    return Camera("PINHOLE", width, height, (f, f, width / 2.0, height / 2.0))


def _queries(split: Split, options: EvalOptions) -> list[_Query]:
    chosen = split.queries[: options.max_queries]
    cameras = [_scaled(q.camera, options.query_scale) for q in chosen]
    queries = [_Query(q.name, camera, q) for q, camera in zip(chosen, cameras, strict=True)]
    for i, (q, camera) in enumerate(zip(chosen[: options.wrong_focal], cameras, strict=False)):
        scale = WRONG_FOCAL_SCALES[i % len(WRONG_FOCAL_SCALES)]
        name = f"{q.name} (focal ×{scale:.2f})"
        queries.append(_Query(name, scale_focal(camera, scale), q, wrong_intrinsics=True))
    camera = chosen[0].camera
    for seed in range(options.unrelated_seed, options.unrelated_seed + options.unrelated):
        png = encode_png(unrelated_image(seed, camera.width, camera.height))
        queries.append(_Query(f"unrelated-{seed}", camera, None, png))
    for path in options.unrelated_images:
        data = path.read_bytes()
        height, width = decode_image(data, 100_000_000).shape[:2]
        queries.append(
            _Query(f"unrelated {path.name}", _resized(camera, width, height), None, data)
        )
    return queries


def run_evaluation(
    split: Split,
    runner_factories: Sequence[Callable[[], Runner]],
    options: EvalOptions,
    log: Callable[[str], None] = print,
    on_record: Callable[[QueryRecord], None] | None = None,
) -> Evaluation:
    """Run every feature configuration (one runner each) × estimator; stops early, keeping
    what it has, on KeyboardInterrupt (``interrupted``) or an error outside a query
    (``error``). A query whose localize raises is recorded as failed and the run goes on.
    ``on_record`` sees each record as it is made."""
    evaluation = Evaluation()
    references = ReferencePoses.of({r.name: r.cam_from_world for r in split.references})
    queries = _queries(split, options)
    try:
        for make_runner in runner_factories:
            runner = make_runner()
            try:
                _load_references(runner, split.references, options, log)
                _localize_all(runner, queries, references, options, evaluation, log, on_record)
            finally:
                runner.close()
    except KeyboardInterrupt:
        evaluation.interrupted = True
        log("interrupted: writing the results so far")
    except Exception as exc:  # a long run keeps what it measured; the error is reported
        evaluation.error = f"{type(exc).__name__}: {exc}"
        log(traceback.format_exc())
        log(f"failed ({evaluation.error}): writing the results so far")
    return evaluation


def failed_query(exc: Exception) -> QueryOutcome:
    """The outcome recorded for a query whose localize raised ``exc`` (reason
    ``error: <exception type>``)."""
    return QueryOutcome.not_localized(f"error: {type(exc).__name__}")


def _load_references(
    runner: Runner, images: list[PosedImage], options: EvalOptions, log: Callable[[str], None]
) -> None:
    start = time.perf_counter()
    for i, image in enumerate(images, start=1):
        runner.add_reference(image, _depth(image, options.use_depth))
        if i % 10 == 0 or i == len(images):
            elapsed = time.perf_counter() - start
            log(f"[{runner.features}] references {i}/{len(images)} ({elapsed:.0f} s)")
    runner.index_references(len(images))


def _localize_all(
    runner: Runner,
    queries: list[_Query],
    references: ReferencePoses,
    options: EvalOptions,
    evaluation: Evaluation,
    log: Callable[[str], None],
    on_record: Callable[[QueryRecord], None] | None,
) -> None:
    start = time.perf_counter()
    estimators = list(options.estimators)
    for i, item in enumerate(queries, start=1):
        image, query = item.image(), item.posed
        depth = _depth(query, options.use_depth and not item.resized) if query is not None else None
        params = localize_params(
            item.camera if options.send_intrinsics else None,
            estimators[0],
            options.top_k,
            options.max_error_px,
        )
        try:
            outcomes = runner.localize_each(image, depth, params, estimators)
        except Exception as exc:  # this query's failure; the run goes on
            log(traceback.format_exc())
            outcomes = [failed_query(exc)] * len(estimators)
        cells = []
        for estimator, outcome in zip(estimators, outcomes, strict=True):
            record = make_record(
                f"{runner.features}/{estimator}",
                item.name,
                outcome,
                query.cam_from_world if query is not None else None,
                references,
            )
            record.wrong_intrinsics = item.wrong_intrinsics
            evaluation.records.append(record)
            if on_record is not None:
                on_record(record)
            cells.append(
                f"{estimator} {record.position_error_m * 100:.1f}cm"
                f"/{record.rotation_error_deg:.1f}°"
                if record.localized and query is not None
                else f"{estimator} {'accepted' if record.localized else record.reason}"
            )
            if outcome.estimator_used not in (None, estimator):
                cells[-1] += f" ({outcome.estimator_used})"
        eta = (time.perf_counter() - start) / i * (len(queries) - i)
        log(
            f"[{runner.features} {i}/{len(queries)}, eta {eta:.0f} s] {item.name}: "
            + "; ".join(cells)
        )


def write_outputs(
    evaluation: Evaluation,
    out_dir: Path,
    meta: dict[str, Any],
    thresholds: tuple[tuple[float, float], ...],
) -> None:
    """Fill ``summaries`` and ``markdown``; write ``results.json``, ``report.md`` and the plots
    into ``out_dir``."""
    configs = list(dict.fromkeys(r.config for r in evaluation.records))
    evaluation.summaries = {}
    for config in configs:
        records = [r for r in evaluation.records if r.config == config]
        summary = summarize(records, thresholds)
        summary["confidence"] = curve_summary(curve_of(records))
        evaluation.summaries[config] = summary
    for config, against in paired_against_auto(evaluation.records, thresholds).items():
        evaluation.summaries[config]["paired"] = against
    evaluation.markdown = markdown_tables(evaluation.summaries, thresholds)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "interrupted": evaluation.interrupted, "error": evaluation.error}
    json_path, md_path = out_dir / "results.json", out_dir / "report.md"
    write_json(json_path, meta, evaluation.summaries, evaluation.records)
    md_path.write_text(evaluation.markdown)
    evaluation.files = [md_path, json_path]
    if evaluation.records:
        evaluation.files += write_plots(out_dir, evaluation.summaries, evaluation.records)
