"""The operator and quality web pages (``planer serve --http``, ``planer hil --http``).

``live.py`` (pure view of the service for the operator page), ``quality.py`` (boards of a
quality log for the quality page), ``app.py`` (the Starlette app), ``server.py`` (uvicorn on
its own thread), ``compose.py`` (the ``serving`` context manager the commands use),
``static/`` (the pages, their scripts, styles and plotting code). See ``docs/web.md``.
"""
