"""The first localize after a map crosses the VLAD threshold, against the others.

On a fresh SQLite map of the demo scene (``slloc synth``), through the service's code path
in process: MIN_IMAGES - 1 references are added and queries localized (the steady state
before), then the reference that makes the vocabulary due is added and a query localized at
once (the first after crossing: training runs in the background meanwhile), then queries are
localized again once the vocabulary is published. Prints wall times per request, their
medians, the ratio first / median before, and the training time.

Run from the repository root (after ``slloc synth --out demo``):
``.venv/bin/python -m tools.benchmarks.vocabulary [--demo demo] [--features sift] [--rounds 5]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from services.retrieval.policy import MIN_IMAGES


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", type=Path, default=Path("demo"))
    parser.add_argument("--features", default="auto")
    parser.add_argument("--rounds", type=int, default=5, help="localizes before and after")
    args = parser.parse_args()
    references = sorted((args.demo / "references").glob("*.json"))
    queries = sorted((args.demo / "queries").glob("*.png"))
    if len(references) < MIN_IMAGES or not queries:
        parser.error(f"{args.demo} needs {MIN_IMAGES}+ references and a query (slloc synth)")
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(database_url=f"sqlite:///{tmp}/bench.db", features=args.features)
        with TestClient(create_app(settings)) as client:
            map_id = client.post("/v1/maps", json={"name": "bench"}).json()["id"]

            def add(meta: Path) -> None:
                response = client.post(
                    f"/v1/maps/{map_id}/images",
                    files={"image": meta.with_suffix(".png").read_bytes()},
                    data={"metadata": meta.read_text()},
                )
                response.raise_for_status()

            def localize(i: int) -> float:
                query = queries[i % len(queries)]
                params = query.with_name(query.stem + ".params.json").read_text()
                start = time.perf_counter()
                response = client.post(
                    f"/v1/maps/{map_id}/localize",
                    files={"image": query.read_bytes()},
                    data={"params": params},
                )
                wall = (time.perf_counter() - start) * 1000
                assert response.json()["localized"], response.text
                return wall

            for meta in references[: MIN_IMAGES - 1]:
                add(meta)
            localize(0)  # warm-up: sessions, caches
            before = [localize(i) for i in range(args.rounds)]
            add(references[MIN_IMAGES - 1])
            first = localize(0)
            trainer = client.app.state.vocabulary_trainer  # type: ignore[attr-defined]
            start = time.perf_counter()
            trainer.wait(600)
            waited = time.perf_counter() - start
            after = [localize(i) for i in range(args.rounds)]
            vocabulary = client.get(f"/v1/maps/{map_id}").json()
    median_before = statistics.median(before)
    print(json.dumps({"features": args.features, "map": vocabulary["image_count"]}))
    print(f"before crossing (thumbnail retrieval), ms: {[round(t) for t in before]}")
    print(f"first after crossing, ms: {first:.0f} (trainer still busy for {waited:.1f} s after)")
    print(f"after publishing (VLAD retrieval), ms: {[round(t) for t in after]}")
    print(
        f"median before {median_before:.0f} ms, after {statistics.median(after):.0f} ms; "
        f"first / median before = {first / median_before:.2f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
