"""bridgeOS robot agent: the Robot Controller, Skill Managers and Skill Routers."""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
