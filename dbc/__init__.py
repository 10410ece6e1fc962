"""The DBC: the single source of truth for every frame on the bess-ded bus."""

from pathlib import Path

DBC_PATH = Path(__file__).with_name("bess_ded.dbc")
FD_DBC_PATH = Path(__file__).with_name("bess_ded_fd.dbc")
"""The same frames as CAN FD frames with the bit-rate switch, λ and its sync with a tag per
receiver (tools/gen_dbc.py, AUTH-34): the DBC of a CAN FD bus (``--fd``, ``[bus] fd =
true``)."""
FD_UNTAGGED_DBC_PATH = Path(__file__).with_name("bess_ded_fd_untagged.dbc")
"""The classic frames as CAN FD frames, every one 8 bytes, λ under its sender's node key:
a CAN FD bus with ``[security] lambda_tags = false`` (``--no-lambda-tags``)."""


def dbc_path(fd: bool = False, lambda_tags: bool = True) -> Path:
    """The DBC of a classic (default) or a CAN FD bus (with λ tags, or without)."""
    if not fd:
        return DBC_PATH
    return FD_DBC_PATH if lambda_tags else FD_UNTAGGED_DBC_PATH
