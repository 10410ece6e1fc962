"""The DBC: the single source of truth for every frame on the bess-ded bus."""

from pathlib import Path

DBC_PATH = Path(__file__).with_name("bess_ded.dbc")
FD_DBC_PATH = Path(__file__).with_name("bess_ded_fd.dbc")
"""The same frames as CAN FD frames with the bit-rate switch (tools/gen_dbc.py): the DBC of
a CAN FD bus (``--fd``, ``[bus] fd = true``)."""


def dbc_path(fd: bool = False) -> Path:
    """The DBC of a classic (default) or a CAN FD bus."""
    return FD_DBC_PATH if fd else DBC_PATH
