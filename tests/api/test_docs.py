"""The interactive API docs work offline: every asset comes from the service itself."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

ASSET = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url\(\s*["']?([^"')]+)""")


def _asset_urls(html: str) -> list[str]:
    return [a or b for a, b in ASSET.findall(html)]


@pytest.mark.parametrize("path", ["/docs", "/redoc"])
def test_docs_reference_only_the_service(client: TestClient, path: str) -> None:
    page = client.get(path)
    assert page.status_code == 200
    urls = _asset_urls(page.text)
    assert urls, f"{path} loads no script or stylesheet"
    external = [u for u in urls if re.match(r"^(?:[a-z]+:)?//", u)]
    assert external == [], f"{path} loads assets from other hosts: {external}"
    assert "fonts.googleapis" not in page.text and "cdn." not in page.text
    for url in urls:
        asset = client.get(url)
        assert asset.status_code == 200, url
        assert len(asset.content) > 0, url
