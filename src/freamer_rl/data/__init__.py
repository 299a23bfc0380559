"""Datasets used by the FreamerV1 domains (PAMAP2 wearable sensors for the health application, paper Section 5)."""

from freamer_rl.data import pamap2
from freamer_rl.data.pamap2 import *  # noqa: F403  (the public names of pamap2, listed once in its __all__)

__all__ = list(pamap2.__all__)
