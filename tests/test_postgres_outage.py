"""A real PostgreSQL server stopped and started again under load: a ``slloc serve`` process
with 8 clients creating maps, adding references, listing maps and localizing never answers
500; while the database is down the routes that need it answer 503 database-unavailable
with Retry-After and /readyz is not ready; /readyz is ready again within 10 s of the
database's return, without a restart; and every write answered 2xx is in the database
afterwards.

The server is a private cluster (initdb into a temporary folder, its own port and socket
folder, stopped and started with pg_ctl in fast mode), never the shared one on 5432. As
root, the cluster runs as the ``postgres`` user (initdb refuses root), as
scripts/postgres.sh's ``pg_ctlcluster`` does. Skipped where no PostgreSQL binaries are
installed."""

from __future__ import annotations

import contextlib
import glob
import json
import os
import pwd
import shutil
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, select

from db.models import Map, ReferenceImage
from tests.conftest import create_map, image_metadata
from tools.evaluation.server import LocalServer, free_port
from tools.synthetic.scene import SyntheticView, encode_png

PROBLEM = "application/problem+json"
CLIENTS = 8
OUTAGE_S = 5.0  # how long the database stays down once pg_ctl stop returned
READY_WITHIN_S = 10.0
AFTER_S = 1.0  # load after /readyz is ready again
MAP_SIZE = 8  # an adder starts a new map after this many references (no vocabulary training)


def _bin_dir() -> Path | None:
    """The newest installed PostgreSQL's binaries (initdb and pg_ctl), or those on PATH."""
    found = sorted(
        glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"),
        key=lambda p: int(Path(p).parts[-3]) if Path(p).parts[-3].isdigit() else 0,
    )
    for pg_ctl in [*reversed(found), shutil.which("pg_ctl")]:
        if pg_ctl and (Path(pg_ctl).parent / "initdb").exists():
            return Path(pg_ctl).parent
    return None


