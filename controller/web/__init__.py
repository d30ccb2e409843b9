"""The operator and quality web pages (``planer serve --http``, ``planer hil --http``).

``live.py`` (pure view of the service for the operator page), ``quality.py`` (boards of a
quality log for the quality page), ``app.py`` (the Starlette app: Host allow-list, event-stream
cap), ``server.py`` (uvicorn on its own thread, bounded), ``compose.py`` (``listen_for``),
``static/`` (the pages, their scripts, styles and plotting code). The commands serve them in
the servers' process (:mod:`controller.edge`). See ``docs/web.md``.
"""
