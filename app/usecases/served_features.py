"""Whether this server can localize against a map: its references' stored features were
described by some extractor (``feature_model``, e.g. ``aliked-n16-1024-640``) and global
descriptor (``descriptor_model``); a localize describes the query with the server's, set up for
the map (``Localizer.for_map``), and only references described by the same are searched. A map
none of whose references this server describes alike cannot be served: a localize is refused
naming the models missing (:class:`FeaturesUnavailableError`), never answered
``no_references``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.usecases.errors import ConflictError
from db.models import Map, ReferenceImage
from db.repositories.maps import MapRepository
from services.components import Localizers, PresetUnavailableError
from services.errors import InvalidInputError
from services.features.configs import FEATURE_CONFIGS, described_by
from services.localization.localizer import Localizer
from services.runtime.manifest import read_manifest


class _Named(Protocol):
    @property
    def name(self) -> str: ...


class _Described(Protocol):
    @property
    def extractor(self) -> _Named: ...

    @property
    def global_descriptor(self) -> _Named: ...


class MapLocalizer(Protocol):
    """What is read of the server's localizers (``services.components.Localizers``): the
    names of the extractor and global descriptor a map's configuration and options give."""

    def for_map(
        self, max_keypoints: int | None, max_side: int | None, preset: str | None = None
    ) -> _Described: ...


class FeaturesUnavailableError(ConflictError):
    """This server cannot describe queries as the map's references were described: the
    models they need are not built here, or the server runs another feature
    configuration."""


@dataclass(frozen=True)
class DescribedBy:
    """References of a map described alike, and whether this server describes queries so."""

    feature_model: str
    descriptor_model: str
    image_count: int
    served: bool


@dataclass(frozen=True)
class MapServing:
    """What this server makes of a map's stored features.

    Attributes:
        feature_model / descriptor_model: what this server describes the map's queries with.
        described_by: the map's references, grouped by what described them.
        servable: some reference (or none stored: an empty map) is described as this server
            describes queries.
        missing_models: the exported models the unserved references' features need that are
            not built in the server's models folder.
        configurations: the feature configurations (``SLLOC_FEATURES``) whose extractor
            described the unserved references.
        detail: one sentence on what is wrong and what to do (None when all is served).
    """

    feature_model: str
    descriptor_model: str
    described_by: tuple[DescribedBy, ...]
    servable: bool
    missing_models: tuple[str, ...] = ()
    configurations: tuple[str, ...] = ()
    detail: str | None = None

    @property
    def unserved_count(self) -> int:
        return sum(group.image_count for group in self.described_by if not group.served)


def map_serving(
    map_id: str,
    max_keypoints: int | None,
    max_side: int | None,
    groups: Iterable[tuple[str, str, int]],
    localizer: MapLocalizer,
    models_dir: Path,
    features: str = "",
    preset: str | None = None,
) -> MapServing:
    """How this server (``localizer``, its models in ``models_dir``, configuration
    ``features``) serves a map of configuration ``preset`` (None: the server's) with these
    feature options whose references are ``groups`` of ``(feature model, descriptor model,
    image count)``."""
    try:
        serving = localizer.for_map(max_keypoints, max_side, preset)
        feature_model = serving.extractor.name
        descriptor_model = serving.global_descriptor.name
    except PresetUnavailableError as exc:  # the map's configuration is not served here
        described = tuple(DescribedBy(f, d, n, False) for f, d, n in groups)
        return MapServing(
            "",
            "",
            described,
            not described,
            configurations=(str(preset),),
            detail=f"map {map_id}: {exc}; until then no localize can be answered on this map",
        )
    except InvalidInputError:  # options the server's extractor cannot honour
        feature_model = descriptor_model = ""
    described = tuple(
        DescribedBy(f, d, n, f == feature_model and d == descriptor_model) for f, d, n in groups
    )
    servable = not described or any(group.served for group in described)
    unserved = [group for group in described if not group.served]
    if not unserved:
        return MapServing(feature_model, descriptor_model, described, True)
    extractors = {group.feature_model for group in unserved}
    configurations = tuple(
        sorted(
            name
            for name, config in FEATURE_CONFIGS.items()
            if any(described_by(config, model) for model in extractors)
        )
    )
    built = set(read_manifest(models_dir))
    needed = {m for name in configurations for m in FEATURE_CONFIGS[name].models}
    missing = tuple(sorted(needed - built))
    count = sum(group.image_count for group in unserved)
    what = ", ".join(sorted(extractors))
    descriptors = {group.descriptor_model for group in unserved}
    detail = (
        f"map {map_id}: {count} of its references were described by {what} "
        f"(global descriptor {', '.join(sorted(descriptors))}); this server describes its "
        f"queries with {feature_model or 'no extractor'} ({descriptor_model or '-'})"
        + (f", SLLOC_FEATURES={features}" if features else "")
        + ". "
    )
    if missing:
        detail += (
            f"Models missing from {models_dir}: {', '.join(missing)}; build them "
            f"(`slloc models build --models {','.join(missing)}`) and restart with "
            f"SLLOC_FEATURES set to one of {', '.join(configurations)}"
        )
    elif configurations:
        detail += (
            f"Their models are built: restart with SLLOC_FEATURES set to one of "
            f"{', '.join(configurations)} (with the budget and image size they were "
            "described at)"
        )
    else:
        detail += (
            "No feature configuration of this server describes them alike (another global "
            "descriptor model, SLLOC_GLOBAL_MODEL, or another version): add the references "
            "again"
        )
    return MapServing(
        feature_model,
        descriptor_model,
        described,
        servable,
        missing,
        configurations,
        detail + ("" if servable else "; until then no localize can be answered on this map"),
    )


