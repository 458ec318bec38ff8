"""``slloc self-evaluate``: start a map's self-evaluation on a running server (or read its
latest), wait for it with progress on stderr, and print what it measured as a Markdown table."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from typing import Any

import httpx

from services.self_evaluation.summary import THRESHOLDS, recall_key

POLL_S = 2.0


def find_map_id(client: httpx.Client, name_or_id: str) -> str:
    """The id of the map with this id or name.

    Raises:
        ValueError: no such map.
    """
    offset = 0
    while True:
        page = client.get("/v1/maps", params={"offset": offset, "limit": 1000})
        page.raise_for_status()
        body = page.json()
        for item in body["items"]:
            if name_or_id in (item["id"], item["name"]):
                return str(item["id"])
        offset += len(body["items"])
        if not body["items"] or offset >= body["total"]:
            raise ValueError(f"no map named {name_or_id!r}")


def _checked(response: httpx.Response) -> dict[str, Any]:
    if response.is_error:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        raise ValueError(
            f"{response.request.method} {response.request.url.path}: "
            f"{response.status_code} {detail}"
        )
    body: dict[str, Any] = response.json()
    return body


def _centimetres(value: float | None) -> str:
    return "–" if value is None else f"{value * 100:.1f}"


def _share(value: float | None) -> str:
    return "–" if value is None else f"{value * 100:.0f} %"


def markdown(evaluation: dict[str, Any]) -> str:
    """The evaluation's figures per configuration as a Markdown table."""
    result = evaluation["result"]
    keys = [recall_key(m, d) for m, d in THRESHOLDS]
    header = (
        "| configuration | held out | localized | "
        + " | ".join(f"({m * 100:g} cm, {d:g}°)" for m, d in THRESHOLDS)
        + " | median cm | p90 cm | median ° | conf > 0.8 precision / recall | p50 ms | took s |"
    )
    lines = [header, "|" + "---|" * (len(keys) + 10)]
    for name, s in result["configurations"].items():
        confidence = s["confidence"]
        latency = s["latency_ms"]["median"]
        rotation = s["rotation_error_deg"]["median"]
        lines.append(
            f"| {name}{' (recommended)' if name == result['recommended'] else ''} "
            f"| {s['held_out']} | {s['localized']} | "
            + " | ".join(_share(s["recall"][k]) for k in keys)
            + f" | {_centimetres(s['position_error_m']['median'])}"
            f" | {_centimetres(s['position_error_m']['p90'])}"
            f" | {'–' if rotation is None else f'{rotation:.2f}'}"
            f" | {_share(confidence['precision'])} / {_share(confidence['recall'])}"
            f" | {'–' if latency is None else f'{latency:.0f}'} | {s['duration_s']:.0f} |"
        )
    lines.append("")
    lines.append(
        f"recommended: {result['recommended']} (server: {result['served']}; "
        f"map of {result['references']} references)"
    )
    return "\n".join(lines) + "\n"


def self_evaluate_main(args: argparse.Namespace) -> int:
    logging.getLogger("httpx").setLevel(logging.WARNING)  # a line per poll would drown progress
    headers = {"X-API-Key": args.api_key} if args.api_key else {}
    with httpx.Client(base_url=args.url.rstrip("/"), headers=headers, timeout=60.0) as client:
        try:
            map_id = find_map_id(client, args.map)
            url = f"/v1/maps/{map_id}/evaluations"
            if args.latest:
                done = [
                    e
                    for e in _checked(client.get(url, params={"limit": 100}))["items"]
                    if e["state"] == "done"
                ]
                if not done:
                    raise ValueError(f"map {args.map} has no finished self-evaluation")
                evaluation = _checked(client.get(f"{url}/{done[0]['id']}"))
            else:
                body = {
                    key: value
                    for key, value in (
                        ("configurations", args.configurations and args.configurations.split(",")),
                        ("sample_size", args.sample_size),
                        ("holdout_radius_m", args.holdout_radius),
                        ("top_k", args.top_k),
                    )
                    if value is not None
                }
                started = _checked(client.post(url, json=body))
                evaluation = _wait(client, f"{url}/{started['id']}", args.timeout)
        except (ValueError, httpx.HTTPError) as exc:
            print(f"slloc self-evaluate: {exc}", file=sys.stderr)
            return 2
    if args.json is not None:
        args.json.write_text(json.dumps(evaluation, indent=2))
    if evaluation["state"] != "done":
        print(
            f"slloc self-evaluate: evaluation {evaluation['id']} {evaluation['state']}: "
            f"{evaluation['error']}",
            file=sys.stderr,
        )
        return 1
    print(markdown(evaluation), end="")
    return 0


def _wait(client: httpx.Client, location: str, timeout_s: float) -> dict[str, Any]:
    """The evaluation once it has ended, its progress on stderr meanwhile.

    Raises:
        ValueError: it did not end within ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    shown = None
    while True:
        evaluation = _checked(client.get(location))
        progress = evaluation["progress"]
        if (evaluation["state"], progress["done"]) != shown:
            shown = (evaluation["state"], progress["done"])
            print(
                f"{evaluation['state']}: {progress['done']}/{progress['total']} held out",
                file=sys.stderr,
                flush=True,
            )
        if evaluation["state"] not in ("queued", "running"):
            return evaluation
        if time.monotonic() > deadline:
            raise ValueError(f"evaluation {evaluation['id']} still {evaluation['state']}")
        time.sleep(POLL_S)
