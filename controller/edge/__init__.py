"""The servers at the edge of the service, in a process of their own (docs/web.md, "Limits").

``compose.py`` (:func:`~controller.edge.compose.serving`, the one context manager the commands
use), ``feed.py`` (the bounded hand-off from the service's loop), ``process.py`` (the servers'
process: OPC UA and the web pages), ``limits.py`` (connections, timeouts, descriptors, log
lines).
"""