def check_servable(
    session: Session,
    map_id: str,
    max_keypoints: int | None,
    max_side: int | None,
    localizer: MapLocalizer,
    models_dir: Path,
    features: str = "",
    preset: str | None = None,
) -> None:
    """Check that this server (``localizer``, not yet set up for the map) can localize
    against the map of configuration ``preset``. Cheap on a served map: one query for a
    reference described as this server describes the map's queries.

    Raises:
        FeaturesUnavailableError: the map's configuration is not served here, or the map has
            references, none of them described so.
    """
    try:
        serving = localizer.for_map(max_keypoints, max_side, preset)
    except PresetUnavailableError as exc:
        raise FeaturesUnavailableError(f"map {map_id}: {exc}") from None
    except InvalidInputError:
        return  # the localize itself reports the map's options
    feature_model = serving.extractor.name
    descriptor_model = serving.global_descriptor.name
    on_map = ReferenceImage.map_id == map_id
    served = session.scalar(
        select(ReferenceImage.id)
        .where(
            on_map,
            ReferenceImage.feature_model == feature_model,
            ReferenceImage.descriptor_model == descriptor_model,
        )
        .limit(1)
    )
    if served is not None:
        return
    if session.scalar(select(ReferenceImage.id).where(on_map).limit(1)) is None:
        return  # an empty map: answered no_references
    groups = MapRepository(session).described_by([map_id]).get(map_id, [])
    verdict = map_serving(
        map_id, max_keypoints, max_side, groups, localizer, models_dir, features, preset
    )
    if not verdict.servable:
        raise FeaturesUnavailableError(verdict.detail)


def map_localizer(localizers: Localizers, map_row: Map) -> Localizer:
    """The localizer of the map's feature configuration, set up for its options.

    Raises:
        FeaturesUnavailableError: the map's configuration is not served here.
        InvalidInputError: its extractor cannot honour the map's options.
    """
    try:
        return localizers.for_map(map_row.max_keypoints, map_row.max_side, map_row.feature_preset)
    except PresetUnavailableError as exc:
        raise FeaturesUnavailableError(f"map {map_row.id}: {exc}") from None


@dataclass(frozen=True)
class UnservableMap:
    """A map this server cannot localize against, and why."""

    id: str
    name: str
    image_count: int
    serving: MapServing


def unservable_maps(
    session: Session,
    localizer: MapLocalizer,
    models_dir: Path,
    features: str = "",
    limit: int = 20,
) -> tuple[int, list[UnservableMap]]:
    """The number of maps with references this server cannot serve at all, and the first
    ``limit`` of them (most references first). Reads every reference's models (one grouped
    query): callers should not run it per request."""
    groups = MapRepository(session).described_by(None)
    if not groups:
        return 0, []
    options = {
        row.id: row
        for row in session.execute(
            select(Map.id, Map.name, Map.max_keypoints, Map.max_side, Map.feature_preset).where(
                Map.id.in_(list(groups))
            )
        )
    }
    found = []
    for map_id, described in groups.items():
        row = options.get(map_id)
        if row is None:  # deleted between the two reads
            continue
        serving = map_serving(
            map_id,
            row.max_keypoints,
            row.max_side,
            described,
            localizer,
            models_dir,
            features,
            row.feature_preset,
        )
        if not serving.servable:
            count = sum(n for _, _, n in described)
            found.append(UnservableMap(map_id, row.name, count, serving))
    found.sort(key=lambda m: (-m.image_count, m.name))
    return len(found), found[:limit]
