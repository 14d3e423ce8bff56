"""``/api/docs``: Swagger UI served from the package's static files, so it works offline.

FastAPI's built-in page loads Swagger UI from a CDN and starts it with an inline script;
this page loads ``static/swagger-ui/`` (the ``swagger-ui-dist`` npm package, with its
licence) and starts it from ``init.js``, so the page's content security policy needs no
external host and no inline script.
"""

from __future__ import annotations

from html import escape

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

from semantic3d.server.web import state_of

API_DOCS_PATH = "/api/docs"
OPENAPI_PATH = "/api/openapi.json"
SWAGGER_UI_DIR = "/static/swagger-ui"

router = APIRouter(include_in_schema=False)

_PAGE = """<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <title>{title} · API</title>
  <link rel="icon" type="image/png" href="{assets}/favicon-32x32.png">
  <link rel="stylesheet" href="{assets}/swagger-ui.css">
</head>
<body>
<div id="swagger-ui" data-openapi-url="{openapi}"></div>
<script src="{assets}/swagger-ui-bundle.js"></script>
<script src="{assets}/init.js"></script>
</body>
</html>
"""


@router.get(API_DOCS_PATH)
def api_docs(request: Request) -> HTMLResponse:
    """The interactive API description (Swagger UI, served locally)."""
    title = escape(state_of(request).settings.site_title)
    return HTMLResponse(_PAGE.format(title=title, assets=SWAGGER_UI_DIR, openapi=OPENAPI_PATH))
