"""The HTTP transport (FastAPI): a thin adapter over the :class:`~service.engine.Engine`.

- ``app.py``: :func:`~service.http.app.create_app` (routers, static mounts, exception handlers, the OpenAPI
  document), the :class:`~service.http.app.RequestGuard` middleware and the drain's body refusal;
- ``dependencies.py``: what routes take from the request (the engine, the caller, a bounded body);
- ``schemas.py``: the response models;
- routers: ``avatars.py``, ``render.py`` (single frames and the WebSocket stream), ``adapters.py``, ``ops.py``
  (health, readiness, metrics, the docs and the pages). The training jobs' routers are the jobs wing's.
"""
