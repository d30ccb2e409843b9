"""Configuration: TOML files loaded into frozen, validated dataclasses.

The TOML files shipped with the product live beside this module (``rig.toml``, ``sim.toml``,
``machine.toml``, ``registers.toml``, ``piezo_amp.eds``); :func:`default_path` finds them when the
package is installed. Loaders raise :class:`core.errors.ConfigError` naming the bad key.
"""

from __future__ import annotations

from config.loading import Section, default_path, load_toml

__all__ = ["Section", "default_path", "load_toml"]
