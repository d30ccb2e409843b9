"""The ground: errors, entry-point checks, units and file helpers that every layer uses.

Nothing here imports from another package of the project.
"""
