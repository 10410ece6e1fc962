"""The DBC: the single source of truth for every frame on the bess-ded bus."""

from pathlib import Path

DBC_PATH = Path(__file__).with_name("bess_ded.dbc")
