"""HTTP/WebSocket interface and live web view of beehave robots (FastAPI + uvicorn).

::

    from beehave.interfaces.http import serve

    server = serve(robot.plane)          # 127.0.0.1, a free port
    print(server.url)                    # open it in a browser
    ...
    server.stop()

REST under ``/api`` (OpenAPI schema at ``/openapi.json``), a coalesced WebSocket stream
at ``/api/ws``, the web view at ``/``. See ``docs/http.md``. Needs the ``http`` extra
(fastapi, uvicorn).
"""

from beehave.interfaces.http.app import STATUS_OF, Auth, SwitchRequest, create_app
from beehave.interfaces.http.server import (
    TOKEN_ENV,
    HttpServer,
    is_loopback,
    parse_address,
    serve,
)

__all__ = ["STATUS_OF", "TOKEN_ENV", "Auth", "HttpServer", "SwitchRequest", "create_app",
           "is_loopback", "parse_address", "serve"]
