"""The browser viewer's files: ``/viewer/`` serves the page and its ES modules (``server/viewer/``,
installed with the package), ``/viewer/vendor/`` three.js's build folder from the project's npm
install (``node_modules/three/build``, or ``settings.viewer_three_dir``). Nothing of three.js is
in the repository; without the npm install the page says how to get it.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import quote

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, RedirectResponse
from starlette.staticfiles import StaticFiles

from server.errors import error_body
from server.settings import Settings

#: The page and its modules.
VIEWER_DIR = Path(__file__).with_name("viewer")
#: three.js's build folder as ``npm ci`` in the repository leaves it.
REPO_THREE_DIR = Path(__file__).resolve().parents[1] / "node_modules" / "three" / "build"
#: The module the page's import map names.
THREE_MODULE = "three.module.js"


def three_dir(settings: Settings) -> Path | None:
    """The folder holding ``three.module.js`` (and the files it imports): the setting when
    given, else the repository's ``node_modules``; None when neither has it."""
    for folder in (settings.viewer_three_dir, REPO_THREE_DIR):
        if folder is not None and (Path(folder) / THREE_MODULE).is_file():
            return Path(folder)
    return None


def viewer_url(base: str, scene: str | None = None, core: str | None = None) -> str:
    """The viewer's URL on the server at ``base`` (``http://host:port``), opening ``scene``
    with ``core`` when given."""
    query = "&".join(f"{k}={quote(v)}" for k, v in (("scene", scene), ("core", core)) if v)
    return f"{base.rstrip('/')}/viewer/" + (f"?{query}" if query else "")


def install_viewer(app: FastAPI, settings: Settings) -> None:
    """Serve the viewer at ``/viewer/`` (``/viewer`` redirects there, keeping the query)."""

    @app.get("/viewer", include_in_schema=False)
    async def viewer_root(request: Request) -> RedirectResponse:
        query = request.url.query
        return RedirectResponse("/viewer/" + (f"?{query}" if query else ""), status_code=307)

    vendor = three_dir(settings)
    if vendor is not None:
        app.mount("/viewer/vendor", StaticFiles(directory=vendor), name="viewer-vendor")
    else:

        @app.get("/viewer/vendor/{path:path}", include_in_schema=False)
        async def no_three(path: str) -> JSONResponse:
            return JSONResponse(error_body(
                "not_found", "three.js is not installed: run `npm ci` in the repository "
                "(scripts/setup.sh does), or set PVS_VIEWER_THREE_DIR to its build folder"), 404)

    app.mount("/viewer", StaticFiles(directory=VIEWER_DIR, html=True), name="viewer")
