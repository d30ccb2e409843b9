"""Sub-commands of the ``planer`` command line."""