class PrivatePostgres:
    """A throwaway PostgreSQL cluster on 127.0.0.1 and a free port, trust authentication."""

    def __init__(self, bin_dir: Path) -> None:
        self.bin_dir = bin_dir
        self.root = Path(tempfile.mkdtemp(prefix="slloc-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.url = f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"
        self._as: list[str] = []
        if os.geteuid() == 0:
            owner = pwd.getpwnam("postgres")
            os.chown(self.root, owner.pw_uid, owner.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"]
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "--no-sync")

    def _run(self, tool: str, *args: str) -> None:
        subprocess.run(
            [*self._as, str(self.bin_dir / tool), *args],
            check=True,
            capture_output=True,
            timeout=60,
        )

    def start(self) -> None:
        options = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1"
        log = str(self.root / "postgres.log")
        self._run(
            "pg_ctl", "-D", str(self.data), "-l", log, "-o", options, "-w", "-t", "30", "start"
        )

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "30", "stop")

    def close(self) -> None:
        if (self.data / "postmaster.pid").exists():
            with contextlib.suppress(subprocess.SubprocessError):
                self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture
def postgres() -> Iterator[PrivatePostgres]:
    bin_dir = _bin_dir()
    if bin_dir is None:
        pytest.skip("no PostgreSQL binaries (initdb, pg_ctl) in /usr/lib/postgresql/*/bin or PATH")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root without a postgres user to run the cluster as")
    cluster = PrivatePostgres(bin_dir)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.close()


@dataclass(frozen=True)
class Answer:
    op: str
    sent: float
    received: float
    status: int
    content_type: str
    retry_after: str | None
    problem_type: str | None
    written_id: str | None  # the map or reference a 2xx write created


def _answer(op: str, sent: float, response: httpx.Response) -> Answer:
    problem_type = None
    if response.headers.get("content-type") == PROBLEM:
        problem_type = str(response.json().get("type", ""))
    written = None
    if op in ("create_map", "add_image") and response.status_code == 201:
        written = str(response.json()["id"])
    return Answer(
        op,
        sent,
        time.monotonic(),
        response.status_code,
        response.headers.get("content-type", ""),
        response.headers.get("retry-after"),
        problem_type,
        written,
    )


class Load:
    """``CLIENTS`` threads, each with its own connection, repeating one kind of request until
    stopped: 2 create maps, 2 add references, 2 list maps, 2 localize."""

    def __init__(
        self, url: str, map_id: str, references: list[SyntheticView], queries: list[SyntheticView]
    ) -> None:
        self.url, self.map_id = url, map_id
        self.references, self.queries = references, queries
        self.answers: list[Answer] = []
        self.failures: list[str] = []  # transport errors: no answer at all
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._filling: dict[int, tuple[str, int]] = {}
        roles: list[Callable[[httpx.Client, int], tuple[str, httpx.Response]]] = [
            self._create_map,
            self._add_image,
            self._list_maps,
            self._localize,
        ]
        self._threads = [
            threading.Thread(target=self._run, args=(roles[i % len(roles)], i), daemon=True)
            for i in range(CLIENTS)
        ]

    def __enter__(self) -> Load:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=120)

    def count(self, op: str, status: int, after: float = 0.0) -> int:
        with self._lock:
            return sum(a.op == op and a.status == status and a.sent >= after for a in self.answers)

    def _run(self, role: Callable[[httpx.Client, int], tuple[str, httpx.Response]], i: int) -> None:
        with httpx.Client(base_url=self.url, timeout=60) as client:
            n = 0
            while not self._stop.is_set():
                sent = time.monotonic()
                try:
                    op, response = role(client, n)
                    answer = _answer(op, sent, response)
                except httpx.HTTPError as exc:
                    with self._lock:
                        self.failures.append(f"client {i}: {exc!r}")
                    continue
                with self._lock:
                    self.answers.append(answer)
                n += 1

    def _create_map(self, client: httpx.Client, n: int) -> tuple[str, httpx.Response]:
        return "create_map", client.post("/v1/maps", json={"name": f"m-{uuid.uuid4().hex}"})

    def _add_image(self, client: httpx.Client, n: int) -> tuple[str, httpx.Response]:
        # the map this adder fills and its size so far
        state = self._filling.get(threading.get_ident())
        if state is None or state[1] >= MAP_SIZE:
            created = client.post("/v1/maps", json={"name": f"adds-{uuid.uuid4().hex}"})
            if created.status_code != 201:
                return "create_map", created
            state = self._filling[threading.get_ident()] = (created.json()["id"], 0)
        view = self.references[n % len(self.references)]
        response = client.post(
            f"/v1/maps/{state[0]}/images",
            files={"image": (view.name, encode_png(view.image), "image/png")},
            data={"metadata": json.dumps(image_metadata(view, f"{view.name}-{n}"))},
        )
        if response.status_code == 201:
            self._filling[threading.get_ident()] = (state[0], state[1] + 1)
        return "add_image", response

    def _list_maps(self, client: httpx.Client, n: int) -> tuple[str, httpx.Response]:
        if n % 2:
            return "get_map", client.get(f"/v1/maps/{self.map_id}")
        return "list_maps", client.get("/v1/maps", params={"limit": 5})

    def _localize(self, client: httpx.Client, n: int) -> tuple[str, httpx.Response]:
        view = self.queries[n % len(self.queries)]
        return "localize", client.post(
            f"/v1/maps/{self.map_id}/localize",
            files={"image": (view.name, encode_png(view.image), "image/png")},
            data={"params": json.dumps({"top_k": 6})},
        )


