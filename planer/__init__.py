"""smart-planer: cuttermark measurement and closed-loop control of a planing machine."""

__version__ = "0.1.0"
