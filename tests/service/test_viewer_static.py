"""The viewer's static files as the service serves them (no browser needed; see test_viewer_browser.py)."""

from __future__ import annotations

import re

from helpers import make_client
from narf_service.app import VIEWER_DIR
from narf_service.settings import Settings

IMPORT = re.compile(r"""^import .*? from "\./([\w.]+)";$|^import \* as \w+ from "\./([\w.]+)";$""", re.M)


def test_the_page_and_every_module_it_imports_are_served(client) -> None:
    redirect = client.get("/viewer", follow_redirects=False)
    assert redirect.status_code == 307 and redirect.headers["location"].endswith("/viewer/")
    page = client.get("/viewer/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<script type="module" src="main.js">' in page.text and 'href="viewer.css"' in page.text
    seen, todo = set(), ["main.js"]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        reply = client.get(f"/viewer/{name}")
        assert reply.status_code == 200, name
        assert "javascript" in reply.headers["content-type"], (name, reply.headers["content-type"])
        todo += [a or b for a, b in IMPORT.findall(reply.text)]
    assert seen == {p.name for p in VIEWER_DIR.glob("*.js")}, "every shipped module is used, every used one shipped"
    assert client.get("/viewer/viewer.css").headers["content-type"].startswith("text/css")


def test_the_viewer_fetches_nothing_from_the_network_and_only_the_public_api() -> None:
    text = "\n".join(p.read_text() for p in VIEWER_DIR.iterdir() if p.suffix in (".html", ".css", ".js"))
    assert not re.search(r"https?://(?!www\.w3\.org/2000/svg)", text), "no CDN or other host: it must work offline"
    assert set(re.findall(r'"(/v1/[a-z]+)', text)) == {"/v1/models", "/v1/render", "/v1/estimate"}


def test_the_page_is_private_with_a_token_unless_listed_public(tmp_path, toy_engine, toy_model) -> None:
    def settings(**kwargs) -> Settings:
        return Settings(models_dir=tmp_path, workers=1, queue_size=2, torch_threads=1, token="s3cret", **kwargs)

    with make_client(settings(), toy_engine, toy_model) as c:
        assert c.get("/viewer/").status_code == 401
    with make_client(settings(public_routes=["/healthz", "/readyz", "/viewer"]), toy_engine, toy_model) as c:
        assert c.get("/viewer/").status_code == 200 and c.get("/viewer/main.js").status_code == 200
        assert c.get("/v1/models").status_code == 401  # the API still needs the token the page sends
        assert c.get("/v1/models", headers={"Authorization": "Bearer s3cret"}).status_code == 200
