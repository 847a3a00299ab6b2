"""Adding a provisioned camera to a tracker config TOML (contracts §4), keeping the rest.

The file is edited as text so that comments, order and formatting survive: a new camera is
appended as a ``[[cameras]]`` table; an existing one (same ``name``) gets its ``url`` line
replaced. The result is parsed again and compared with the original document; only if that
check fails is the document rewritten whole (which loses comments, and is logged).
"""

from __future__ import annotations

import json
import logging
import re
import tomllib
from pathlib import Path

from cubecam.errors import CubecamError
from cubetrack.io.config import write_toml

log = logging.getLogger(__name__)

_TABLE_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\"' -]+?)\s*\]\]?\s*(#.*)?$")
_URL_LINE = re.compile(r"^(\s*)url\s*=")
_NAME_LINE = re.compile(r"^\s*name\s*=")


def _toml_string(value: str) -> str:
    return json.dumps(value, ensure_ascii=False)  # a JSON string is a valid TOML basic string


def _load(text: str, path: Path) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CubecamError(f"{path}: not valid TOML ({exc}); fix it or choose another --config") from None


def set_camera(path: str | Path, name: str, url: str) -> str:
    """Add or update camera ``name`` with ``url``; returns "added", "updated" or "unchanged"."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8") if path.exists() else ""
    except OSError as exc:
        raise CubecamError(f"{path}: cannot read the tracker config ({exc.strerror or exc})") from None
    doc = _load(text, path)
    cameras = doc.get("cameras", [])
    if not isinstance(cameras, list) or not all(isinstance(c, dict) for c in cameras):
        raise CubecamError(f"{path}: 'cameras' must be [[cameras]] tables with name and url")
    index = next((i for i, c in enumerate(cameras) if c.get("name") == name), None)
    if index is not None and cameras[index].get("url") == url:
        return "unchanged"
    expected = json.loads(json.dumps(doc, default=str))
    if index is None:
        expected.setdefault("cameras", []).append({"name": name, "url": url})
        sep = "" if not text or text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")
        new_text: str | None = text + sep + f"[[cameras]]\nname = {_toml_string(name)}\nurl = {_toml_string(url)}\n"
        outcome = "added"
    else:
        expected["cameras"][index]["url"] = url
        new_text = _replace_url(text, index, url)
        outcome = "updated"
    try:
        ok = new_text is not None and json.loads(json.dumps(tomllib.loads(new_text), default=str)) == expected
    except tomllib.TOMLDecodeError:
        ok = False
    try:
        if ok and new_text is not None:  # (ok: it is)
            tmp = path.with_name(path.name + ".part")
            tmp.write_text(new_text, encoding="utf-8")
            tmp.replace(path)
        else:
            log.warning("%s: could not edit in place; rewriting the whole file (comments are lost)", path)
            doc_new = _load(text, path)
            if index is None:
                doc_new.setdefault("cameras", []).append({"name": name, "url": url})
            else:
                doc_new["cameras"][index]["url"] = url
            write_toml(doc_new, path)
    except OSError as exc:
        raise CubecamError(f"{path}: cannot write the tracker config ({exc.strerror or exc})") from None
    return outcome


def _replace_url(text: str, index: int, url: str) -> str | None:
    """Replace (or add) the url line of the index-th [[cameras]] table; None when not found."""
    lines = text.splitlines(keepends=True)
    seen = -1
    inside = False
    name_at = None
    for i, line in enumerate(lines):
        m = _TABLE_HEADER.match(line)
        if m:
            if inside:
                break
            if line.strip().startswith("[[") and m.group(1).strip() == "cameras":
                seen += 1
                inside = seen == index
            continue
        if not inside:
            continue
        um = _URL_LINE.match(line)
        if um:
            lines[i] = f"{um.group(1)}url = {_toml_string(url)}\n"
            return "".join(lines)
        if _NAME_LINE.match(line):
            name_at = i
    if name_at is None:
        return None
    lines.insert(name_at + 1, f"url = {_toml_string(url)}\n")
    return "".join(lines)