def _poll(condition: Callable[[], bool], timeout_s: float, every_s: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(every_s)
    return condition()


def _ready(client: httpx.Client) -> bool:
    return client.get("/readyz").is_success


def test_postgres_stopped_and_started_under_load(
    postgres: PrivatePostgres,
    tmp_path: Path,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    env = {
        "SLLOC_DATABASE_URL": postgres.url,
        "SLLOC_DATA_DIR": str(tmp_path / "data"),
        "SLLOC_FEATURES": "sift",
        "SLLOC_MODELS_DIR": "/nonexistent-models",
    }
    with (
        LocalServer(env, log_level="info") as server,
        httpx.Client(base_url=server.url, timeout=30) as probe,
    ):
        map_id = create_map(probe)  # type: ignore[arg-type]
        for view in reference_views[:6]:
            response = probe.post(
                f"/v1/maps/{map_id}/images",
                files={"image": (view.name, encode_png(view.image), "image/png")},
                data={"metadata": json.dumps(image_metadata(view))},
            )
            assert response.status_code == 201, response.text
        assert _ready(probe)

        with Load(server.url, map_id, reference_views[6:], query_views) as load:
            # every kind of request answered once with the database up
            assert _poll(
                lambda: all(
                    load.count(op, 200) + load.count(op, 201)
                    for op in ("create_map", "add_image", "list_maps", "localize")
                ),
                60,
            ), load.answers[-20:]

            stopping = time.monotonic()
            postgres.stop()
            down = time.monotonic()
            assert _poll(lambda: not _ready(probe), READY_WITHIN_S)
            not_ready_after_s = time.monotonic() - down
            # down for OUTAGE_S; /readyz answers not ready all along
            readiness: list[httpx.Response] = []
            while time.monotonic() < down + OUTAGE_S:
                readiness.append(probe.get("/readyz"))
                time.sleep(0.2)
            scraped_down = probe.get("/metrics")
            starting = time.monotonic()
            postgres.start()
            up = time.monotonic()
            assert _poll(lambda: _ready(probe), READY_WITHIN_S), server.log_text()[-4000:]
            ready_after_s = time.monotonic() - up
            # writes succeed again, on the same process
            assert _poll(
                lambda: all(
                    load.count(op, 201, after=up + ready_after_s) >= 2
                    for op in ("create_map", "add_image")
                ),
                30,
            ), load.answers[-20:]
            time.sleep(AFTER_S)  # more load after the recovery, not a proof of anything
            scraped_up = probe.get("/metrics")
        assert server.process.poll() is None  # never restarted
        log = server.log_text()

    answers = load.answers
    assert not load.failures, load.failures[:5]
    assert not [a for a in answers if a.status >= 500 and a.status != 503], [
        a for a in answers if a.status >= 500 and a.status != 503
    ][:5]
    assert "unhandled error" not in log, log[-4000:]

    # every 503 is a problem document with Retry-After; the database's own
    unavailable = [a for a in answers if a.status == 503]
    for a in unavailable:
        assert a.content_type == PROBLEM and a.retry_after and int(a.retry_after) > 0, a
        assert a.problem_type and a.problem_type.endswith("/database-unavailable"), a
    # a request sent and answered while the database was down is 503 on every route
    during = [a for a in answers if a.sent >= down and a.received <= starting]
    assert {a.op for a in during} >= {"create_map", "add_image", "list_maps", "localize"}, {
        a.op for a in during
    }
    assert all(a.status == 503 for a in during), [a for a in during if a.status != 503][:5]
    # with the database up, every request succeeds
    outside = [a for a in answers if a.received < stopping or a.sent > up + ready_after_s]
    assert all(a.status in (200, 201) for a in outside), [
        a for a in outside if a.status not in (200, 201)
    ][:5]
    assert all(r.status_code == 503 and r.headers["retry-after"] for r in readiness)
    assert all("database" in r.text for r in readiness)
    # /metrics answers through the outage and says whether the database answered it
    assert scraped_down.status_code == 200 and scraped_up.status_code == 200
    assert "\nslloc_database_up 0.0\n" in scraped_down.text, scraped_down.text[-2000:]
    assert "\nslloc_database_up 1.0\n" in scraped_up.text

    # no acknowledged write lost
    maps = {a.written_id for a in answers if a.op == "create_map" and a.written_id}
    images = {a.written_id for a in answers if a.op == "add_image" and a.written_id}
    engine = create_engine(postgres.url)
    try:
        with engine.connect() as conn:
            stored_maps = set(conn.scalars(select(Map.id)))
            stored_images = set(conn.scalars(select(ReferenceImage.id)))
    finally:
        engine.dispose()
    assert maps - stored_maps == set() and images - stored_images == set()

    print(
        f"\noutage {starting - down:.1f} s (stop took {down - stopping:.2f} s); "
        f"{len(answers)} answers, {len(unavailable)} 503 "
        f"({len(during)} sent and answered while down), 0 500; "
        f"/readyz not ready {not_ready_after_s:.2f} s after the stop, "
        f"{len(readiness)} polls 503 while down, ready {ready_after_s:.2f} s after the start; "
        f"{len(maps)} maps and {len(images)} references acknowledged, all stored"
    )
