"""Access control against the real server (``server.auth``): bearer tokens on HTTP and
WebSocket, per-scene allow lists, CORS and the WebSocket Origin check, per-token quotas, tokens
from a file and from the environment, and the headless client with a token."""

from __future__ import annotations

import asyncio
import json
import logging

import httpx
import pytest
import websockets
from websockets.asyncio.client import connect

import pvs_cli
from client.session import Session, SessionError
from protocol.auth import token_subprotocols
from protocol.codes import CloseCode
from protocol.messages import Hello, dump_message, parse_server_message
from server.settings import Settings
from server.tokens import read_tokens_file
from tests.conftest import make_tiny_scene, serving, wait_for

#: Tokens of the protected server: one with every scene (as PVS_TOKENS gives), one limited
#: to "tiny", one limited to "tiny" with small quotas (its own, so other tests never use them).
ALL = "all-scenes-token-0123456789"
TINY_ONLY = "tiny-only-token-0123456789"
QUOTA = "quota-token-0123456789abcd"
ORIGIN = "https://viewer.example.org"
TIMEOUT = 60.0


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


def hello(scene: str = "tiny") -> str:
    return dump_message(Hello(scene=scene, core="test_near", params={"radius": 3.0},
                              prefetch=False))


@pytest.fixture(scope="module")
def tokens_file(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("auth") / "tokens.json"
    path.write_text(json.dumps({"tokens": {
        TINY_ONLY: {"name": "tiny-only", "scenes": ["tiny"]},
        QUOTA: {"name": "quota", "scenes": ["tiny"], "max_sessions": 1, "pvs_per_minute": 2},
    }}))
    return str(path)


@pytest.fixture(scope="module")
def protected(settings, registered_test_cores, tokens_file):
    """The real server with tokens (a file and an environment-style list) and one CORS
    origin; yields (base URL, app)."""
    with serving(settings, scenes={"tiny": make_tiny_scene(), "tiny2": make_tiny_scene()},
                 tokens=[ALL], tokens_file=tokens_file, cors_origins=[ORIGIN]) as served:
        yield served


@pytest.fixture(scope="module")
def url(protected) -> str:
    return protected[0]


@pytest.fixture(scope="module")
def ws_url(url) -> str:
    return url.replace("http://", "ws://") + "/ws"


async def refused(ws_url: str, *, first: str | None = None, **kw) -> tuple[list, int | None]:
    """Open a WebSocket (``kw`` to ``connect``), send ``first``, read until the close: the
    messages and the close code."""
    out = []
    async with connect(ws_url, open_timeout=TIMEOUT, **kw) as ws:
        if first is not None:
            try:
                await ws.send(first)
            except websockets.ConnectionClosed:
                pass  # refused before the hello: what came first is still to be read
        try:
            async for raw in ws:
                out.append(parse_server_message(raw))
        except websockets.ConnectionClosed:
            pass
        return out, ws.close_code


async def welcomed(ws_url: str, **kw):
    """Open a WebSocket, send hello; the first answer and the connection (left open)."""
    ws = await connect(ws_url, open_timeout=TIMEOUT, **kw)
    await ws.send(hello())
    return parse_server_message(await asyncio.wait_for(ws.recv(), TIMEOUT)), ws


# --------------------------------------------------------------------------- HTTP
def test_no_token_is_401_before_any_parsing_or_routing(url):
    for method, path, body in [("GET", "/scenes", None), ("GET", "/cores", None),
                               ("GET", "/metrics", None), ("GET", "/scenes/tiny/cells/0/pvs",
                                                           None),
                               ("POST", "/scenes/tiny/pvs", b"{not json"),
                               ("GET", "/no/such/route", None), ("OPTIONS", "/scenes", None)]:
        r = httpx.request(method, url + path, content=body, timeout=TIMEOUT)
        assert r.status_code == 401, (method, path, r.text)
        assert r.headers["www-authenticate"] == 'Bearer realm="pvs"'
        err = r.json()["error"]
        assert err["code"] == "unauthorized" and "Authorization: Bearer" in err["message"]


def test_bad_tokens_are_401_invalid_token(url):
    for value in [f"Bearer {ALL}x", f"Bearer {ALL[:-1]}", f"bearer  {ALL[::-1]}",
                  f"Basic {ALL}", "Bearer", f"Token {ALL}", ALL,
                  f"Bearer {ALL} extra", "Bearer short"]:
        r = httpx.get(url + "/scenes", headers={"Authorization": value}, timeout=TIMEOUT)
        assert r.status_code == 401, value
        assert r.headers["www-authenticate"] == 'Bearer realm="pvs", error="invalid_token"'
        assert r.json()["error"] == {"code": "unauthorized",
                                     "message": "the bearer token is not valid"}
    # Two Authorization headers, one of them good: refused, not guessed at.
    r = httpx.get(url + "/scenes", headers=[("Authorization", f"Bearer {ALL}"),
                                            ("Authorization", f"Bearer {ALL}")])
    assert r.status_code == 401


def test_good_token_is_answered(url):
    r = httpx.get(url + "/scenes", headers=bearer(ALL), timeout=TIMEOUT)
    assert r.status_code == 200
    assert {"tiny", "tiny2"} <= {s["name"] for s in r.json()["scenes"]}
    # The scheme is case-insensitive (RFC 7235).
    r = httpx.get(url + "/scenes/tiny/cells/1/pvs", params={"core": "test_near"},
                  headers={"Authorization": f"bEaReR {ALL}"}, timeout=TIMEOUT)
    assert r.status_code == 200 and r.json()["cell"] == 1
    r = httpx.post(url + "/scenes/tiny2/pvs", headers=bearer(ALL), timeout=TIMEOUT,
                   json={"box": [[1, 1, 1], [2, 2, 2]], "core": "test_near"})
    assert r.status_code == 200 and r.json()["count"] > 0
    assert httpx.get(url + "/metrics", headers=bearer(ALL), timeout=TIMEOUT).status_code == 200


def test_health_and_the_api_description_stay_open(url):
    # A refusal of its own: the other tests' may have run in another process.
    assert httpx.get(url + "/scenes", timeout=TIMEOUT).status_code == 401
    r = httpx.get(url + "/health", timeout=TIMEOUT)
    assert r.status_code == 200 and r.json()["status"] == "ok"
    assert r.json()["stream"]["access_unauthorized"] > 0  # refusals are counted
    assert httpx.get(url + "/docs", timeout=TIMEOUT).status_code == 200
    spec = httpx.get(url + "/openapi.json", timeout=TIMEOUT).json()
    assert spec["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    scenes = spec["paths"]["/scenes"]["get"]
    assert scenes["security"] == [{"bearer": []}] and "401" in scenes["responses"]
    assert "403" in spec["paths"]["/scenes/{scene}/pvs"]["post"]["responses"]
    assert "403" not in scenes["responses"]
    assert "security" not in spec["paths"]["/health"]["get"]


def test_the_viewer_page_and_its_files_are_open_and_nothing_else(url):
    """A browser opening the viewer sends no token: the page and its modules answer without
    one; the data they fetch, and whatever only looks like the viewer, still need one."""
    page = httpx.get(url + "/viewer/", timeout=TIMEOUT)
    assert page.status_code == 200 and "<title>PVS viewer</title>" in page.text
    assert httpx.get(url + "/viewer?scene=tiny", timeout=TIMEOUT).status_code == 307
    for path in ("/viewer/main.js", "/viewer/token.js", "/viewer/index.html"):
        r = httpx.get(url + path, timeout=TIMEOUT)
        assert r.status_code == 200, path
    # three.js's build, or the JSON 404 saying how to install it: open either way.
    assert httpx.get(url + "/viewer/vendor/three.module.js",
                     timeout=TIMEOUT).status_code in (200, 404)
    assert httpx.get(url + "/scenes", timeout=TIMEOUT).status_code == 401
    # Traversal (percent-encoded, as a client that does not normalise sends it), look-alike
    # prefixes, hidden files, other file types and other methods: not opened.
    for raw in ("/viewer/%2e%2e/scenes", "/viewer/..%2fscenes", "/viewer/x/%2E%2E/%2e%2e/scenes",
                "/viewer//scenes", "/viewerx/main.js", "/viewer.js", "/viewer/.hidden.js",
                "/viewer/scenes", "/viewer/cells.json", "/viewer/main.js/scenes"):
        with httpx.Client(timeout=TIMEOUT) as http:
            r = http.send(http.build_request("GET", url + raw))
        assert r.status_code == 401, (raw, r.status_code)
    r = httpx.post(url + "/viewer/main.js", timeout=TIMEOUT)
    assert r.status_code == 401
    # A token is still welcome there (the page's own data requests carry one).
    assert httpx.get(url + "/viewer/main.js", headers=bearer("not a token"),
                     timeout=TIMEOUT).status_code == 200


def test_scene_allow_list_is_403_and_filters_the_listing(url):
    h = bearer(TINY_ONLY)
    assert httpx.get(url + "/scenes/tiny", headers=h, timeout=TIMEOUT).status_code == 200
    listing = httpx.get(url + "/scenes", headers=h, timeout=TIMEOUT).json()["scenes"]
    assert [s["name"] for s in listing] == ["tiny"]
    for method, path, kw in [
        ("GET", "/scenes/tiny2", {}),
        ("GET", "/scenes/tiny2/cells", {}),
        ("GET", "/scenes/tiny2/cells/0/pvs", {}),
        ("POST", "/scenes/tiny2/pvs", {"json": {"box": [[1, 1, 1], [2, 2, 2]]}}),
        ("GET", "/scenes/no_such_scene", {}),  # 403, not 404: nothing about other scenes
        ("GET", "/cores", {"params": {"scene": "tiny2"}}),
        ("GET", "/cores?sc%65ne=tiny2", {}),  # as the router decodes it
        ("GET", "/cores", {"params": [("scene", "tiny"), ("scene", "tiny2")]}),
    ]:
        r = httpx.request(method, url + path, headers=h, timeout=TIMEOUT, **kw)
        assert r.status_code == 403, (method, path, kw, r.text)
        assert r.json()["error"]["code"] == "forbidden"
        assert "insufficient_scope" in r.headers["www-authenticate"]
    r = httpx.get(url + "/cores", params={"scene": "tiny"}, headers=h, timeout=TIMEOUT)
    assert r.status_code == 200 and "fit" in r.json()


# --------------------------------------------------------------------------- WebSocket
def test_ws_without_a_valid_token_closes_with_4401(ws_url):
    for kw in [{}, {"additional_headers": bearer(ALL + "x")},
               {"additional_headers": {"Authorization": "Basic abc"}},
               {"subprotocols": ["pvs", "pvs.bearer.not-the-token-0123456"]},
               {"subprotocols": ["pvs", "pvs.bearer." + ALL, "pvs.bearer." + TINY_ONLY]}]:
        msgs, code = run(refused(ws_url, first=hello(), **kw))
        assert code == CloseCode.UNAUTHORIZED == 4401, kw
        assert [(m.type, m.code, m.fatal) for m in msgs] == [("error", "unauthorized", True)]
    # Nothing sent at all: refused the same way, at once (the hello is never awaited).
    msgs, code = run(refused(ws_url))
    assert code == 4401 and msgs[0].code == "unauthorized"


def test_ws_with_a_token_by_header_or_subprotocol_is_welcomed(ws_url, url):
    async def go():
        first, ws = await welcomed(ws_url, additional_headers=bearer(ALL))
        assert first.type == "welcome" and ws.subprotocol is None
        await ws.close()
        # The browser way: the token as a subprotocol beside "pvs", which the server selects.
        first, ws = await welcomed(ws_url, subprotocols=token_subprotocols(TINY_ONLY))
        assert first.type == "welcome" and ws.subprotocol == "pvs"
        await ws.close()
        # The headless client.
        s = await Session.connect(url, "tiny", "test_near", {"radius": 3.0}, token=ALL)
        assert s.welcome.scene.name == "tiny"
        await s.close()
        with pytest.raises(SessionError) as exc:
            await Session.connect(url, "tiny", "test_near", {"radius": 3.0})
        assert (exc.value.code, exc.value.close_code) == ("unauthorized", 4401)

    run(go())


def test_ws_scene_outside_the_allow_list_is_refused_after_hello(ws_url):
    for scene in ("tiny2", "no_such_scene"):
        msgs, code = run(refused(ws_url, first=hello(scene),
                                 additional_headers=bearer(TINY_ONLY)))
        assert code == CloseCode.FORBIDDEN == 4403
        assert [(m.type, m.code) for m in msgs] == [("error", "forbidden")]
        assert "tiny-only" in msgs[0].message and TINY_ONLY not in msgs[0].message


# --------------------------------------------------------------------------- CORS, Origin
def test_cors_preflight_answers_allowed_origins_only(url, settings):
    ask = {"Access-Control-Request-Method": "POST",
           "Access-Control-Request-Headers": "authorization, content-type"}
    r = httpx.options(url + "/scenes/tiny/pvs", headers={"Origin": ORIGIN, **ask})
    assert r.status_code == 200
    assert r.headers["access-control-allow-origin"] == ORIGIN
    assert "authorization" in r.headers["access-control-allow-headers"].lower()
    assert "POST" in r.headers["access-control-allow-methods"]
    r = httpx.options(url + "/scenes/tiny/pvs", headers={"Origin": "https://evil.example",
                                                          **ask})
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers
    # A page of the allowed origin can read its refusals and the PVS headers.
    r = httpx.get(url + "/scenes", headers={"Origin": ORIGIN})
    assert r.status_code == 401 and r.headers["access-control-allow-origin"] == ORIGIN
    r = httpx.get(url + "/scenes/tiny/cells/1/pvs", params={"core": "test_near"},
                  headers={"Origin": ORIGIN, "Accept": "application/octet-stream", **bearer(ALL)})
    assert r.status_code == 200 and "X-PVS-Count" in r.headers["access-control-expose-headers"]
    # Without origins configured, nothing changes: a preflight is a 405, as before.
    with serving(settings) as (plain, _):
        r = httpx.options(plain + "/scenes", headers={"Origin": ORIGIN, **ask})
        assert r.status_code == 405 and "access-control-allow-origin" not in r.headers


def test_ws_from_another_origin_is_refused_before_the_upgrade(ws_url):
    with pytest.raises(websockets.InvalidStatus) as exc:
        run(welcomed(ws_url, origin="https://evil.example", additional_headers=bearer(ALL)))
    response = exc.value.response
    assert response.status_code == 403
    assert json.loads(response.body)["error"]["code"] == "forbidden"

    async def go():
        first, ws = await welcomed(ws_url, origin=ORIGIN, additional_headers=bearer(ALL))
        await ws.close()
        return first

    assert run(go()).type == "welcome"


# --------------------------------------------------------------------------- quotas
def test_pvs_quota_per_token_is_429_with_retry_after(url):
    h = bearer(QUOTA)
    path = url + "/scenes/tiny/cells/0/pvs"
    for _ in range(2):
        assert httpx.get(path, params={"core": "test_near"}, headers=h).status_code == 200
    r = httpx.get(path, params={"core": "test_near"}, headers=h)
    assert r.status_code == 429
    assert 1 <= int(r.headers["retry-after"]) <= 60
    err = r.json()["error"]
    assert (err["code"], err["limit"], err["value"]) == ("over_quota", "pvs_per_minute", 2)
    # Only PVS requests count, and only this token's.
    assert httpx.get(url + "/scenes/tiny", headers=h).status_code == 200
    assert httpx.get(path, params={"core": "test_near"}, headers=bearer(TINY_ONLY)).status_code \
        == 200


def test_ws_session_quota_per_token_closes_with_4429_and_frees_on_close(ws_url, protected):
    access = protected[1].state.server.access

    async def go():
        first, ws = await welcomed(ws_url, additional_headers=bearer(QUOTA))
        assert first.type == "welcome"
        msgs, code = await refused(ws_url, first=hello(), additional_headers=bearer(QUOTA))
        assert code == CloseCode.OVER_QUOTA == 4429
        assert [(m.type, m.code) for m in msgs] == [("error", "over_quota")]
        # Another token is not affected.
        other, ws2 = await welcomed(ws_url, additional_headers=bearer(TINY_ONLY))
        assert other.type == "welcome"
        await ws2.close()
        await ws.close()

    run(go())
    grant = access.book.lookup(QUOTA)
    wait_for(lambda: access.quotas.sessions(grant) == 0)

    async def again():
        first, ws = await welcomed(ws_url, additional_headers=bearer(QUOTA))
        await ws.close()
        return first

    assert run(again()).type == "welcome"
    wait_for(lambda: access.quotas.sessions(grant) == 0)


def test_concurrent_sessions_never_pass_the_quota(ws_url, protected):
    """Ten handshakes at once for a token with one place: exactly one is welcomed."""
    access = protected[1].state.server.access
    grant = access.book.lookup(QUOTA)
    wait_for(lambda: access.quotas.sessions(grant) == 0)

    async def go():
        async def one():
            try:
                return await welcomed(ws_url, additional_headers=bearer(QUOTA))
            except websockets.ConnectionClosed:
                return None, None

        got = await asyncio.gather(*[one() for _ in range(10)])
        kinds = sorted(m.type if m is not None else "closed" for m, _ in got)
        for _, ws in got:
            if ws is not None:
                await ws.close()
        return kinds

    kinds = run(go())
    wait_for(lambda: access.quotas.sessions(grant) == 0)
    assert kinds.count("welcome") == 1 and kinds.count("error") + kinds.count("closed") == 9


# --------------------------------------------------------------------------- tokens' sources
def test_tokens_from_a_toml_file_and_the_environment(settings, registered_test_cores, tmp_path):
    toml = tmp_path / "tokens.toml"
    toml.write_text(f'[tokens.{TINY_ONLY}]\nname = "from-toml"\nscenes = ["tiny"]\n')
    env = {"PVS_TOKENS": f" {ALL} , other-env-token-0123456789 ", "PVS_TOKENS_FILE": str(toml),
           "PVS_CORS_ORIGINS": "https://A.example.org:443/, http://b.example:8080"}
    base = settings.model_dump(exclude={"tokens", "tokens_file", "cors_origins"})
    s = Settings.from_env(env, **base)
    assert s.cors_origins == ["https://a.example.org", "http://b.example:8080"]
    assert ALL not in repr(s) and ALL not in str(s.model_dump())
    with serving(s, scenes={"tiny": make_tiny_scene(), "tiny2": make_tiny_scene()}) as (u, _):
        for token, scenes in [(ALL, {"tiny", "tiny2"}), ("other-env-token-0123456789",
                                                          {"tiny", "tiny2"}),
                              (TINY_ONLY, {"tiny"})]:
            r = httpx.get(u + "/scenes", headers=bearer(token), timeout=TIMEOUT)
            assert r.status_code == 200
            assert {x["name"] for x in r.json()["scenes"]} & {"tiny", "tiny2"} == scenes
        assert httpx.get(u + "/scenes", headers=bearer(QUOTA)).status_code == 401
    # The command line: flags over the environment.
    args = pvs_cli.build_parser().parse_args(
        ["serve", "--tokens-file", str(toml), "--cors-origin", "https://c.example",
         "--cors-origin", "*"])
    s = pvs_cli.serve_settings(args, {"PVS_CORS_ORIGINS": "https://ignored.example"})
    assert s.tokens_file == toml and s.cors_origins == ["https://c.example", "*"]


@pytest.mark.parametrize("content, why", [
    ('{"tokens": {}}', "no tokens"),
    ('{"tokens": {"short": {}}}', "a token must match"),
    ('{"tokens": {"SECRET-token-0123456789": {"scenes": "tiny"}}}', "scenes"),
    ('{"tokens": {"SECRET-token-0123456789": {"max_sessions": -1}}}', "max_sessions"),
    ('{"tokens": {"SECRET-token-0123456789": {"pvs_per_minute": 1e9}}}', "pvs_per_minute"),
    ('{"tokens": {"SECRET-token-0123456789": {"nmae": "typo"}}}', "nmae"),
    ('{"tokens": {"SECRET-token-0123456789": {}}, "more": 1}', "one table"),
    ('{"tokens": {"SECRET-token-0123456789": {}', "not JSON"),
])
def test_bad_tokens_files_are_refused_without_quoting_a_token(tmp_path, content, why):
    path = tmp_path / "tokens.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=why) as exc:
        read_tokens_file(path)
    assert "SECRET" not in str(exc.value) and "short" not in str(exc.value).split(":")[-1]
    with pytest.raises(ValueError, match=why) as exc:  # pvs serve fails at start-up
        Settings(tokens_file=path)
    assert "SECRET" not in str(exc.value)


def test_bad_environment_tokens_and_origins_are_refused(tmp_path):
    with pytest.raises(ValueError, match="PVS_TOKENS #2") as exc:
        Settings.from_env({"PVS_TOKENS": f"{ALL},SECRET!"})
    assert "SECRET" not in str(exc.value)
    with pytest.raises(ValueError, match="CORS origin"):
        Settings(cors_origins=["https://a.example/path"])
    with pytest.raises(ValueError, match="CORS origin"):
        Settings(cors_origins=["ftp://a.example"])
    path = tmp_path / "t.json"
    path.write_text(json.dumps({"tokens": {ALL: {"name": "again"}}}))
    from server.app import create_app

    with pytest.raises(ValueError, match="repeats the token") as exc:
        create_app(Settings(tokens=[ALL], tokens_file=path, generated={}))
    assert ALL not in str(exc.value)


def test_tokens_never_reach_the_logs(url, ws_url, caplog):
    """The server's own loggers, uvicorn's (access lines included) and its WebSocket
    library's, at DEBUG, while tokens good and bad come by header and subprotocol."""
    for name in ("", "uvicorn", "uvicorn.error", "uvicorn.access", "websockets.server"):
        caplog.set_level(logging.DEBUG, logger=name)
    for token in (ALL, ALL + "x", TINY_ONLY):
        httpx.get(url + "/scenes/nope", headers=bearer(token), timeout=TIMEOUT)
        # Every session ends at its hello: 4004 (ALL), 4401 (not a token), 4403 (TINY_ONLY).
        run(refused(ws_url, first=hello("nope"), additional_headers=bearer(token)))
        run(refused(ws_url, first=hello("nope"), subprotocols=token_subprotocols(token)))
    # The test's own clients log what they send; only the server's side counts here.
    lines = "\n".join(r.getMessage() for r in caplog.records
                      if not r.name.startswith(("websockets.client", "httpx", "httpcore")))
    assert "unauthorized" in lines and "forbidden" in lines  # the refusals are logged
    assert "GET /scenes/nope" in lines and "WebSocket /ws" in lines  # so are the requests
    for token in (ALL, TINY_ONLY):
        assert token not in lines


# --------------------------------------------------------------------------- the client
def test_pvs_walk_and_query_with_a_token(url, tmp_path, capsys, monkeypatch):
    walk = ["walk", "--server", url, "--scene", "rooms", "--core", "test_near", "--param",
            "radius=4", "--duration", "1", "--width", "32", "--height", "32", "--no-realtime",
            "--quiet"]
    monkeypatch.delenv("PVS_TOKEN", raising=False)
    with pytest.raises(SystemExit, match="unauthorized"):
        pvs_cli.main([*walk, "--out", str(tmp_path / "refused")])
    assert pvs_cli.main([*walk, "--token", ALL, "--out", str(tmp_path / "walk")]) == 0
    summary = json.loads((tmp_path / "walk" / "summary.json").read_text())
    assert len(summary["frames"]) >= 5 and ALL not in json.dumps(summary)
    capsys.readouterr()
    monkeypatch.setenv("PVS_TOKEN", TINY_ONLY)
    assert pvs_cli.main(["query", "--server", url, "--scene", "tiny", "--cell", "0", "--core",
                         "test_near"]) == 0
    assert json.loads(capsys.readouterr().out)["cell"] == 0
    assert pvs_cli.main(["query", "--server", url, "--scene", "tiny2", "--cell", "0"]) == 1
    assert "forbidden" in capsys.readouterr().err
