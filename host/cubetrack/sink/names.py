"""Names that every consumer accepts, whatever a robot or camera is called.

ROS 2 topic tokens and tf frame ids, VRPN sender names (as vrpn_client_ros and vrpn_mocap
require), Zenoh key chunks and Foxglove topics all accept ``[A-Za-z][A-Za-z0-9_]*`` with no
repeated underscore (ROS forbids ``__``). :func:`identifier` maps any text onto that set;
:func:`identifiers` does it for a whole list and keeps the results distinct.
"""

from __future__ import annotations

import re

_INVALID = re.compile(r"[^A-Za-z0-9_]+")
_REPEATED = re.compile(r"_{2,}")
MAX_LENGTH = 64  # well under VRPN's 95-byte sender limit and readable as a topic


def identifier(text: str, fallback: str = "x") -> str:
    """``text`` as ``[A-Za-z][A-Za-z0-9_]*``: other characters become ``_``, repeated and
    trailing underscores are dropped, a leading digit or underscore gets ``fallback + "_"``
    in front (``"3 bots"`` -> ``"x_3_bots"``), empty text becomes ``fallback``."""
    name = _REPEATED.sub("_", _INVALID.sub("_", text)).strip("_")
    if not name:
        return fallback
    if not name[0].isalpha():
        name = f"{fallback}_{name}"
    return name[:MAX_LENGTH].rstrip("_")


def identifiers(texts: list[str] | tuple[str, ...], fallback: str = "x") -> dict[str, str]:
    """Text -> :func:`identifier`, distinct: a clash gets ``_2``, ``_3``... in input order."""
    out: dict[str, str] = {}
    taken: set[str] = set()
    for text in texts:
        base = identifier(text, fallback)
        name, n = base, 1
        while name in taken:
            n += 1
            name = f"{base}_{n}"
        taken.add(name)
        out[text] = name
    return out
